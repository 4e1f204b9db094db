"""The assembly program as data, and its export for a real controller.

A :class:`Program` is an ordered list of steps: timed arm motions (:class:`planning.timing.TimedPath`) and
gripper commands. It is computed first; simulating it and writing it out are separate consumers.

Exports (documented in the README):

- ``trajectory.csv``: the whole program sampled at 1 kHz: ``t`` (s), ``q_panda_joint1..7`` (rad),
  ``qd_...`` (rad/s), ``qdd_...`` (rad/s^2), ``gripper_width`` (m, commanded opening). Gripper commands take
  :data:`GRIPPER_TIME_S` during which the arm holds still.
- ``program.json``: ``{"joint_names", "rate_hz", "duration_s", "steps": [...]}``; a motion step holds a
  ``trajectory`` shaped like ROS 2 ``trajectory_msgs/JointTrajectory`` (``joint_names``, ``points`` with
  ``positions``, ``velocities``, ``accelerations``, ``time_from_start`` as ``{"sec", "nanosec"}``, sampled at
  :data:`JSON_RATE_HZ`); a gripper step holds ``width_m`` and ``duration_s``.

Both are checked against the real arm's published limits before anything is written (:func:`check_limits`).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cell.robot import ARM_JOINTS
from planning.robot_limits import PANDA, RobotLimits
from planning.timing import TimedPath

CSV_RATE_HZ = 1000.0
JSON_RATE_HZ = 100.0
GRIPPER_TIME_S = 0.5
LIMIT_TOLERANCE = 1e-6  # relative


@dataclass
class MotionStep:
    label: str  # e.g. "pick leg_front_left: approach"
    timed: TimedPath
    part: str | None = None


@dataclass
class GripperStep:
    label: str
    width_m: float  # commanded opening, 0..0.08
    part: str | None = None
    duration_s: float = GRIPPER_TIME_S


@dataclass
class Program:
    steps: list[MotionStep | GripperStep] = field(default_factory=list)
    initial_width_m: float = 0.08

    @property
    def duration_s(self) -> float:
        return sum(s.timed.duration if isinstance(s, MotionStep) else s.duration_s for s in self.steps)

    def sample(self, rate_hz: float = CSV_RATE_HZ) -> dict[str, np.ndarray]:
        """The whole program on one uniform clock ``t = k / rate_hz`` (the last sample holds the final state):
        t (N,), q, qd, qdd (N, 7), gripper_width (N,). A gripper step holds the arm still at its last position
        and commands its width from the step's start."""
        if not self.steps or not isinstance(self.steps[0], MotionStep):
            raise ValueError("a program must start with a motion")
        durations = np.array([s.timed.duration if isinstance(s, MotionStep) else s.duration_s for s in self.steps])
        starts = np.concatenate([[0.0], np.cumsum(durations)])
        count = int(np.ceil(starts[-1] * rate_hz - 1e-9)) + 1
        times = np.arange(count) / rate_hz
        q, qd, qdd = np.zeros((count, 7)), np.zeros((count, 7)), np.zeros((count, 7))
        width = np.empty(count)
        step_of = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self.steps) - 1)
        current_width, held_q = self.initial_width_m, None
        for index, step in enumerate(self.steps):
            mask = step_of == index
            local = np.minimum(times[mask] - starts[index], durations[index])
            if isinstance(step, MotionStep):
                q[mask], qd[mask], qdd[mask] = step.timed.at_times(local)
                held_q = step.timed.waypoints[-1]
            else:
                q[mask] = held_q
                current_width = step.width_m
            width[mask] = current_width
        return {"t": times, "q": q, "qd": qd, "qdd": qdd, "gripper_width": width}


class LimitViolation(ValueError):
    """The program exceeds a joint limit; the message names the joint, the quantity, the time and the value."""


