"""The Panda's closed-form inverse kinematics (planning.panda_ik), pure numpy."""

import numpy as np

from planning import panda_ik

# the joint limits of pybullet_data's franka_panda/panda.urdf (radians)
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])


def test_each_configuration_is_among_the_solutions_at_its_own_joint_7():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = rng.uniform(LOWER, UPPER)
        solutions = panda_ik.ik_solutions(panda_ik.forward_tcp(q), [q[6]], LOWER, UPPER)
        assert 1 <= len(solutions) <= 8
        assert np.min(np.abs(solutions - q).max(axis=1)) < 1e-6, q


def test_every_solution_reaches_the_pose_within_the_limits():
    rng = np.random.default_rng(1)
    q = rng.uniform(0.5 * LOWER, 0.5 * UPPER)
    target = panda_ik.forward_tcp(q)
    solutions = panda_ik.ik_solutions(target, np.linspace(LOWER[6], UPPER[6], 32), LOWER, UPPER)
    assert len(solutions) >= 8 and len(np.unique(solutions[:, 6])) >= 4  # the arm is redundant: many elbows
    assert np.all((solutions >= LOWER) & (solutions <= UPPER))
    reached = panda_ik.forward_tcp(solutions)
    assert np.abs(reached - target).max() < 1e-9
    assert len(np.unique(np.round(solutions[:, 3], 6))) > 1  # elbow angles differ, not one solution repeated


def test_a_pose_out_of_reach_or_outside_joint_7s_range_has_no_solution():
    far = panda_ik.forward_tcp(np.zeros(7))
    far[:3, 3] = [1.2, 0.0, 0.4]  # past the arm's 0.855 m reach from the shoulder
    assert panda_ik.ik_solutions(far, np.linspace(LOWER[6], UPPER[6], 64), LOWER, UPPER).shape == (0, 7)
    q = np.array([0.2, -0.3, 0.1, -2.0, 0.2, 1.9, 0.5])
    assert len(panda_ik.ik_solutions(panda_ik.forward_tcp(q), [3.1], LOWER, UPPER)) == 0  # joint 7 past its limit


def test_forward_kinematics_takes_a_batch():
    rng = np.random.default_rng(2)
    qs = rng.uniform(LOWER, UPPER, size=(5, 7))
    batch = panda_ik.forward_tcp(qs)
    assert batch.shape == (5, 4, 4)
    assert np.allclose(batch[3], panda_ik.forward_tcp(qs[3]))
    assert np.allclose(batch[:, :3, :3] @ np.swapaxes(batch[:, :3, :3], 1, 2), np.eye(3))
