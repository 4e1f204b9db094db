"""Up direction and the upright assembly frame on hand-made cases whose answers are known."""

import numpy as np
import pytest
import trimesh

from cell.render import CameraSpec
from perception.upright import (
    UpSettings,
    angle_deg,
    dominant_yaw_axis,
    elevation_of,
    estimate_up,
    manhattan_up,
    surface_directions,
    up_from_elevation,
    upright_frame,
)
from planning.pose import Pose


def camera_rotation(azimuth_deg, elevation_deg):
    """camera_from_assembly rotation of a training camera (no roll)."""
    return CameraSpec(azimuth_deg, elevation_deg, 1.0, (0.0, 0.0, 0.0)).camera_from_assembly().rotation


@pytest.mark.parametrize("elevation", [10.0, 27.5, 50.0])
def test_up_of_a_training_camera_is_its_elevation(elevation):
    true_up = camera_rotation(123.0, elevation)[:, 2]
    assert np.allclose(up_from_elevation(elevation), true_up, atol=1e-12)
    assert elevation_of(true_up) == pytest.approx(elevation)


def placed_directions(meshes_and_rotations):
    """Surface directions (camera frame) and weights of meshes turned by the given rotations."""
    directions, weights = [], []
    for mesh, rotation in meshes_and_rotations:
        d, w = surface_directions(mesh)
        directions.append(d @ rotation.T)
        weights.append(w)
    return np.concatenate(directions), np.concatenate(weights)


def test_surface_directions_of_a_box_are_its_three_axes_by_area():
    directions, weights = surface_directions(trimesh.creation.box([0.1, 0.2, 0.4]))
    assert len(directions) == 3 and weights.sum() == pytest.approx(1.0)
    areas = {0: 0.2 * 0.4, 1: 0.1 * 0.4, 2: 0.1 * 0.2}
    for d, w in zip(directions, weights):
        axis = int(np.argmax(np.abs(d)))
        assert np.abs(d[axis]) == pytest.approx(1.0) and w == pytest.approx(areas[axis] / sum(areas.values()))


def test_axis_aligned_parts_give_the_exact_elevation():
    camera = camera_rotation(40.0, 33.0)
    # boards, a leg and a cylinder along the assembly axes, and one tilted part
    parts = [(trimesh.creation.box([0.4, 0.3, 0.02]), camera), (trimesh.creation.box([0.02, 0.02, 0.4]), camera),
             (trimesh.creation.cylinder(0.01, 0.4, sections=24), camera),
             (trimesh.creation.box([0.1, 0.1, 0.1]),
              camera @ trimesh.transformations.rotation_matrix(0.6, [1, 1, 0])[:3, :3])]
    directions, weights = placed_directions(parts)
    elevation, score = manhattan_up(directions, weights, UpSettings())
    assert elevation == pytest.approx(33.0, abs=0.5)  # the broad kernel lets the tilted part pull a little
    assert score > 3.0
    assert manhattan_up(directions, weights, UpSettings(kernel_deg=3.0))[0] == pytest.approx(33.0, abs=0.05)
    points = trimesh.creation.box([0.6, 0.4, 0.8]).vertices @ camera.T
    estimate = estimate_up(directions, weights, points)
    assert angle_deg(estimate.up_camera, camera[:, 2]) < 0.05


def test_a_merged_part_with_tilted_principal_axes_still_votes_right():
    """An L of two boards: its principal axes are tilted, its faces are not."""
    camera = camera_rotation(300.0, 47.0)
    ell = trimesh.util.concatenate([trimesh.creation.box([0.4, 0.3, 0.02]),
                                    trimesh.creation.box([0.02, 0.3, 0.4], transform=trimesh.transformations.
                                                         translation_matrix([0.19, 0.0, 0.2]))])
    directions, weights = placed_directions([(ell, camera)])
    estimate = estimate_up(directions, weights, ell.vertices @ camera.T, UpSettings(snap_deg=0.0))
    assert angle_deg(estimate.up_camera, camera[:, 2]) < 0.05


def test_stable_face_refines_the_surfaces_estimate():
    """A box standing on the floor, seen at 22 degrees, its parts' surfaces 1-2 degrees off: the hull's bottom
    face gives the exact up."""
    camera = camera_rotation(200.0, 22.0)
    box = trimesh.creation.box([0.4, 0.3, 0.5])
    directions, weights = placed_directions(
        [(box, camera @ trimesh.transformations.rotation_matrix(a, [1, 0, 0])[:3, :3]) for a in (0.03, -0.02, 0.035)])
    estimate = estimate_up(directions, weights, box.vertices @ camera.T)
    assert estimate.method == "stable"
    assert angle_deg(estimate.up_camera, camera[:, 2]) < 1e-6
    assert abs(estimate.surfaces_elevation_deg - 22.0) > 0.1


def test_no_structure_falls_back_to_the_prior():
    # every direction at 45 degrees from parallel and perpendicular to all admissible ups: nothing votes
    directions = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]) / np.sqrt(2.0)
    directions = directions @ trimesh.transformations.rotation_matrix(np.radians(30), [1, 0, 0])[:3, :3].T
    estimate = estimate_up(directions, np.ones(2), np.zeros((4, 3)), settings=UpSettings(kernel_deg=0.5))
    assert estimate.method == "prior" and estimate.elevation_deg == pytest.approx(30.0)


def test_yaw_axis_is_the_quarter_turn_nearest_the_camera():
    camera = camera_rotation(70.0, 30.0)  # camera on the side of azimuth 70: +y is the nearest axis to it
    directions, weights = placed_directions([(trimesh.creation.box([0.4, 0.3, 0.2]), camera)])
    x = dominant_yaw_axis(directions, weights, camera[:, 2])
    assert np.allclose(x, camera[:, 1], atol=1e-3)


def test_upright_frame_puts_the_lowest_point_on_the_floor_at_the_footprint_centre():
    camera = camera_rotation(10.0, 40.0)
    assembly_points = np.array([[0.1, 0.2, 0.05], [0.5, 0.2, 0.05], [0.1, 0.6, 0.05], [0.5, 0.6, 0.9]])
    camera_from_true = Pose.from_rotation(camera, np.array([0.0, 0.0, 2.0]))
    points_camera = camera_from_true.apply(assembly_points)
    camera_from_assembly = upright_frame(points_camera, camera[:, 2], camera[:, 0])
    local = camera_from_assembly.inverse().apply(points_camera)
    assert local[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(0.5 * (local.min(0) + local.max(0))[:2], 0.0, atol=1e-12)
    assert np.allclose(local - local[0], assembly_points - assembly_points[0], atol=1e-12)  # no rotation left


def test_the_elevation_read_from_the_picture_sets_up():
    """Given the picture's elevation, up is that no-roll direction whatever the parts say; the surfaces' own
    estimate is still reported."""
    camera = camera_rotation(200.0, 22.0)
    box = trimesh.creation.box([0.4, 0.3, 0.5])
    directions, weights = placed_directions([(box, camera)])
    estimate = estimate_up(directions, weights, box.vertices @ camera.T, image_elevation_deg=31.0)
    assert estimate.method == "image" and estimate.elevation_deg == pytest.approx(31.0)
    assert angle_deg(estimate.up_camera, up_from_elevation(31.0)) < 1e-9
    assert estimate.surfaces_elevation_deg == pytest.approx(22.0, abs=0.1)
