"""The assembly program as data, and its export for a real controller.

A :class:`Program` is an ordered list of steps: timed arm motions (:class:`planning.timing.TimedPath`, or the
points of a loaded program, :class:`planning.controller_replay.ControllerTrajectory`) and gripper commands. It is
computed first; simulating it and writing it out are separate consumers. Every step lasts a whole number of
control cycles (:data:`CONTROL_RATE_HZ`, the Franka arm's 1 kHz): a motion's timed duration is rounded up, the arm
at rest at its end for the rest of the last cycle.

Exports (documented in the README):

- ``trajectory.csv``: the whole program sampled at :data:`CSV_RATE_HZ`, one row per control cycle: ``t`` (s),
  ``q_panda_joint1..7`` (rad), ``qd_...`` (rad/s), ``qdd_...`` (rad/s^2), ``gripper_width`` (m, the opening the
  simulator commands). Gripper commands take :data:`GRIPPER_TIME_S` during which the arm holds still.
- ``program.json`` (:func:`program_json`, read back by :func:`load`): the robot, its joint names as its ROS 2
  driver names them, and the steps; a motion holds a ``trajectory`` shaped like ROS 2
  ``trajectory_msgs/JointTrajectory``, whose points are rows of ``trajectory.csv`` (every
  1 / :data:`POINT_RATE_HZ` s, closer where the controller's spline between them would leave the motion; see
  :func:`motion_points`); a gripper step is a ``move`` (width, speed) or a ``grasp`` (the part's width, speed,
  force, epsilon), and a ``payload`` step after each grasp and release gives the load the arm then carries.
- ``trajectory.mcap``: the same as a ROS 2 bag (:mod:`cell.ros2_export`).

Both are checked against the real arm's published limits (:mod:`planning.robot_limits`) before anything is
written (:func:`check_limits`, :func:`check_controller_replay`).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cell.robot import ARM_JOINTS
from planning.controller_replay import POINT_SPACINGS, ControllerTrajectory, first_violation, replay, select_points
from planning.payload import FlangeLoad
from planning.robot_limits import PANDA, RobotLimits, robot_limits
from planning.timing import TimedPath

CONTROL_RATE_HZ = 1000.0  # the arm's control cycle (libfranka, and the controller manager of franka_ros2)
CSV_RATE_HZ = CONTROL_RATE_HZ
POINT_RATE_HZ = CONTROL_RATE_HZ / POINT_SPACINGS[0]  # a motion's JointTrajectory points, where no closer are needed
GRIPPER_TIME_S = 0.5
GRIPPER_SPEED_M_S = 0.1  # the fingers' speed of a gripper command (franka_gripper's default)
GRASP_EPSILON_M = 0.005  # a grasp succeeds when the fingers stop this close to the part's width (Franka's default)
LIMIT_TOLERANCE = 1e-6  # relative
def arm_limits(robot: str) -> RobotLimits:
    """The published limits and ROS 2 names of the program's ``robot`` (:mod:`planning.robot_limits`); a
    ValueError naming the known models otherwise."""
    try:
        return robot_limits(robot)
    except KeyError as exc:
        raise ValueError(exc.args[0]) from None


def controller_joint_names(robot: str) -> list[str]:
    """The arm's joint names as its ROS 2 driver (franka_ros2) names them: ``fer_joint1..7`` for the Panda,
    ``fr3_joint1..7`` for the FR3."""
    return list(arm_limits(robot).ros_joint_names)


def flange_frame(robot: str) -> str:
    """The flange link (the frame of a SetLoad request) as the ROS 2 driver names it."""
    return arm_limits(robot).ros_flange_frame


@dataclass
class MotionStep:
    label: str  # e.g. "pick leg_front_left: approach"
    timed: TimedPath | ControllerTrajectory
    part: str | None = None

    @property
    def cycles(self) -> int:
        """Control cycles the step lasts: its motion's duration rounded up to whole cycles."""
        return int(np.ceil(self.timed.duration * CONTROL_RATE_HZ - 1e-6))


