"""Time parameterisation of joint-space paths with Ruckig (community edition), jerk-limited.

Ruckig's community edition times one state-to-state motion; multi-waypoint paths are timed segment by segment
(its waypoint API needs the cloud). The motion does not stop at every waypoint: each interior waypoint gets a
via velocity along the bisector of its two segments, scaled down with the turn angle (zero at a right angle or
more), and each segment is timed with phase synchronisation so that, when the boundary velocities are parallel
to the segment, the motion stays on the straight joint-space segment. The caller re-checks the timed motion for
collisions densely (:func:`first_invalid_sample`) and, where a blend leaves the planned path and collides, stops
at those waypoints instead (:func:`time_path` does this with ``is_valid``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Synchronization
from ruckig import Trajectory as RuckigTrajectory


@dataclass(frozen=True)
class JointLimits:
    velocity: np.ndarray  # rad/s
    acceleration: np.ndarray  # rad/s^2
    jerk: np.ndarray  # rad/s^3


@dataclass
class TimedPath:
    """A timed joint motion: Ruckig segments back to back. ``via_velocities`` (K, dof) at the waypoints."""

    waypoints: np.ndarray
    via_velocities: np.ndarray
    segments: list[RuckigTrajectory]
    durations: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.durations.sum())

    def sample(self, rate_hz: float = 1000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(t, q, qd, qdd) at ``rate_hz``, the last sample exactly at the end."""
        count = max(2, int(np.floor(self.duration * rate_hz)) + 1)
        times = np.linspace(0.0, self.duration, count) if self.duration > 0 else np.zeros(1)
        return (times, *self.at_times(times))

    def at_times(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        starts = np.concatenate([[0.0], np.cumsum(self.durations)])
        dof = self.waypoints.shape[1]
        q, qd, qdd = (np.empty((len(times), dof)) for _ in range(3))
        indices = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self.segments) - 1)
        for k, (t, segment_index) in enumerate(zip(times, indices)):
            local = min(max(t - starts[segment_index], 0.0), self.durations[segment_index])
            position, velocity, acceleration = self.segments[segment_index].at_time(local)
            q[k], qd[k], qdd[k] = position, velocity, acceleration
        return q, qd, qdd


def via_velocities(waypoints: np.ndarray, limits: JointLimits, speed_fraction: float = 0.6) -> np.ndarray:
    """Velocities at the waypoints: zero at the ends; inside, along the bisector of the two segment directions
    with a magnitude that falls from ``speed_fraction`` of the limits (straight on) to zero (turns of 90 degrees
    or more), and never more than what the shorter neighbouring segment can brake from."""
    count, dof = waypoints.shape
    velocities = np.zeros((count, dof))
    for k in range(1, count - 1):
        incoming, outgoing = waypoints[k] - waypoints[k - 1], waypoints[k + 1] - waypoints[k]
        n_in, n_out = np.linalg.norm(incoming), np.linalg.norm(outgoing)
        if n_in < 1e-9 or n_out < 1e-9:
            continue
        u_in, u_out = incoming / n_in, outgoing / n_out
        cos_turn = float(np.dot(u_in, u_out))
        if cos_turn <= 0.0:
            continue
        direction = u_in + u_out
        direction /= np.linalg.norm(direction)
        # fastest speed along `direction` within every joint's velocity limit
        speed = speed_fraction * cos_turn * float(np.min(limits.velocity / np.maximum(np.abs(direction), 1e-12)))
        # and slow enough to stop within the shorter segment (v^2 <= a * d, per joint, with margin)
        shortest = min(n_in, n_out)
        brake = float(np.min(np.sqrt(limits.acceleration * shortest * np.maximum(np.abs(direction), 1e-12))
                             / np.maximum(np.abs(direction), 1e-12)))
        velocities[k] = direction * min(speed, 0.5 * brake)
    return velocities


class StraightSegment:
    """A motion exactly along the joint-space segment ``q0 -> q1``: a one-dimensional Ruckig trajectory of the
    arc length ``s`` (rad) with limits scaled so that every joint keeps within its own, ``q = q0 + s * u``.
    Same interface as Ruckig's trajectory (``duration``, ``at_time``)."""

    def __init__(self, q0: np.ndarray, u: np.ndarray, length: float, s_velocity: tuple[float, float],
                 limits: JointLimits) -> None:
        self.q0, self.u = np.asarray(q0, dtype=np.float64), u
        scale = np.maximum(np.abs(u), 1e-12)
        inp = InputParameter(1)
        inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [s_velocity[0]], [0.0]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [length], [s_velocity[1]], [0.0]
        inp.max_velocity = [float(np.min(limits.velocity / scale))]
        inp.max_acceleration = [float(np.min(limits.acceleration / scale))]
        inp.max_jerk = [float(np.min(limits.jerk / scale))]
        self.trajectory = RuckigTrajectory(1)
        result = Ruckig(1).calculate(inp, self.trajectory)
        if result not in (Result.Working, Result.Finished):
            raise ValueError(f"Ruckig could not time a straight segment ({result})")

    @property
    def duration(self) -> float:
        return self.trajectory.duration

    def at_time(self, t: float):
        s, ds, dds = (value[0] for value in self.trajectory.at_time(t))
        return list(self.q0 + s * self.u), list(ds * self.u), list(dds * self.u)


