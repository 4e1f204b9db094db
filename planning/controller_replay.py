"""A joint trajectory as a ROS 2 controller plays it: ros2_control's ``joint_trajectory_controller`` (JTC).

The JTC receives ``trajectory_msgs/JointTrajectory`` points (``time_from_start``, positions and, optionally,
velocities and accelerations) and, at every cycle of its controller manager (1 kHz for a Franka arm), commands the
spline between the two points around that time (``joint_trajectory_controller/src/trajectory.cpp``,
``interpolate_between_points``): per joint, a quintic polynomial where both points give positions, velocities and
accelerations (matching all three at both ends), a cubic where they give positions and velocities, a straight line
where they give positions only. After the last point it holds that point.

This module plays such points back the same way (:class:`ControllerTrajectory`), chooses the points of a timed
motion so that its playback stays on it (:func:`select_points`), and checks a playback against joint limits
(:func:`first_violation`). Between two points the quintic only reproduces the motion where the motion itself is a
polynomial of degree five or less there; a jerk-limited (Ruckig) motion switches its jerk inside an interval, and
its quintic, matched at points 10 ms apart, overshoots the motion's accelerations by up to a fifth and its jerks
by over half: such points are placed closer together.

Units: seconds, radians (rad/s, rad/s^2, rad/s^3); arrays (N, dof).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# the playback may differ from the timed motion it comes from by at most this much, per joint at every control
# cycle (see select_points): about 0.01 mm at the TCP, 1 mm/s and 0.05 rad/s^2 of a joint
POSITION_TOLERANCE_RAD = 1e-5
VELOCITY_TOLERANCE_RAD_S = 1e-3
ACCELERATION_TOLERANCE_RAD_S2 = 0.05
# a playback may stray this far from the motion the planner checked (see cell.program.check_controller_replay): the
# insertion's own blends keep within this of its path
REPLAY_DEVIATION_LIMIT_RAD = 1e-4
POINT_SPACINGS = (10, 5, 2, 1)  # control cycles between two points: the widest that keeps to the tolerances


def spline_coefficients(duration_s, start: tuple[np.ndarray, ...], end: tuple[np.ndarray, ...]) -> np.ndarray:
    """The JTC's polynomial between two points ``duration_s`` apart: coefficients (..., 6, dof) of ``1, t, .., t^5``
    (t from the first point). ``start`` and ``end``: (positions,) or (positions, velocities) or (positions,
    velocities, accelerations), each (..., dof): a straight line, a cubic or a quintic, as the JTC chooses.
    ``duration_s``: a number or (...,), one per pair of points."""
    p0, p1 = (np.asarray(start[0], dtype=np.float64), np.asarray(end[0], dtype=np.float64))
    c = np.zeros((*p0.shape[:-1], 6, p0.shape[-1]))
    c[..., 0, :] = p0
    T = np.asarray(duration_s, dtype=np.float64)[..., None] * np.ones_like(p0)
    moving = T != 0.0
    T = np.where(moving, T, 1.0)  # no division by zero; the terms below are dropped where the points coincide
    order = min(len(start), len(end))
    if order == 1:
        c[..., 1, :] = np.where(moving, (p1 - p0) / T, 0.0)
        return c
    v0, v1 = np.asarray(start[1], dtype=np.float64), np.asarray(end[1], dtype=np.float64)
    c[..., 1, :] = v0
    if order == 2:
        c[..., 2, :] = np.where(moving, (-3.0 * p0 + 3.0 * p1 - 2.0 * v0 * T - v1 * T) / T ** 2, 0.0)
        c[..., 3, :] = np.where(moving, (2.0 * p0 - 2.0 * p1 + v0 * T + v1 * T) / T ** 3, 0.0)
        return c
    a0, a1 = np.asarray(start[2], dtype=np.float64), np.asarray(end[2], dtype=np.float64)
    c[..., 2, :] = 0.5 * a0
    c[..., 3, :] = np.where(moving, (-20.0 * p0 + 20.0 * p1 - 3.0 * a0 * T ** 2 + a1 * T ** 2 - 12.0 * v0 * T
                                     - 8.0 * v1 * T) / (2 * T ** 3), 0.0)
    c[..., 4, :] = np.where(moving, (30.0 * p0 - 30.0 * p1 + 3.0 * a0 * T ** 2 - 2.0 * a1 * T ** 2 + 16.0 * v0 * T
                                     + 14.0 * v1 * T) / (2 * T ** 4), 0.0)
    c[..., 5, :] = np.where(moving, (-12.0 * p0 + 12.0 * p1 - a0 * T ** 2 + a1 * T ** 2 - 6.0 * v0 * T
                                     - 6.0 * v1 * T) / (2 * T ** 5), 0.0)
    return c


def _evaluate(c: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration (len(t), dof) of the polynomials ``c`` (6, dof) or (len(t), 6, dof)."""
    c = np.broadcast_to(c, (len(t), *c.shape[-2:]))
    t = np.asarray(t, dtype=np.float64)[:, None]
    q = c[:, 0] + t * (c[:, 1] + t * (c[:, 2] + t * (c[:, 3] + t * (c[:, 4] + t * c[:, 5]))))
    qd = c[:, 1] + t * (2 * c[:, 2] + t * (3 * c[:, 3] + t * (4 * c[:, 4] + t * 5 * c[:, 5])))
    qdd = 2 * c[:, 2] + t * (6 * c[:, 3] + t * (12 * c[:, 4] + t * 20 * c[:, 5]))
    return q, qd, qdd