@dataclass
class GripperStep:
    """A gripper command while the arm holds still. ``kind``: ``"move"`` (the fingers to ``width_m``) or ``"grasp"``
    (close on a part ``grasp_width_m`` wide with ``force_n``; it succeeds when the fingers stop within
    ``epsilon_inner_m`` below and ``epsilon_outer_m`` above that width). ``width_m`` is the opening the simulator
    commands (a grasp's squeezes the part: less than its width). ``load``: what the arm carries from the end of this
    step on (Franka's SetLoad), None where it carries on as before."""

    label: str
    width_m: float  # the simulator's command, 0..0.08
    part: str | None = None
    duration_s: float = GRIPPER_TIME_S
    kind: str = "move"
    grasp_width_m: float | None = None
    speed_m_s: float = GRIPPER_SPEED_M_S
    force_n: float = 0.0
    epsilon_inner_m: float = GRASP_EPSILON_M
    epsilon_outer_m: float = GRASP_EPSILON_M
    load: FlangeLoad | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("move", "grasp"):
            raise ValueError(f"gripper step {self.label!r}: kind must be 'move' or 'grasp', got {self.kind!r}")
        if self.kind == "grasp" and self.grasp_width_m is None:
            raise ValueError(f"gripper step {self.label!r}: a grasp needs the part's width (grasp_width_m)")

    @property
    def cycles(self) -> int:
        return int(np.ceil(self.duration_s * CONTROL_RATE_HZ - 1e-6))

    @property
    def goal_width_m(self) -> float:
        """The width the real gripper is sent to: a grasp's part width, a move's opening."""
        return float(self.grasp_width_m if self.kind == "grasp" else self.width_m)


@dataclass
class Program:
    steps: list[MotionStep | GripperStep] = field(default_factory=list)
    initial_width_m: float = 0.08
    robot: str = "panda"  # the robot model: "panda" (Franka Emika Robot) or "fr3"

    def step_cycles(self) -> np.ndarray:
        """(S,) int: control cycles per step."""
        return np.array([s.cycles for s in self.steps], dtype=np.int64)

    def step_starts_s(self) -> np.ndarray:
        """(S + 1,): when each step starts, and the program's end (s; whole control cycles)."""
        return np.concatenate([[0], np.cumsum(self.step_cycles())]) / CONTROL_RATE_HZ

    @property
    def duration_s(self) -> float:
        return float(self.step_cycles().sum() / CONTROL_RATE_HZ)

    def sample(self, rate_hz: float = CSV_RATE_HZ) -> dict[str, np.ndarray]:
        """The whole program on one uniform clock ``t = k / rate_hz`` (the last sample holds the final state):
        t (N,), q, qd, qdd (N, 7), gripper_width (N,). A gripper step holds the arm still at its last position
        and commands its width from the step's start. At the control rate, sample k is control cycle k."""
        if not self.steps or not isinstance(self.steps[0], MotionStep):
            raise ValueError("a program must start with a motion")
        cycles = np.concatenate([[0], np.cumsum(self.step_cycles())])
        starts = cycles / CONTROL_RATE_HZ
        count = int(np.ceil(starts[-1] * rate_hz - 1e-9)) + 1
        ticks = np.arange(count)
        times = ticks / rate_hz
        q, qd, qdd = np.zeros((count, 7)), np.zeros((count, 7)), np.zeros((count, 7))
        width = np.empty(count)
        step_of = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self.steps) - 1)
        current_width, held_q = self.initial_width_m, None
        for index, step in enumerate(self.steps):
            mask = step_of == index
            # the time into the step from whole numbers (exact at the control rate: (k - start cycle) / rate)
            local = (ticks[mask] * CONTROL_RATE_HZ - cycles[index] * rate_hz) / (rate_hz * CONTROL_RATE_HZ)
            if isinstance(step, MotionStep):
                q[mask], qd[mask], qdd[mask] = step.timed.at_times(np.minimum(local, step.timed.duration))
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


