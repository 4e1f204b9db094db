"""The picture solver (perception.solver) and the renderer's material modes, on real renders of a procedural table."""

import numpy as np
import pytest

from cell.render import MATERIALS, Appearance, AssemblyRenderer, sample_camera
from perception.agreement import object_mask
from perception.equivalence import equivalence_classes
from perception.normalize import normalize_parts
from perception.solver import SolverSettings, solve
from perception.synth import generate
from planning.collision import ConvexPart
from planning.pose import Pose


@pytest.fixture(scope="module")
def table_view():
    assembly = generate("table", "3", np.random.default_rng([11, 0]), "table")
    rng = np.random.default_rng(5)
    with AssemblyRenderer(assembly) as renderer:
        view = renderer.render(sample_camera(rng, assembly.bounds()), Appearance.sample(rng, len(assembly.parts)))
    return assembly, view


def test_one_material_changes_only_the_parts_colours():
    coloured = Appearance.sample(np.random.default_rng(3), 6, "parts")
    one = Appearance.sample(np.random.default_rng(3), 6, "one")
    few = Appearance.sample(np.random.default_rng(3), 6, "few")
    assert len(np.unique(coloured.part_rgb, axis=0)) == 6
    assert len(np.unique(one.part_rgb, axis=0)) == 1
    assert len(np.unique(few.part_rgb, axis=0)) in (2, 3)
    for other in (one, few):
        np.testing.assert_array_equal(other.background_rgb, coloured.background_rgb)
        np.testing.assert_array_equal(other.light_direction, coloured.light_direction)
    with pytest.raises(ValueError, match="materials must be one of"):
        Appearance.sample(np.random.default_rng(3), 6, "wood")
    assert MATERIALS == ("parts", "one", "few")


def test_the_solver_moves_a_displaced_leg_back_onto_the_picture(table_view):
    assembly, view = table_view
    mask, source = object_mask(view.rgb, None)
    assert source == "plain background"
    convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    normalized = normalize_parts([p.mesh for p in assembly.parts])
    classes = equivalence_classes(normalized.points_norm, normalized.extents_norm)
    truth = [p.assembly_from_part for p in assembly.parts]
    leg = next(k for k, p in enumerate(assembly.parts) if "leg" in p.name)
    extent_m = float(np.max(assembly.bounds()[1] - assembly.bounds()[0]))
    across = view.camera_from_assembly.rotation[0]  # the picture's x axis, assembly frame: a move the picture shows
    displaced = list(truth)
    displaced[leg] = Pose(truth[leg].position + 0.25 * extent_m * across, truth[leg].quat_wxyz)
    result = solve([c.piece_vertices for c in convex], classes, displaced, view.camera_from_assembly, mask,
                   SolverSettings())
    error_before = np.linalg.norm(displaced[leg].position - truth[leg].position)
    error_after = np.linalg.norm(result.assembly_from_part[leg].position - truth[leg].position)
    assert result.iou_after > result.iou_before + 0.02
    assert result.score_after > result.score_before
    assert error_after < 0.35 * error_before
    others = [k for k in range(len(truth)) if k != leg]
    moved_m = [np.linalg.norm(result.assembly_from_part[k].position - truth[k].position) for k in others]
    assert max(moved_m) < 0.1 * extent_m  # the parts where the picture shows them stay there
