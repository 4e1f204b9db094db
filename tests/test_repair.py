"""Pose repair: interpenetration removed, near-contacts closed, faces aligned, moves bounded."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planning.assembly import read_assembly
from planning.collision import ConvexPart
from planning.contact import contact_graph
from planning.pose import Pose
from planning.repair import RepairSettings, repair_poses, snap_rotation_to_axes
from scenes import sample_folder


def perturbed(truth, seed, position_sigma_m=0.004, angle_sigma_deg=2.0):
    rng = np.random.default_rng(seed)
    out = []
    for pose in truth:
        rotation = Rotation.from_rotvec(rng.normal(size=3) * np.radians(angle_sigma_deg)).as_matrix()
        out.append(Pose.from_rotation(rotation @ pose.rotation, pose.position + rng.normal(size=3) * position_sigma_m))
    return out


def edges(graph):
    return {frozenset(e) for e in graph.edges}


@pytest.mark.parametrize("category", ["chair", "table", "cabinet"])
def test_repair_restores_contacts_and_removes_penetration(category):
    assembly = read_assembly(sample_folder(category))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    truth = [p.assembly_from_part for p in assembly.parts]
    noisy = perturbed(truth, seed=1)
    settings = RepairSettings()
    repaired, report = repair_poses(parts, noisy, settings)
    assert report.deepest_penetration_before_m > 0.002
    assert report.deepest_penetration_after_m <= 0.001
    assert max(report.translation_m.values()) <= settings.max_translation_m + 1e-9
    assert max(report.rotation_deg.values()) <= settings.max_rotation_deg + 1e-6
    # the generator builds along the axes: aligned faces come back exactly
    for pose, true_pose in zip(repaired, truth):
        assert np.degrees(pose.distance(true_pose)[1]) < 1e-6
    # the contacts of the true assembly are there again
    assert edges(contact_graph(parts, truth)) <= edges(contact_graph(parts, repaired))


def test_moves_are_bounded():
    assembly = read_assembly(sample_folder("table"))
    parts = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
    poses = [p.assembly_from_part for p in assembly.parts]
    top = assembly.part_names.index("top")
    poses[top] = Pose(poses[top].position - [0, 0, 0.05], poses[top].quat_wxyz)  # sunk 5 cm into the legs
    settings = RepairSettings(max_translation_m=0.02)
    repaired, report = repair_poses(parts, poses, settings)
    assert repaired[top].position[2] > poses[top].position[2] + 0.01  # pushed up out of the legs
    assert all(v <= 0.02 + 1e-9 for v in report.translation_m.values())
    assert max(report.translation_m.values()) == pytest.approx(0.02, abs=1e-6)  # the bound was needed


def test_snap_rotation():
    small = Rotation.from_rotvec([0.02, -0.03, 0.05]).as_matrix()
    np.testing.assert_array_equal(snap_rotation_to_axes(small, 8.0), np.eye(3))
    turned = Rotation.from_rotvec([0, 0, np.pi / 2 + 0.05]).as_matrix()
    np.testing.assert_allclose(snap_rotation_to_axes(turned, 8.0), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    tilted = Rotation.from_rotvec([0, 0.3, 0]).as_matrix()  # 17 degrees: left alone
    np.testing.assert_array_equal(snap_rotation_to_axes(tilted, 8.0), tilted)