def _along(v: np.ndarray, u: np.ndarray) -> float | None:
    """``v``'s speed along the unit vector ``u`` when ``v`` is parallel to it (or zero) and not backwards."""
    speed = float(np.dot(v, u))
    if speed < -1e-12 or np.linalg.norm(v - speed * u) > 1e-9 * max(1.0, abs(speed)):
        return None
    return max(speed, 0.0)


def _time_segment(q0, v0, q1, v1, limits: JointLimits):
    """A Ruckig trajectory from (q0, v0) to (q1, v1) at rest acceleration. When both velocities point along the
    segment (stops included) it stays exactly on it (:class:`StraightSegment`: Ruckig's phase synchronisation
    is not always possible and falls back to time synchronisation, which leaves the straight line)."""
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    length = float(np.linalg.norm(q1 - q0))
    if length > 1e-12:
        u = (q1 - q0) / length
        s0, s1 = _along(np.asarray(v0, dtype=np.float64), u), _along(np.asarray(v1, dtype=np.float64), u)
        if s0 is not None and s1 is not None:
            return StraightSegment(q0, u, length, (s0, s1), limits)
    dof = len(q0)
    inp = InputParameter(dof)
    inp.current_position, inp.current_velocity, inp.current_acceleration = list(q0), list(v0), [0.0] * dof
    inp.target_position, inp.target_velocity, inp.target_acceleration = list(q1), list(v1), [0.0] * dof
    inp.max_velocity = list(limits.velocity)
    inp.max_acceleration = list(limits.acceleration)
    inp.max_jerk = list(limits.jerk)
    inp.synchronization = Synchronization.Phase
    trajectory = RuckigTrajectory(dof)
    result = Ruckig(dof).calculate(inp, trajectory)
    if result not in (Result.Working, Result.Finished):
        raise ValueError(f"Ruckig could not time a segment ({result})")
    return trajectory


def time_waypoints(waypoints: np.ndarray, limits: JointLimits, velocities: np.ndarray) -> TimedPath:
    waypoints = np.asarray(waypoints, dtype=np.float64)
    segments = [_time_segment(waypoints[k], velocities[k], waypoints[k + 1], velocities[k + 1], limits)
                for k in range(len(waypoints) - 1)]
    return TimedPath(waypoints, velocities, segments, np.array([s.duration for s in segments]))


def first_invalid_sample(timed: TimedPath, is_valid: Callable[[np.ndarray], bool],
                         step_s: float = 0.004) -> tuple[int, float] | None:
    """(segment index, time) of the first sample (every ``step_s``) failing ``is_valid``, or None."""
    starts = np.concatenate([[0.0], np.cumsum(timed.durations)])
    times = np.arange(0.0, timed.duration + step_s, step_s)
    times[-1] = min(times[-1], timed.duration)
    q, _, _ = timed.at_times(times)
    for t, configuration in zip(times, q):
        if not is_valid(configuration):
            segment = int(np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(timed.segments) - 1))
            return segment, float(t)
    return None


def time_path(waypoints: Sequence[np.ndarray], limits: JointLimits,
              is_valid: Callable[[np.ndarray], bool] | None = None, max_repairs: int = 20) -> TimedPath:
    """Time a path without stopping at its waypoints; where the blended motion collides (checked densely with
    ``is_valid``), stop at the waypoints of the colliding segment and time again."""
    waypoints = np.asarray(waypoints, dtype=np.float64)
    if len(waypoints) < 2:
        raise ValueError("a path needs at least two waypoints")
    velocities = via_velocities(waypoints, limits)
    timed = time_waypoints(waypoints, limits, velocities)
    if is_valid is None:
        return timed
    for _ in range(max_repairs):
        hit = first_invalid_sample(timed, is_valid)
        if hit is None:
            return timed
        segment = hit[0]
        if not np.any(velocities[segment]) and not np.any(velocities[segment + 1]):
            break  # already stopping at both ends: the straight segment itself is invalid
        velocities[segment] = 0.0
        velocities[segment + 1] = 0.0
        timed = time_waypoints(waypoints, limits, velocities)
    hit = first_invalid_sample(timed, is_valid)
    if hit is not None:
        raise ValueError(f"the timed motion collides at t = {hit[1]:.3f} s in segment {hit[0]} even when stopping "
                         "at its waypoints: the path itself is not collision-free")
    return timed