@dataclass(frozen=True)
class MotionPoints:
    """The ``JointTrajectory`` points of motion step ``step`` (index into the program's steps): ``rows`` (P,) int,
    the control cycles (rows of the program's samples at :data:`CSV_RATE_HZ`) they are taken at, the first at the
    step's start, the last at its end."""

    step: int
    rows: np.ndarray

    def time_from_start_ns(self) -> np.ndarray:
        """(P,) int: each point's ``time_from_start`` in nanoseconds (whole control cycles)."""
        return (self.rows - self.rows[0]) * int(round(1e9 / CONTROL_RATE_HZ))

    def trajectory(self, samples: dict[str, np.ndarray]) -> ControllerTrajectory:
        """The points (positions, velocities, accelerations from ``samples``) as the controller receives them."""
        return ControllerTrajectory(self.time_from_start_ns() / 1e9, samples["q"][self.rows], samples["qd"][self.rows],
                                    samples["qdd"][self.rows])


def _checked_samples(program: Program, samples: dict[str, np.ndarray]) -> np.ndarray:
    cycles = np.concatenate([[0], np.cumsum(program.step_cycles())])
    if len(samples["t"]) != cycles[-1] + 1:
        raise ValueError(f"the samples must be the program's at {CSV_RATE_HZ:.0f} Hz ({cycles[-1] + 1}), got "
                         f"{len(samples['t'])}")
    return cycles


def motion_points(program: Program, samples: dict[str, np.ndarray]) -> list[MotionPoints]:
    """Per motion step, the samples (``program.sample(CSV_RATE_HZ)``) sent to the controller as its points: every
    1 / :data:`POINT_RATE_HZ` s, closer (down to every cycle) where the controller's spline between two points
    would stray from the motion (:func:`planning.controller_replay.select_points`); a loaded program's own
    points."""
    cycles = _checked_samples(program, samples)
    found = []
    for index, step in enumerate(program.steps):
        if not isinstance(step, MotionStep):
            continue
        a, b = int(cycles[index]), int(cycles[index + 1])
        if isinstance(step.timed, ControllerTrajectory):
            rows = a + np.round(step.timed.times_s * CONTROL_RATE_HZ).astype(np.int64)
        else:
            rows = a + select_points(samples["q"][a:b + 1], samples["qd"][a:b + 1], samples["qdd"][a:b + 1],
                                     rate_hz=CONTROL_RATE_HZ)
        found.append(MotionPoints(index, rows))
    return found


def check_controller_replay(program: Program, samples: dict[str, np.ndarray], lower: np.ndarray,
                            upper: np.ndarray, points: list[MotionPoints] | None = None) -> list[MotionPoints]:
    """Play every motion's points back as ros2_control's joint trajectory controller does
    (:mod:`planning.controller_replay`: its spline between the points, commanded at :data:`CONTROL_RATE_HZ`) and
    raise :class:`LimitViolation`, naming the step and the joint, where a command leaves the position range
    [``lower``, ``upper``] (rad) or passes the velocity, acceleration or jerk limits of the program's robot
    (:mod:`planning.robot_limits`), or strays more than :data:`planning.controller_replay.REPLAY_DEVIATION_LIMIT_RAD`
    from the program's own motion (which the planner checked for collisions). Returns the points checked
    (``points``, or :func:`motion_points`)."""
    from planning.controller_replay import REPLAY_DEVIATION_LIMIT_RAD

    cycles = _checked_samples(program, samples)
    points = motion_points(program, samples) if points is None else points
    names = controller_joint_names(program.robot)
    arm = arm_limits(program.robot)  # the real arm's published limits
    for motion in points:
        step = program.steps[motion.step]
        replayed = replay(motion.trajectory(samples), CONTROL_RATE_HZ)
        where = (f"step {motion.step + 1} ({step.label!r}), as the joint trajectory controller plays its "
                 f"{len(motion.rows)} points")
        violation = first_violation(replayed, lower, upper, arm.velocity_rad_s, arm.acceleration_rad_s2,
                                    arm.jerk_rad_s3, LIMIT_TOLERANCE)
        if violation is not None:
            j = violation.joint
            raise LimitViolation(f"{where}: joint {j + 1} ({names[j]}) {violation.quantity} {violation.value:.4f} at "
                                 f"{violation.time_s:.3f} s into the step passes its limit {violation.limit:.4f}")
        a = int(cycles[motion.step])
        own = samples["q"][a:a + len(replayed["q"])]
        deviation = np.abs(replayed["q"] - own)
        if deviation.max() > REPLAY_DEVIATION_LIMIT_RAD:
            k, j = np.unravel_index(np.argmax(deviation), deviation.shape)
            raise LimitViolation(f"{where}: joint {j + 1} ({names[j]}) strays {deviation[k, j]:.2e} rad from the "
                                 f"planned motion at {replayed['t'][k]:.3f} s into the step (at most "
                                 f"{REPLAY_DEVIATION_LIMIT_RAD:g} rad)")
    return points


