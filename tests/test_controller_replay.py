"""The joint trajectory controller's playback of exported points (planning/controller_replay.py): its splines as
ros2_control writes them, the points chosen so that the playback keeps to the timed motion, and the limit check."""

import numpy as np
import pytest

from planning.controller_replay import (
    POSITION_TOLERANCE_RAD,
    ControllerTrajectory,
    first_violation,
    replay,
    select_points,
    spline_coefficients,
)
from planning.timing import JointLimits, time_path

# Franka's published limits, written out here on purpose (not imported from the code under test)
VELOCITY = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
ACCELERATION = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])
JERK = np.array([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0])
LOWER = np.full(7, -2.8)
UPPER = np.full(7, 3.7)
HOME = np.array([0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785])


def polynomial(coefficients, t):
    """Position, velocity, acceleration of sum c_k t^k (coefficients (6, dof))."""
    powers = np.arange(6)
    q = sum(coefficients[k] * t ** k for k in powers)
    qd = sum(k * coefficients[k] * t ** (k - 1) for k in powers[1:])
    qdd = sum(k * (k - 1) * coefficients[k] * t ** (k - 2) for k in powers[2:])
    return q, qd, qdd


def test_the_quintic_matches_both_points_and_reproduces_a_quintic():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(6, 3))
    T = 0.037
    start, end = polynomial(truth, 0.0), polynomial(truth, T)
    np.testing.assert_allclose(spline_coefficients(T, start, end), truth, rtol=1e-7, atol=1e-9)
    # positions and velocities only: the JTC's cubic, matching both ends
    cubic = spline_coefficients(T, start[:2], end[:2])
    assert np.all(cubic[4:] == 0.0)
    np.testing.assert_allclose(polynomial(cubic, T)[:2], end[:2], rtol=1e-9, atol=1e-9)
    # positions only: a straight line
    line = spline_coefficients(T, start[:1], end[:1])
    np.testing.assert_allclose(line[1], (end[0] - start[0]) / T)


def test_between_points_the_playback_is_the_spline_and_after_the_last_it_holds():
    times = np.array([0.0, 0.01, 0.03])
    positions = np.array([[0.0], [0.01], [0.05]])
    velocities = np.array([[0.0], [1.5], [0.0]])
    accelerations = np.array([[0.0], [10.0], [0.0]])
    trajectory = ControllerTrajectory(times, positions, velocities, accelerations)
    q, qd, qdd = trajectory.at_times(np.array([0.0, 0.01, 0.02, 0.03, 0.05]))
    np.testing.assert_array_equal(q[[0, 1, 3, 4], 0], [0.0, 0.01, 0.05, 0.05])  # at the points exactly; then held
    c = spline_coefficients(0.02, (positions[1], velocities[1], accelerations[1]),
                            (positions[2], velocities[2], accelerations[2]))
    np.testing.assert_allclose(q[2], polynomial(c, 0.01)[0])
    with pytest.raises(ValueError, match="must increase"):
        ControllerTrajectory(np.array([0.0, 0.0]), positions[:2])


@pytest.fixture(scope="module")
def motion():
    """A jerk-limited motion through three waypoints at 90% of the limits, sampled every millisecond."""
    limits = JointLimits(0.9 * VELOCITY, 0.9 * ACCELERATION, 0.9 * JERK)
    waypoints = np.stack([HOME, HOME + [1.5, 0.8, -1.0, 0.9, 1.2, -0.6, 1.5],
                          HOME + [-0.2, 0.1, 0.3, 0.2, 0.0, 0.2, 0.0]])
    timed = time_path(waypoints, limits)
    t = np.arange(int(np.ceil(timed.duration * 1000)) + 1) / 1000.0
    return (t, *timed.at_times(np.minimum(t, timed.duration)))


def test_chosen_points_play_back_on_the_motion_within_the_limits(motion):
    t, q, qd, qdd = motion
    rows = select_points(q, qd, qdd)
    assert rows[0] == 0 and rows[-1] == len(t) - 1 and np.all(np.diff(rows) >= 1) and np.all(np.diff(rows) <= 10)
    assert len(rows) < len(t) / 3  # mostly every 10 ms
    replayed = replay(ControllerTrajectory(t[rows], q[rows], qd[rows], qdd[rows]))
    np.testing.assert_array_equal(replayed["t"], t)
    assert np.abs(replayed["q"] - q).max() <= POSITION_TOLERANCE_RAD
    assert first_violation(replayed, LOWER, UPPER, VELOCITY, ACCELERATION, JERK) is None
    # the motion's own jerk, as the commands change from cycle to cycle, keeps to 90% of the limits
    assert np.all(np.abs(replayed["jerk"]) <= JERK * 0.9 * 1.01)


def test_points_every_10_ms_overshoot_the_motion(motion):
    """Why the points are closer in places: the quintic through points 10 ms apart, matching a jerk-limited motion
    at both, commands more acceleration and jerk than the motion has where its jerk switches between them."""
    t, q, qd, qdd = motion
    rows = np.unique(np.concatenate([np.arange(0, len(t), 10), [len(t) - 1]]))
    replayed = replay(ControllerTrajectory(t[rows], q[rows], qd[rows], qdd[rows]))
    assert np.any(np.abs(replayed["qdd"]) > 0.9 * ACCELERATION * 1.05)
    assert np.any(np.abs(replayed["jerk"]) > JERK)


def test_thinned_points_break_a_limit_named_by_joint_and_quantity(motion):
    t, q, qd, qdd = motion
    rows = np.unique(np.concatenate([np.arange(0, len(t), 150), [len(t) - 1]]))
    replayed = replay(ControllerTrajectory(t[rows], q[rows], qd[rows], qdd[rows]))
    violation = first_violation(replayed, LOWER, UPPER, VELOCITY, ACCELERATION, JERK)
    assert violation is not None and violation.quantity in ("velocity", "acceleration", "jerk")
    limit = {"velocity": VELOCITY, "acceleration": ACCELERATION, "jerk": JERK}[violation.quantity][violation.joint]
    assert abs(violation.value) > abs(violation.limit) == pytest.approx(limit)
    key = {"velocity": "qd", "acceleration": "qdd", "jerk": "jerk"}[violation.quantity]
    k = int(np.round(violation.time_s * 1000))
    assert replayed[key][k, violation.joint] == violation.value
    # nothing earlier breaks any limit
    earlier = {name: values[:k] for name, values in replayed.items()}
    assert first_violation(earlier, LOWER, UPPER, VELOCITY, ACCELERATION, JERK) is None
