"""Kitting: stable rest poses and a pick grasp that also serves at the target."""

import numpy as np
import pytest
import trimesh

from planning.assembly import read_assembly
from planning.grasp import feasible_grasps
from planning.kitting import KittingError, plan_kitting, stable_rest_poses
from planning.sequence import GraspChecker
from scenes import sample_folder


def test_a_board_rests_flat_most_often():
    board = trimesh.creation.box([0.3, 0.1, 0.02])
    poses = stable_rest_poses(board)
    rest_from_part, probability = poses[0]
    rested = board.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    assert rested[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert np.ptp(rested[:, 2]) == pytest.approx(0.02)  # lying on its face
    assert probability == max(p for _, p in poses)


def test_chair_parts_get_slots_with_grasps_valid_at_pick():
    assembly = read_assembly(sample_folder("chair"))
    checker = GraspChecker(assembly)
    slots = plan_kitting(assembly.part_names, [p.mesh for p in assembly.parts], checker.candidates,
                         lambda name, grasp: True, np.array([0.0, 0.3]), np.array([1.0, 1.0]), 0.0, 0.12)
    assert [s.part for s in slots] == assembly.part_names
    for slot in slots:
        mesh = assembly.part(slot.part).mesh
        lowest = slot.world_from_part.apply(mesh.vertices)[:, 2].min()
        assert lowest == pytest.approx(0.12, abs=1e-6)  # resting on its pedestal
        again = feasible_grasps([slot.grasp], slot.world_from_part,
                                [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal)], None, floor_z=0.0)
        assert len(again) == 1


def test_no_grasp_at_target_is_named():
    assembly = read_assembly(sample_folder("table"))
    checker = GraspChecker(assembly)
    with pytest.raises(KittingError, match="part 'top'"):
        plan_kitting(assembly.part_names[::-1], [p.mesh for p in assembly.parts][::-1], checker.candidates,
                     lambda name, grasp: name != "top", np.array([0.0, 0.3]), np.array([1.0, 1.0]), 0.0, 0.12)