def _time_from_start(nanoseconds: int) -> dict:
    return {"sec": int(nanoseconds // 1_000_000_000), "nanosec": int(nanoseconds % 1_000_000_000)}


def _load_json(load: FlangeLoad, robot: str) -> dict:
    return {"mass_kg": load.mass_kg, "center_of_mass_m": list(load.flange_from_com_m),
            "inertia_kg_m2": [list(row) for row in load.inertia_kg_m2], "frame": flange_frame(robot)}


def program_json(program: Program, samples: dict[str, np.ndarray] | None = None,
                 points: list[MotionPoints] | None = None) -> dict:
    """``program.json``'s content (see the module's docstring); ``samples``: ``program.sample(CSV_RATE_HZ)``,
    ``points``: :func:`motion_points`, when the caller has them."""
    samples = program.sample(CSV_RATE_HZ) if samples is None else samples
    points = {m.step: m for m in (motion_points(program, samples) if points is None else points)}
    names = controller_joint_names(program.robot)
    cycles = np.concatenate([[0], np.cumsum(program.step_cycles())])
    starts = cycles / CONTROL_RATE_HZ
    steps = []
    for index, step in enumerate(program.steps):
        timing = {"label": step.label, "part": step.part, "start_s": float(starts[index]),
                  "duration_s": float(step.cycles / CONTROL_RATE_HZ)}
        if isinstance(step, MotionStep):
            motion = points[index]
            rows = motion.rows
            steps.append({"type": "motion", **timing, "trajectory": {
                "joint_names": names,
                "points": [{"positions": samples["q"][r].tolist(), "velocities": samples["qd"][r].tolist(),
                            "accelerations": samples["qdd"][r].tolist(), "time_from_start": _time_from_start(ns)}
                           for r, ns in zip(rows, motion.time_from_start_ns())],
            }})
            continue
        command = {"type": "gripper", "kind": step.kind, **timing, "width_m": step.goal_width_m,
                   "speed_m_s": step.speed_m_s}
        if step.kind == "grasp":
            command.update(force_n=step.force_n,
                           epsilon_m={"inner": step.epsilon_inner_m, "outer": step.epsilon_outer_m},
                           simulated_width_m=step.width_m)
        steps.append(command)
        if step.load is not None:
            steps.append({"type": "payload", "label": f"{step.label}: load",
                          "part": step.part if step.load.mass_kg > 0 else None, "start_s": float(starts[index + 1]),
                          "duration_s": 0.0, **_load_json(step.load, program.robot)})
    return {"robot": program.robot, "joint_names": names, "csv_rate_hz": CSV_RATE_HZ, "point_rate_hz": POINT_RATE_HZ,
            "control_rate_hz": CONTROL_RATE_HZ, "duration_s": program.duration_s,
            "initial_width_m": program.initial_width_m, "steps": steps}


class ProgramFormatError(ValueError):
    """A ``program.json`` that :func:`load` cannot read; the message names the file, the step and the field."""


def load(path: str | Path) -> Program:
    """The :class:`Program` written to ``path`` (``program.json``): its motions as their points
    (:class:`planning.controller_replay.ControllerTrajectory`: sampled, they play back as the controller would),
    its gripper steps with their payloads. Raises :class:`ProgramFormatError` naming what is wrong."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProgramFormatError(f"{path}: not a readable program.json ({exc})") from exc
    where = f"{path}"
    try:
        program = Program(initial_width_m=float(document["initial_width_m"]), robot=str(document["robot"]))
        names = controller_joint_names(program.robot)
        for index, entry in enumerate(document["steps"]):
            where = f"{path}, step {index + 1}"
            kind = entry["type"]
            if kind == "motion":
                trajectory = entry["trajectory"]
                if trajectory["joint_names"] != names:
                    raise ProgramFormatError(f"{where}: joint names {trajectory['joint_names']} are not the "
                                             f"{program.robot}'s {names}")
                rows = trajectory["points"]
                times = np.array([p["time_from_start"]["sec"] * 1_000_000_000 + p["time_from_start"]["nanosec"]
                                  for p in rows]) / 1e9
                program.steps.append(MotionStep(entry["label"], ControllerTrajectory(
                    times, [p["positions"] for p in rows], [p["velocities"] for p in rows],
                    [p["accelerations"] for p in rows]), entry["part"]))
            elif kind == "gripper":
                grasp = entry["kind"] == "grasp"
                program.steps.append(GripperStep(
                    entry["label"], float(entry["simulated_width_m"] if grasp else entry["width_m"]), entry["part"],
                    float(entry["duration_s"]), entry["kind"], float(entry["width_m"]) if grasp else None,
                    float(entry["speed_m_s"]), float(entry["force_n"]) if grasp else 0.0,
                    *((float(entry["epsilon_m"]["inner"]), float(entry["epsilon_m"]["outer"])) if grasp
                      else (GRASP_EPSILON_M, GRASP_EPSILON_M))))
            elif kind == "payload":
                if not program.steps or not isinstance(program.steps[-1], GripperStep):
                    raise ProgramFormatError(f"{where}: a payload step must follow a gripper step")
                program.steps[-1].load = FlangeLoad(
                    float(entry["mass_kg"]), tuple(float(v) for v in entry["center_of_mass_m"]),
                    tuple(tuple(float(v) for v in row) for row in entry["inertia_kg_m2"]))
            else:
                raise ProgramFormatError(f"{where}: unknown step type {kind!r} (motion, gripper or payload)")
    except ProgramFormatError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise ProgramFormatError(f"{where}: {exc.__class__.__name__}: {exc}") from exc
    return program


def write_exports(program: Program, folder: Path, lower: np.ndarray, upper: np.ndarray,
                  samples: dict[str, np.ndarray] | None = None, points: list[MotionPoints] | None = None,
                  bag_storage: str = "mcap") -> dict[str, np.ndarray]:
    """Check the limits of the program's robot (:func:`check_limits`, :func:`check_controller_replay`), then write
    ``trajectory.csv``, ``program.json`` and the ROS 2 bag (:func:`cell.ros2_export.write_bag`, ``bag_storage``
    "mcap" or "sqlite3") into ``folder``; returns the samples. ``samples``: ``program.sample(CSV_RATE_HZ)`` and
    ``points``: the checked :func:`motion_points`, when the caller has them (the limits are checked again)."""
    from cell.ros2_export import write_bag

    samples = program.sample(CSV_RATE_HZ) if samples is None else samples
    check_limits(samples, lower, upper, arm_limits(program.robot))
    points = check_controller_replay(program, samples, lower, upper, points)
    folder.mkdir(parents=True, exist_ok=True)
    header = (["t"] + [f"q_{n}" for n in ARM_JOINTS] + [f"qd_{n}" for n in ARM_JOINTS]
              + [f"qdd_{n}" for n in ARM_JOINTS] + ["gripper_width"])
    with open(folder / "trajectory.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        table = np.column_stack([samples["t"], samples["q"], samples["qd"], samples["qdd"], samples["gripper_width"]])
        writer.writerows(np.round(table, 9).tolist())
    (folder / "program.json").write_text(json.dumps(program_json(program, samples, points)) + "\n")
    write_bag(program, samples, points, folder, bag_storage)
    return samples