@dataclass
class ControllerTrajectory:
    """``JointTrajectory`` points and their playback by the JTC. ``times_s`` (P,): ``time_from_start`` of each
    point, increasing, the first 0 (the arm is there, at rest, when the trajectory starts); ``positions`` (P, dof);
    ``velocities``, ``accelerations`` (P, dof) or None (not given). Same interface as
    :class:`planning.timing.TimedPath` for what a program needs (``duration``, ``at_times``, ``sample``,
    ``waypoints``)."""

    times_s: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray | None = None
    accelerations: np.ndarray | None = None
    _coefficients: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.times_s = np.asarray(self.times_s, dtype=np.float64)
        self.positions = np.atleast_2d(np.asarray(self.positions, dtype=np.float64))
        if len(self.times_s) != len(self.positions) or len(self.times_s) == 0:
            raise ValueError(f"a trajectory needs as many times as points, at least one; got {len(self.times_s)} "
                             f"times and {len(self.positions)} points")
        if np.any(np.diff(self.times_s) <= 0.0):
            raise ValueError("a trajectory's times_from_start must increase")
        for name in ("velocities", "accelerations"):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                if value.shape != self.positions.shape:
                    raise ValueError(f"{name} has shape {value.shape}, the positions {self.positions.shape}")
                setattr(self, name, value)
        if self.velocities is None:
            self.accelerations = None  # the JTC's quintic needs velocities too

    @property
    def duration(self) -> float:
        return float(self.times_s[-1])

    @property
    def waypoints(self) -> np.ndarray:
        """The points' positions (P, dof); the last is where the motion ends."""
        return self.positions

    def _point(self, k: int | np.ndarray) -> tuple[np.ndarray, ...]:
        fields = [self.positions, self.velocities, self.accelerations]
        return tuple(f[k] for f in fields if f is not None)

    def coefficients(self) -> np.ndarray:
        """(P-1, 6, dof): the polynomial of each interval between neighbouring points (:func:`spline_coefficients`)."""
        if self._coefficients is None:
            self._coefficients = spline_coefficients(np.diff(self.times_s), self._point(slice(0, -1)),
                                                     self._point(slice(1, None)))
        return self._coefficients

    def at_times(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Commanded positions, velocities, accelerations (len(times), dof) at ``times`` (s from the start): the
        spline of the interval each time falls in (an interval holds from its first point up to, not including, its
        last), the last point from the last point's time on, the first point before the start."""
        times = np.asarray(times, dtype=np.float64)
        dof = self.positions.shape[1]
        q, qd, qdd = np.empty((len(times), dof)), np.zeros((len(times), dof)), np.zeros((len(times), dof))
        interval = np.searchsorted(self.times_s, times, side="right") - 1
        last = len(self.times_s) - 1
        held = (interval >= last) | (interval < 0)
        held_at = np.where(interval < 0, 0, last)[held]
        q[held] = self.positions[held_at]
        if self.velocities is not None:
            qd[held] = self.velocities[held_at]
        if self.accelerations is not None:
            qdd[held] = self.accelerations[held_at]
        inside = ~held
        if inside.any():
            k = interval[inside]
            q[inside], qd[inside], qdd[inside] = _evaluate(self.coefficients()[k], times[inside] - self.times_s[k])
        return q, qd, qdd

    def sample(self, rate_hz: float = 1000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(t, q, qd, qdd) at the control cycles ``k / rate_hz`` from the start to the last point."""
        count = int(np.floor(self.duration * rate_hz + 1e-9)) + 1
        times = np.arange(count) / rate_hz
        return (times, *self.at_times(times))


def replay(trajectory: ControllerTrajectory, rate_hz: float = 1000.0) -> dict[str, np.ndarray]:
    """What the JTC commands at ``rate_hz`` over ``trajectory``: ``t`` (N,), ``q``, ``qd``, ``qdd`` (N, dof) at
    the control cycles from its start to its last point, and ``jerk`` (N, dof), the change of the commanded
    acceleration from the cycle before (rad/s^3; the first cycle's from the first point's acceleration, the arm at
    rest before): the jerk of the command stream the robot receives."""
    t, q, qd, qdd = trajectory.sample(rate_hz)
    before = qdd[:1] if trajectory.accelerations is None else trajectory.accelerations[:1]
    jerk = np.diff(np.concatenate([before, qdd]), axis=0) * rate_hz
    return {"t": t, "q": q, "qd": qd, "qdd": qdd, "jerk": jerk}


def select_points(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, spacings: tuple[int, ...] = POINT_SPACINGS,
                  position_tolerance: float = POSITION_TOLERANCE_RAD,
                  velocity_tolerance: float = VELOCITY_TOLERANCE_RAD_S,
                  acceleration_tolerance: float = ACCELERATION_TOLERANCE_RAD_S2,
                  rate_hz: float = 1000.0) -> np.ndarray:
    """Indices of the samples of a timed motion (``q``, ``qd``, ``qdd``: (N, dof) at ``rate_hz``, the first at
    the motion's start, the last at its end) to send as ``JointTrajectory`` points: the first and the last, and
    between them every ``spacings[0]`` samples, each interval where the JTC's quintic between its two points strays
    from the motion at a sample between them by more than the tolerances split at ``spacings[1]`` samples, and so
    on down to ``spacings[-1]`` (1: every sample, where the playback is the motion itself)."""
    tolerances = (position_tolerance, velocity_tolerance, acceleration_tolerance)
    last = len(q) - 1
    chosen = [np.array([0, last])]
    pending = np.arange(0, last, spacings[0])  # interval starts, each up to the next multiple of spacings[0]
    ends = np.minimum(pending + spacings[0], last)
    for level, spacing in enumerate(spacings):
        if len(pending) == 0:
            break
        chosen.append(pending)
        if level + 1 == len(spacings) or spacing <= 1:
            break
        failing = ~_keep_to(q, qd, qdd, pending, ends, rate_hz, tolerances)
        finer = spacings[level + 1]
        starts, stops = [], []
        for a, b in zip(pending[failing], ends[failing]):
            inner = np.arange(a, b, finer)
            starts.append(inner)
            stops.append(np.minimum(inner + finer, b))
        pending = np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)
        ends = np.concatenate(stops) if stops else np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(chosen))


def _keep_to(q, qd, qdd, starts: np.ndarray, ends: np.ndarray, rate_hz: float, tolerances) -> np.ndarray:
    """(len(starts),) bool: whether the quintic between samples ``starts[i]`` and ``ends[i]`` keeps within
    ``tolerances`` (position, velocity, acceleration) of the samples between them."""
    keeps = np.ones(len(starts), dtype=bool)
    lengths = ends - starts
    for length in np.unique(lengths):
        if length <= 1:
            continue
        which = np.flatnonzero(lengths == length)
        a, b = starts[which], ends[which]
        c = spline_coefficients(np.full(len(a), length / rate_hz), (q[a], qd[a], qdd[a]), (q[b], qd[b], qdd[b]))
        inside = a[:, None] + np.arange(1, length)[None]  # (M, length - 1) sample indices
        t = np.arange(1, length) / rate_hz
        ok = np.ones(len(a), dtype=bool)
        for k, (value, tolerance) in enumerate(zip(_evaluate_many(c, t), tolerances)):
            ok &= np.abs(value - (q, qd, qdd)[k][inside]).max(axis=(1, 2)) <= tolerance
        keeps[which] = ok
    return keeps


def _evaluate_many(c: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity, acceleration (M, len(t), dof) of the polynomials ``c`` (M, 6, dof) at the times ``t``."""
    c = c[:, None]  # (M, 1, 6, dof)
    t = t[None, :, None]
    q = c[..., 0, :] + t * (c[..., 1, :] + t * (c[..., 2, :] + t * (c[..., 3, :] + t * (c[..., 4, :]
                                                                                        + t * c[..., 5, :]))))
    qd = c[..., 1, :] + t * (2 * c[..., 2, :] + t * (3 * c[..., 3, :] + t * (4 * c[..., 4, :] + t * 5 * c[..., 5, :])))
    qdd = 2 * c[..., 2, :] + t * (6 * c[..., 3, :] + t * (12 * c[..., 4, :] + t * 20 * c[..., 5, :]))
    return q, qd, qdd


@dataclass(frozen=True)
class ReplayViolation:
    """The first command of a playback outside a limit: ``joint`` (zero-based), ``quantity`` (position, velocity,
    acceleration or jerk), ``time_s`` (from the trajectory's start), the commanded ``value`` and the ``limit`` it
    passes (signed: the bound it crosses)."""

    joint: int
    quantity: str
    time_s: float
    value: float
    limit: float


def first_violation(replayed: dict[str, np.ndarray], lower: np.ndarray, upper: np.ndarray, velocity: np.ndarray,
                    acceleration: np.ndarray, jerk: np.ndarray, tolerance: float = 1e-6) -> ReplayViolation | None:
    """The earliest command of ``replayed`` (:func:`replay`) outside the position range [``lower``, ``upper``]
    (rad) or over the velocity, acceleration or jerk limits (per joint, rad/s, rad/s^2, rad/s^3; ``tolerance``
    relative, for rounding), or None."""
    found = []
    for quantity, key, low, high in (("position", "q", lower, upper), ("velocity", "qd", -velocity, velocity),
                                     ("acceleration", "qdd", -acceleration, acceleration),
                                     ("jerk", "jerk", -jerk, jerk)):
        low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        slack = (np.full(low.shape, 1e-9) if quantity == "position"
                 else tolerance * np.maximum(np.abs(low), np.abs(high)))
        values = replayed[key]
        bad = (values < low - slack) | (values > high + slack)
        if bad.any():
            k, j = np.argwhere(bad)[0]
            limit = float(low[j] if values[k, j] < low[j] - slack[j] else high[j])
            found.append(ReplayViolation(int(j), quantity, float(replayed["t"][k]), float(values[k, j]), limit))
    return min(found, key=lambda v: v.time_s) if found else None


__all__ = ["ControllerTrajectory", "ReplayViolation", "first_violation", "replay", "select_points",
           "spline_coefficients"]