def check_limits(samples: dict[str, np.ndarray], lower: np.ndarray, upper: np.ndarray,
                 arm: RobotLimits = PANDA) -> None:
    """Raise :class:`LimitViolation` at the first sample outside the position range (``lower``, ``upper``; rad) or
    the real arm's published velocity or acceleration limits (``arm``, :mod:`planning.robot_limits`)."""
    checks = [
        ("position", samples["q"] - upper[None], "above its upper limit"),
        ("position", lower[None] - samples["q"], "below its lower limit"),
        ("velocity", np.abs(samples["qd"]) - arm.velocity_rad_s[None] * (1 + LIMIT_TOLERANCE), "over its limit"),
        ("acceleration", np.abs(samples["qdd"]) - arm.acceleration_rad_s2[None] * (1 + LIMIT_TOLERANCE),
         "over its limit"),
    ]
    for quantity, excess, words in checks:
        tolerance = 1e-9 if quantity == "position" else 0.0
        bad = np.argwhere(excess > tolerance)
        if len(bad):
            k, j = bad[0]
            value = {"position": samples["q"], "velocity": samples["qd"], "acceleration": samples["qdd"]}[quantity]
            raise LimitViolation(f"{ARM_JOINTS[j]} {quantity} {value[k, j]:.4f} at t = {samples['t'][k]:.3f} s is "
                                 f"{words}")
    widths = samples["gripper_width"]
    if np.any(widths < 0) or np.any(widths > 0.08 + 1e-9):
        raise LimitViolation(f"gripper width {widths[(widths < 0) | (widths > 0.08)][0]:.4f} m is outside 0-0.08 m")


def _time_from_start(seconds: float) -> dict:
    sec = int(np.floor(seconds))
    return {"sec": sec, "nanosec": int(round((seconds - sec) * 1e9))}


def program_json(program: Program) -> dict:
    steps = []
    for step in program.steps:
        if isinstance(step, MotionStep):
            t, q, qd, qdd = step.timed.sample(JSON_RATE_HZ)
            steps.append({
                "type": "motion", "label": step.label, "part": step.part, "duration_s": step.timed.duration,
                "trajectory": {
                    "joint_names": list(ARM_JOINTS),
                    "points": [{"positions": q[k].tolist(), "velocities": qd[k].tolist(),
                                "accelerations": qdd[k].tolist(), "time_from_start": _time_from_start(t[k])}
                               for k in range(len(t))],
                },
            })
        else:
            steps.append({"type": "gripper", "label": step.label, "part": step.part, "width_m": step.width_m,
                          "duration_s": step.duration_s})
    return {"joint_names": list(ARM_JOINTS), "rate_hz": CSV_RATE_HZ, "duration_s": program.duration_s,
            "steps": steps}


def write_exports(program: Program, folder: Path, lower: np.ndarray, upper: np.ndarray,
                  samples: dict[str, np.ndarray] | None = None, arm: RobotLimits = PANDA) -> dict[str, np.ndarray]:
    """Check the limits (:func:`check_limits`), then write ``trajectory.csv`` and ``program.json`` into ``folder``;
    returns the samples. ``samples``: ``program.sample(CSV_RATE_HZ)`` when the caller has it already (they are
    checked again)."""
    samples = program.sample(CSV_RATE_HZ) if samples is None else samples
    check_limits(samples, lower, upper, arm)
    folder.mkdir(parents=True, exist_ok=True)
    header = (["t"] + [f"q_{n}" for n in ARM_JOINTS] + [f"qd_{n}" for n in ARM_JOINTS]
              + [f"qdd_{n}" for n in ARM_JOINTS] + ["gripper_width"])
    with open(folder / "trajectory.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        table = np.column_stack([samples["t"], samples["q"], samples["qd"], samples["qdd"], samples["gripper_width"]])
        writer.writerows(np.round(table, 9).tolist())
    (folder / "program.json").write_text(json.dumps(program_json(program)) + "\n")
    return samples
