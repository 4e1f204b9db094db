"""Normalised part clouds, equivalence classes and the way back to metres."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from perception.dataset.sample import object_sample
from perception.equivalence import equivalence_classes, instance_onehot
from perception.normalize import camera_from_part_metres, normalize_parts
from perception.pointcloud import canonical_frame, chamfer_distance, surface_moments
from planning.assembly import Assembly, AssemblyPart
from planning.pose import Pose


def l_bracket() -> trimesh.Trimesh:
    """An asymmetric part: its PCA frame has a well-defined direction on every axis."""
    a = trimesh.creation.box([0.2, 0.03, 0.02])
    b = trimesh.creation.box([0.03, 0.1, 0.02])
    b.apply_translation([0.085, 0.065, 0])
    return trimesh.util.concatenate([a, b])


def test_surface_moments_of_a_box():
    box = trimesh.creation.box([0.4, 0.2, 0.1])
    box.apply_translation([1.0, 2.0, 3.0])
    centroid, covariance = surface_moments(box)
    np.testing.assert_allclose(centroid, [1, 2, 3], atol=1e-12)
    points, _ = trimesh.sample.sample_surface(box, 200000, seed=0)
    np.testing.assert_allclose(covariance, np.cov(points.T), atol=2e-4)


def test_identical_meshes_get_identical_canonical_clouds_whatever_their_frame():
    mesh = l_bracket()
    moved = mesh.copy()
    moved_from_mesh = Pose([0.3, -0.1, 0.2], Rotation.random(random_state=1).as_quat()[[3, 0, 1, 2]])
    moved.apply_transform(moved_from_mesh.matrix())
    # the canonical frame moves with the mesh: the same canonical frame, exactly
    assert canonical_frame(moved).is_close(moved_from_mesh @ canonical_frame(mesh), 1e-9, 1e-7)
    parts = normalize_parts([mesh, moved])
    # so the clouds coincide up to sampling, without any alignment
    same = chamfer_distance(parts.points_norm[0], parts.points_norm[1])
    flipped = chamfer_distance(parts.points_norm[0] * [-1, -1, 1], parts.points_norm[1])
    assert same < 1e-3 < flipped
    np.testing.assert_allclose(parts.extents_norm[0], parts.extents_norm[1], atol=1e-6)
    # canonical frame maps back onto the mesh
    frame = canonical_frame(moved)
    back = frame.apply(parts.points_norm[1] / parts.scale_per_m)
    assert np.abs(moved.nearest.signed_distance(back[:50])).max() < 1e-6


def test_scale_makes_longest_diagonal_one():
    parts = normalize_parts([trimesh.creation.box([0.3, 0.04, 0.04]), trimesh.creation.box([0.1, 0.1, 0.02])])
    assert np.linalg.norm(parts.extents_norm, axis=1).max() == pytest.approx(1.0)
    assert parts.points_norm.shape == (2, 1000, 3) and parts.points_norm.dtype == np.float32
    assert np.abs(parts.points_norm).max() <= 0.5 + 1e-6


def test_equivalence_classes_and_instance_onehot():
    leg = trimesh.creation.box([0.03, 0.03, 0.3])
    seat = trimesh.creation.box([0.3, 0.3, 0.03])
    short_leg = trimesh.creation.box([0.03, 0.03, 0.18])
    parts = normalize_parts([leg, seat, leg.copy(), short_leg, leg.copy()])
    classes = equivalence_classes(parts.points_norm, parts.extents_norm)
    assert classes.tolist() == [0, 1, 0, 2, 0]
    onehot = instance_onehot(classes)
    assert onehot.shape == (5, 20)
    assert onehot.argmax(axis=1).tolist() == [0, 0, 1, 0, 2]


def test_targets_map_back_to_the_rendered_poses():
    bracket = l_bracket()
    assembly = Assembly("two", [
        AssemblyPart("base", trimesh.creation.box([0.25, 0.2, 0.03]), Pose([0, 0, 0.015], [1, 0, 0, 0])),
        AssemblyPart("bracket", bracket, Pose([0.0, 0.0, 0.04], [np.cos(0.4), 0, 0, np.sin(0.4)])),
    ])
    sample = object_sample(assembly, views=2, rng=np.random.default_rng(0))
    assert sample["images"].shape == (2, 224, 224, 3)
    for k in range(2):
        camera_from_assembly = Pose(sample["camera_from_assembly_position_m"][k],
                                    sample["camera_from_assembly_quat_wxyz"][k])
        for i, part in enumerate(assembly.parts):
            part_from_canonical = Pose(sample["part_from_canonical_position_m"][i],
                                       sample["part_from_canonical_quat_wxyz"][i])
            recovered = camera_from_part_metres(sample["pose_quat_wxyz"][k, i],
                                                sample["pose_translation_norm"][k, i], part_from_canonical,
                                                sample["centre_camera_m"][k], float(sample["scale_per_m"]))
            expected = camera_from_assembly @ part.assembly_from_part
            assert recovered.is_close(expected, atol_position=1e-6, atol_angle_rad=1e-5)
            # the canonical cloud posed by the target lands on the mesh seen from the camera
            cloud_cam = Pose(np.zeros(3), sample["pose_quat_wxyz"][k, i]).apply(sample["points_norm"][i])
            cloud_cam = cloud_cam + sample["pose_translation_norm"][k, i]
            mesh_cam = part.mesh.copy()
            mesh_cam.apply_transform(expected.matrix())
            mesh_cam.apply_translation(-sample["centre_camera_m"][k])
            mesh_cam.apply_scale(float(sample["scale_per_m"]))
            assert np.abs(mesh_cam.nearest.signed_distance(cloud_cam[:100])).max() < 1e-5


def test_classes_match_the_all_pairs_definition_on_a_real_sample():
    import networkx as nx

    from perception.equivalence import CHAMFER_TOLERANCE, EXTENT_TOLERANCE, aligned_chamfer
    from planning.assembly import read_assembly
    from scenes import sample_folder

    assembly = read_assembly(sample_folder("chair"))
    parts = normalize_parts([p.mesh for p in assembly.parts])
    graph = nx.Graph()
    graph.add_nodes_from(range(len(parts)))
    for i in range(len(parts)):
        for j in range(i + 1, len(parts)):
            if np.all(np.abs(parts.extents_norm[i] - parts.extents_norm[j]) < EXTENT_TOLERANCE) and (
                aligned_chamfer(parts.points_norm[i], parts.points_norm[j]) < CHAMFER_TOLERANCE
            ):
                graph.add_edge(i, j)
    expected = {frozenset(c) for c in nx.connected_components(graph)}
    classes = equivalence_classes(parts.points_norm, parts.extents_norm)
    assert {frozenset(np.flatnonzero(classes == c)) for c in np.unique(classes)} == expected
    assert len(expected) < len(parts)  # the chair has interchangeable legs
