"""Pose algebra and its conversions at the PyBullet, FCL and scipy edges."""

import fcl
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.bullet import import_pybullet
from planning.pose import Pose, matrix_to_quat, quat_angle_rad, quat_to_matrix

pb = import_pybullet()


def random_poses(count, seed=0):
    rng = np.random.default_rng(seed)
    rotations = Rotation.random(count, random_state=seed)
    return [Pose(rng.normal(size=3), r.as_quat()[[3, 0, 1, 2]]) for r in rotations]


def test_quaternion_matches_scipy():
    for pose in random_poses(50):
        expected = Rotation.from_quat(pose.quat_wxyz[[1, 2, 3, 0]]).as_matrix()  # scipy: x first
        np.testing.assert_allclose(pose.rotation, expected, atol=1e-12)
        np.testing.assert_allclose(matrix_to_quat(expected), pose.quat_wxyz, atol=1e-12)


def test_matrix_round_trip_covers_every_branch():
    # rotations by pi about each axis hit the non-trace branches of Shepperd's method
    for axis in np.eye(3):
        q = np.array([0.0, *axis])
        np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)
    for pose in random_poses(50, seed=1):
        assert Pose.from_matrix(pose.matrix()).is_close(pose)


def test_compose_inverse_apply():
    a, b = random_poses(2, seed=2)
    points = np.random.default_rng(3).normal(size=(10, 3))
    np.testing.assert_allclose((a @ b).apply(points), a.apply(b.apply(points)), atol=1e-12)
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    assert (a @ a.inverse()).is_close(Pose.identity(), atol_position=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(points)), points, atol=1e-12)


def test_distance():
    a = Pose([0, 0, 0], [1, 0, 0, 0])
    b = Pose([3, 4, 0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90 degrees about z
    dp, da = a.distance(b)
    assert dp == pytest.approx(5.0)
    assert da == pytest.approx(np.pi / 2)
    # q and -q are the same rotation
    assert quat_angle_rad(b.quat_wxyz, -b.quat_wxyz) == pytest.approx(0.0, abs=1e-7)


def test_pybullet_round_trip():
    a, b = random_poses(2, seed=4)
    pos, orn = pb.multiplyTransforms(*a.to_pybullet(), *b.to_pybullet())
    assert Pose.from_pybullet(pos, orn).is_close(a @ b, atol_position=1e-6, atol_angle_rad=1e-6)
    pos, orn = pb.invertTransform(*a.to_pybullet())
    assert Pose.from_pybullet(pos, orn).is_close(a.inverse(), atol_position=1e-6, atol_angle_rad=1e-6)
    matrix = np.array(pb.getMatrixFromQuaternion(a.to_pybullet()[1])).reshape(3, 3)
    np.testing.assert_allclose(matrix, a.rotation, atol=1e-9)


def test_fcl_round_trip():
    pose = random_poses(1, seed=5)[0]
    transform = pose.to_fcl()
    np.testing.assert_allclose(transform.getRotation(), pose.rotation, atol=1e-12)
    assert Pose.from_fcl(transform).is_close(pose)
    # a unit box moved by the pose: FCL sees it where the pose says
    box = fcl.CollisionObject(fcl.Box(0.1, 0.1, 0.1), transform)
    probe = fcl.CollisionObject(fcl.Sphere(0.01), fcl.Transform(pose.apply([0.0, 0.0, 0.0])))
    assert fcl.collide(box, probe, fcl.CollisionRequest())
    far = fcl.CollisionObject(fcl.Sphere(0.01), fcl.Transform(pose.apply([0.0, 0.0, 0.2])))
    assert not fcl.collide(box, far, fcl.CollisionRequest())


def test_invalid_input_is_named():
    with pytest.raises(ValueError, match="cannot be normalised"):
        Pose([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="not finite"):
        Pose([np.nan, 0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError, match="norm 2"):
        Pose.from_checked_quat([0, 0, 0], [2, 0, 0, 0])
    with pytest.raises(ValueError, match="proper rotation"):
        Pose.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))
