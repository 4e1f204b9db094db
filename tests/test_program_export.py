"""Program export: trajectory.csv and program.json, checked by code independent of the writer."""

import csv
import json

import numpy as np
import pytest

from cell.program import GripperStep, LimitViolation, MotionStep, Program, write_exports
from cell.robot import ACCELERATION_LIMITS, JERK_LIMITS, VELOCITY_LIMITS
from planning.timing import JointLimits, time_path

# Franka's published limits, written out again here on purpose (independent of cell.robot)
FRANKA_VELOCITY = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
FRANKA_ACCELERATION = [15, 7.5, 10, 12.5, 15, 20, 20]
LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])

HOME = np.array([0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.785])
A = HOME + [0.4, 0.2, 0.0, 0.3, 0.0, -0.2, 0.0]
B = HOME + [-0.4, 0.1, 0.2, 0.2, 0.1, 0.0, -0.3]


# the planner's: 90% of the published limits (a program timed at 100% of the jerk limit breaks it by a fraction of a
# percent as the controller plays its points back, and is refused)
PANDA_LIMITS = JointLimits(0.9 * VELOCITY_LIMITS, 0.9 * ACCELERATION_LIMITS, 0.9 * JERK_LIMITS)


def program(limits=PANDA_LIMITS):
    return Program([
        MotionStep("to A", time_path(np.stack([HOME, A]), limits)),
        GripperStep("close", 0.02, part="leg"),
        MotionStep("to B via home", time_path(np.stack([A, HOME, B]), limits), part="leg"),
        GripperStep("open", 0.08, part="leg"),
    ])


def test_exports_are_well_formed_and_within_limits(tmp_path):
    write_exports(program(), tmp_path, LOWER, UPPER)
    with open(tmp_path / "trajectory.csv") as handle:
        rows = list(csv.reader(handle))
    header, data = rows[0], np.array(rows[1:], dtype=float)
    assert header[0] == "t" and header[-1] == "gripper_width"
    assert header[1:8] == [f"q_panda_joint{i}" for i in range(1, 8)]
    assert header[8] == "qd_panda_joint1" and header[15] == "qdd_panda_joint1"
    t, q, qd, qdd, width = data[:, 0], data[:, 1:8], data[:, 8:15], data[:, 15:22], data[:, 22]
    np.testing.assert_allclose(np.diff(t), 0.001, atol=2e-6)  # 1 kHz
    np.testing.assert_allclose(q[0], HOME, atol=1e-9)
    np.testing.assert_allclose(q[-1], B, atol=1e-9)
    assert np.all(q >= LOWER) and np.all(q <= UPPER)
    assert np.all(np.abs(qd) <= np.array(FRANKA_VELOCITY) + 1e-6)
    assert np.all(np.abs(qdd) <= np.array(FRANKA_ACCELERATION) + 1e-6)
    # positions are continuous: no jump bigger than max velocity x dt
    assert np.all(np.abs(np.diff(q, axis=0)) <= np.array(FRANKA_VELOCITY) * 0.001 * 1.01)
    # the gripper closes while the arm stands still for half a second, then carries the part at that width
    closing = np.flatnonzero(np.isclose(width, 0.02))
    assert len(closing) > 500 and np.allclose(qd[closing[:500]], 0.0)
    assert np.any(np.abs(qd[closing[500:]]) > 0.1)

    document = json.loads((tmp_path / "program.json").read_text())
    assert [s["type"] for s in document["steps"]] == ["motion", "gripper", "motion", "gripper"]
    trajectory = document["steps"][2]["trajectory"]
    assert trajectory["joint_names"] == [f"fer_joint{i}" for i in range(1, 8)]  # franka_ros2's Panda
    point = trajectory["points"][-1]
    assert set(point) == {"positions", "velocities", "accelerations", "time_from_start"}
    assert set(point["time_from_start"]) == {"sec", "nanosec"}
    np.testing.assert_allclose(point["positions"], B, atol=1e-9)
    assert document["duration_s"] == pytest.approx(t[-1], abs=2e-3)


def test_limit_violation_is_named_and_nothing_written(tmp_path):
    too_fast = JointLimits(VELOCITY_LIMITS * 3, ACCELERATION_LIMITS * 3, JERK_LIMITS * 3)
    with pytest.raises(LimitViolation, match=r"panda_joint\d (velocity|acceleration) .* at t = .* over its limit"):
        write_exports(program(too_fast), tmp_path / "out", LOWER, UPPER)
    assert not (tmp_path / "out").exists()
