"""Up direction and the upright assembly frame on hand-made cases whose answers are known."""

import numpy as np
import pytest
import trimesh

from cell.render import CameraSpec
from perception.upright import (
    UpSettings,
    angle_deg,
    axes_up,
    dominant_yaw_axis,
    elevation_of,
    estimate_up,
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


def test_axis_aligned_parts_give_the_exact_elevation():
    camera = camera_rotation(40.0, 33.0)
    # parts whose axes are the assembly axes permuted, plus one tilted part that must not matter
    perms = [np.eye(3), np.eye(3)[[1, 2, 0]].T, np.eye(3)[[2, 0, 1]].T]
    tilted = trimesh.transformations.rotation_matrix(0.6, [1, 1, 0])[:3, :3]
    rotations = np.stack([camera @ perms[i % 3] for i in range(6)] + [camera @ tilted])
    elevation, score = axes_up(rotations, settings=UpSettings())
    assert elevation == pytest.approx(33.0, abs=0.25)
    assert score > 5.5
    points = trimesh.creation.box([0.6, 0.4, 0.8]).vertices @ camera.T
    estimate = estimate_up(rotations, points)
    assert angle_deg(estimate.up_camera, camera[:, 2]) < 0.3


def test_stable_face_refines_the_axes_estimate():
    """A box standing on the floor, seen at 22 degrees: the hull's bottom face gives the exact up."""
    camera = camera_rotation(200.0, 22.0)
    box = trimesh.creation.box([0.4, 0.3, 0.5])
    points = box.vertices @ camera.T
    noisy_axes = np.stack([camera @ trimesh.transformations.rotation_matrix(a, [1, 0, 0])[:3, :3]
                           for a in (0.05, -0.04, 0.06)])
    estimate = estimate_up(noisy_axes, points)
    assert estimate.method == "stable"
    assert angle_deg(estimate.up_camera, camera[:, 2]) < 1e-6


def test_no_structure_falls_back_to_the_prior():
    # no axis within several kernel widths of any admissible up direction: nothing votes, mid elevation
    rotation = trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1])[:3, :3]
    rotation = trimesh.transformations.rotation_matrix(np.pi / 4, [1, 0, 0])[:3, :3] @ rotation
    estimate = estimate_up(rotation[None], np.zeros((4, 3)), settings=UpSettings(kernel_deg=0.5))
    assert estimate.method == "prior" and estimate.elevation_deg == pytest.approx(30.0)


def test_yaw_axis_is_the_quarter_turn_nearest_the_camera():
    camera = camera_rotation(70.0, 30.0)  # camera on the side of azimuth 70: +y is the nearest axis to it
    up = camera[:, 2]
    x = dominant_yaw_axis(camera[None], up)
    assert np.allclose(x, camera[:, 1], atol=1e-2)


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
