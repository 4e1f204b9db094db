"""Time parameterisation of joint-space paths with Ruckig (community edition), jerk-limited.

Ruckig's community edition times one state-to-state motion; multi-waypoint paths are timed piece by piece (its
waypoint API needs the cloud). The motion does not stop at every waypoint: it follows each straight joint-space
segment exactly (a one-dimensional Ruckig profile of the arc length, :class:`StraightSegment`) and rounds each
interior waypoint with a short blend: from a point ``distance`` before the waypoint, moving along the incoming
segment at ``speed``, to the point ``distance`` after it, moving along the outgoing segment at the same speed (a
time-synchronised Ruckig motion). Per waypoint, the blend distance and speed are chosen from a few candidates to
make the motion quickest while the blend stays within ``max_deviation_rad`` of the planned path
(:func:`plan_corners`). The caller re-checks the timed motion for collisions densely (:func:`first_invalid_sample`)
and, where a blend collides, blends closer to the waypoint and finally stops there (:func:`time_path` does this
with ``is_valid`` or ``first_invalid``).

Units: radians, seconds; limits per joint (rad/s, rad/s^2, rad/s^3).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, RuckigError, Synchronization
from ruckig import Trajectory as RuckigTrajectory


@dataclass(frozen=True)
class JointLimits:
    velocity: np.ndarray  # rad/s
    acceleration: np.ndarray  # rad/s^2
    jerk: np.ndarray  # rad/s^3

    def slowed(self, factor: float) -> JointLimits:
        """The limits under which every motion timed within these is timed ``1 / factor`` times slower (velocity x
        factor, acceleration x factor^2, jerk x factor^3); ``factor`` in (0, 1]."""
        if not 0.0 < factor <= 1.0:
            raise ValueError(f"a slow-down factor must lie in (0, 1], got {factor}")
        return JointLimits(self.velocity * factor, self.acceleration * factor ** 2, self.jerk * factor ** 3)


@dataclass
class TimedPath:
    """A timed joint motion: Ruckig pieces back to back. ``waypoints`` (K, dof) are the pieces' end points (the
    planned waypoints where the motion stops there, the ends of each blend where it does not) and
    ``via_velocities`` (K, dof) the velocities there; ``durations`` (K-1,) seconds per piece."""

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


MAX_DEVIATION_RAD = 0.05  # how far (joint-space distance) a blend may leave the planned path
SPEED_FRACTIONS = (1.0, 0.8, 0.6, 0.45, 0.3, 0.2, 0.1)  # blend speeds tried, of the fastest along both segments
DISTANCE_FRACTIONS = (1.0, 0.6, 0.35, 0.2, 0.1)  # blend distances tried, of 49% of the shorter neighbouring segment
_DEVIATION_SAMPLES = 12  # samples per blend when measuring how far it leaves the path
_SWEEPS = 2  # coordinate-descent passes over the waypoints


@dataclass(frozen=True)
class Corner:
    """How the motion passes an interior waypoint: along a blend that starts ``distance_rad`` before it on the
    incoming segment and ends ``distance_rad`` after it on the outgoing one, at ``speed`` (rad/s of joint-space
    arc length) at both ends; a stop at the waypoint when ``speed`` is 0."""

    distance_rad: float = 0.0
    speed: float = 0.0

    @property
    def stops(self) -> bool:
        return self.speed <= 0.0 or self.distance_rad <= 0.0


STOP = Corner()


def _directions(waypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (K-1, dof) and lengths (K-1,) of the segments."""
    steps = np.diff(waypoints, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    return steps / np.maximum(lengths, 1e-12)[:, None], lengths


def _fastest(direction: np.ndarray, limits: JointLimits) -> float:
    """The fastest arc-length speed along ``direction`` within every joint's velocity limit (a hair below: Ruckig
    refuses a target velocity equal to its limit after rounding)."""
    return (1.0 - 1e-6) * float(np.min(limits.velocity / np.maximum(np.abs(direction), 1e-12)))


def _breakpoints(waypoints: np.ndarray, corners: Sequence[Corner]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The points where pieces meet (P, dof), the velocities there (P, dof) and, per piece, the index of the
    corner it blends (or -1 for a straight piece). ``corners[k]`` belongs to waypoint k (ends ignored)."""
    units, _ = _directions(waypoints)
    points, velocities, blends = [waypoints[0]], [np.zeros(waypoints.shape[1])], []
    for k in range(1, len(waypoints) - 1):
        corner = corners[k]
        if corner.stops:
            points.append(waypoints[k])
            velocities.append(np.zeros(waypoints.shape[1]))
            blends.append(-1)
            continue
        points += [waypoints[k] - corner.distance_rad * units[k - 1], waypoints[k] + corner.distance_rad * units[k]]
        velocities += [corner.speed * units[k - 1], corner.speed * units[k]]
        blends += [-1, k]
    points.append(waypoints[-1])
    velocities.append(np.zeros(waypoints.shape[1]))
    blends.append(-1)
    return np.array(points), np.array(velocities), blends


def _distance_to_polyline(points: np.ndarray, polyline: Sequence[np.ndarray]) -> np.ndarray:
    """(N,) joint-space distance (rad) from each of ``points`` (N, dof) to the polyline through ``polyline``."""
    best = np.full(len(points), np.inf)
    for a, b in zip(polyline[:-1], polyline[1:]):
        direction = b - a
        s = np.clip((points - a) @ direction / max(float(direction @ direction), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - a - s[:, None] * direction, axis=1))
    return best


def _blend_deviation(trajectory, start: np.ndarray, corner: np.ndarray, end: np.ndarray) -> float:
    """Largest distance (rad) from samples of a blend to the path it replaces, start -> corner -> end."""
    times = np.linspace(0.0, trajectory.duration, _DEVIATION_SAMPLES + 2)[1:-1]
    samples = np.array([trajectory.at_time(t)[0] for t in times])
    return float(_distance_to_polyline(samples, (start, corner, end)).max())


def _stays_on_segment(piece) -> bool:
    """Whether a straight piece's arc length stays within [0, length] (no overshoot past its ends)."""
    if not isinstance(piece, StraightSegment):
        return True
    extrema = piece.trajectory.position_extrema[0]
    return extrema.min >= -1e-9 and extrema.max <= piece.length + 1e-9


def plan_corners(waypoints: np.ndarray, limits: JointLimits, max_deviation_rad: float = MAX_DEVIATION_RAD,
                 allowed: Sequence[float] | None = None) -> list[Corner]:
    """A :class:`Corner` per waypoint (stops at the ends): per interior waypoint, the blend distance (a fraction in
    :data:`DISTANCE_FRACTIONS` of 49% of the shorter neighbouring segment, at most ``allowed[k]`` when given) and
    speed (a fraction in :data:`SPEED_FRACTIONS` of the fastest along both segments), refined by a pattern search,
    that make the pieces around it quickest while the blend stays within ``max_deviation_rad`` of the path and the
    straight pieces do not overshoot; or a stop. Coordinate descent over the waypoints, starting from stops
    everywhere."""
    waypoints = np.asarray(waypoints, dtype=np.float64)
    count = len(waypoints)
    units, lengths = _directions(waypoints)
    corners = [STOP] * count

    def local_cost(k: int) -> float:
        """Duration of the pieces from waypoint k-1's blend end to waypoint k+1's blend start, inf if infeasible."""
        first, last = max(k - 1, 0), min(k + 1, count - 1)
        points, velocities, blends = _breakpoints(waypoints[first:last + 1], [STOP] + corners[first + 1:last] + [STOP])
        # the window's ends: where the neighbours' blends end/start (their own blends are not part of the window)
        if first > 0 and not corners[first].stops:
            points[0] = waypoints[first] + corners[first].distance_rad * units[first]
            velocities[0] = corners[first].speed * units[first]
        if last < count - 1 and not corners[last].stops:
            points[-1] = waypoints[last] - corners[last].distance_rad * units[last - 1]
            velocities[-1] = corners[last].speed * units[last - 1]
        total = 0.0
        for i, blend in enumerate(blends):
            piece = _feasible_piece(points, velocities, i, None if blend < 0 else waypoints[first + blend], limits,
                                    max_deviation_rad)
            if piece is None:
                return np.inf
            total += piece.duration
        return total

    for _ in range(_SWEEPS):
        for k in range(1, count - 1):
            if lengths[k - 1] < 1e-9 or lengths[k] < 1e-9 or float(units[k - 1] @ units[k]) < -0.999:
                continue  # a repeated waypoint or a reversal: stop there
            room = 0.49 * min(lengths[k - 1], lengths[k])  # neighbouring blends never meet
            if allowed is not None:
                room = min(room, allowed[k])
            fastest = min(_fastest(units[k - 1], limits), _fastest(units[k], limits))
            best_corner, best = STOP, np.inf
            for candidate in [STOP] + [Corner(room * d, fastest * f) for d in DISTANCE_FRACTIONS
                                       for f in SPEED_FRACTIONS if room * d > 1e-6]:
                corners[k] = candidate
                cost = local_cost(k)
                if cost < best - 1e-9:
                    best_corner, best = candidate, cost
            # then a pattern search around the best blend: distance and speed up and down, steps halving
            step = 0.25
            while not best_corner.stops and step > 0.02:
                improved = False
                for scale_d, scale_s in ((1 + step, 1.0), (1 - step, 1.0), (1.0, 1 + step), (1.0, 1 - step)):
                    candidate = Corner(min(room, best_corner.distance_rad * scale_d),
                                       min(fastest, best_corner.speed * scale_s))
                    corners[k] = candidate
                    cost = local_cost(k)
                    if cost < best - 1e-9:
                        best_corner, best, improved = candidate, cost, True
                if not improved:
                    step /= 2
            corners[k] = best_corner
    # a corner whose every choice was infeasible kept its stop while a neighbour's blend, chosen before, relies
    # on it not stopping (e.g. a straight piece entering a stop too fast to halt on it): stop there too
    for _ in range(count):
        points, velocities, blends = _breakpoints(waypoints, corners)
        bad = next((i for i, blend in enumerate(blends) if _feasible_piece(
            points, velocities, i, None if blend < 0 else waypoints[blend], limits, max_deviation_rad) is None), None)
        if bad is None:
            break
        culprits = [k for k in _corners_of_piece(waypoints, corners, bad) if not corners[k].stops]
        if not culprits:
            raise ValueError(f"piece {bad} of a path stopping at its waypoints cannot be timed")
        for k in culprits:
            corners[k] = STOP
    return corners


def _feasible_piece(points: np.ndarray, velocities: np.ndarray, i: int, corner: np.ndarray | None,
                    limits: JointLimits, max_deviation_rad: float):
    """Piece ``i`` from ``points[i]`` to ``points[i + 1]`` timed by Ruckig, or None where it is infeasible: Ruckig
    fails, a straight piece overshoots its ends or leaves its line, or a blend (around ``corner``, None for a
    straight piece) strays more than ``max_deviation_rad`` from the path."""
    try:
        piece = _time_segment(points[i], velocities[i], points[i + 1], velocities[i + 1], limits)
    except (ValueError, RuckigError):
        return None
    if corner is None:
        if not _stays_on_segment(piece):
            return None
        if not isinstance(piece, StraightSegment) and _blend_deviation(
                piece, points[i], points[i], points[i + 1]) > max_deviation_rad:
            return None  # a straight piece Ruckig could not keep on its line (e.g. of zero length)
        return piece
    if _blend_deviation(piece, points[i], corner, points[i + 1]) > max_deviation_rad:
        return None
    return piece


def time_corners(waypoints: np.ndarray, limits: JointLimits, corners: Sequence[Corner]) -> TimedPath:
    """The motion along ``waypoints`` with the given corners: straight pieces and blends back to back. The
    result's ``waypoints`` and ``via_velocities`` are the pieces' end points and the velocities there."""
    waypoints = np.asarray(waypoints, dtype=np.float64)
    points, velocities, _ = _breakpoints(waypoints, corners)
    return time_waypoints(points, limits, velocities)


class StraightSegment:
    """A motion exactly along the joint-space segment ``q0 -> q1``: a one-dimensional Ruckig trajectory of the
    arc length ``s`` (rad) with limits scaled so that every joint keeps within its own, ``q = q0 + s * u``.
    Same interface as Ruckig's trajectory (``duration``, ``at_time``)."""

    def __init__(self, q0: np.ndarray, u: np.ndarray, length: float, s_velocity: tuple[float, float],
                 limits: JointLimits) -> None:
        self.q0, self.u, self.length = np.asarray(q0, dtype=np.float64), u, float(length)
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


def first_invalid_sample(timed: TimedPath, is_valid: Callable[[np.ndarray], bool] | None = None,
                         step_s: float = 0.004, first_invalid: Callable[[np.ndarray], int | None] | None = None,
                         from_segment: int = 0) -> tuple[int, float] | None:
    """(segment index, time) of the first sample (every ``step_s`` seconds, from the start of segment
    ``from_segment``) failing ``is_valid``, or None. ``first_invalid(qs)``, when given, checks all samples (N, dof)
    at once and returns the index of the first invalid one (or None), e.g.
    :meth:`planning.robot_collision.RobotCollisionChecker.first_invalid`."""
    starts = np.concatenate([[0.0], np.cumsum(timed.durations)])
    times = np.arange(starts[from_segment], timed.duration + step_s, step_s)
    times[-1] = min(times[-1], timed.duration)
    q, _, _ = timed.at_times(times)
    if first_invalid is not None:
        index = first_invalid(q)
    else:
        index = next((i for i, configuration in enumerate(q) if not is_valid(configuration)), None)
    if index is None:
        return None
    t = float(times[index])
    return int(np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(timed.segments) - 1)), t


def _corners_of_piece(waypoints: np.ndarray, corners: Sequence[Corner], piece: int) -> list[int]:
    """The interior waypoints whose passing piece ``piece`` of the motion belongs to: the blended corner, or, for a
    straight piece, the corners at its two ends."""
    _, _, blends = _breakpoints(waypoints, corners)
    if blends[piece] >= 0:
        return [blends[piece]]
    # a straight piece lies on original segment k: count the original waypoints passed before it
    passed = sum(1 for b in blends[:piece] if b < 0)  # straight pieces before this one = segments started
    return [k for k in (passed, passed + 1) if 0 < k < len(waypoints) - 1]


def first_over_limits(timed: TimedPath, lower: np.ndarray, upper: np.ndarray) -> tuple[int, float] | None:
    """(segment index, time from the start) of the first piece of ``timed`` whose exact position extrema (Ruckig's)
    leave [lower, upper] (rad), or None. Straight pieces stay between their end points."""
    start = 0.0
    for index, segment in enumerate(timed.segments):
        if not isinstance(segment, StraightSegment):
            for j, extremum in enumerate(segment.position_extrema):
                if extremum.min < lower[j] - 1e-12 or extremum.max > upper[j] + 1e-12:
                    t = extremum.t_min if extremum.min < lower[j] - 1e-12 else extremum.t_max
                    return index, start + float(t)
        start += float(timed.durations[index])
    return None


def _check_within(waypoints: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
    """Raise ValueError naming the first waypoint and joint outside [lower, upper] (rad)."""
    outside = (waypoints < lower - 1e-12) | (waypoints > upper + 1e-12)
    if outside.any():
        k, j = np.argwhere(outside)[0]
        raise ValueError(f"waypoint {k} has joint {j + 1} at {waypoints[k, j]:.4f} rad, outside its limits "
                         f"{lower[j]:.4f} .. {upper[j]:.4f}")


def time_path(waypoints: Sequence[np.ndarray], limits: JointLimits,
              is_valid: Callable[[np.ndarray], bool] | None = None, max_repairs: int = 60,
              first_invalid: Callable[[np.ndarray], int | None] | None = None,
              max_deviation_rad: float = MAX_DEVIATION_RAD,
              position_limits: tuple[np.ndarray, np.ndarray] | None = None,
              stops: Sequence[int] = ()) -> TimedPath:
    """Time a path without stopping at its waypoints (blends from :func:`plan_corners`). With ``is_valid`` (one
    configuration) or ``first_invalid`` (a batch, see :func:`first_invalid_sample`), the timed motion is re-checked
    densely; where a blend collides, that corner's blend distance is halved (and its speed chosen again), and after
    two halvings the motion stops at the waypoint; then the path is timed again.

    ``position_limits`` (lower, upper; rad): a blend that overshoots a joint's position limit (a path running along
    the limit) is treated like one that collides. The waypoints themselves must lie within the limits; the straight
    pieces between them then do too. ``stops``: indices of interior waypoints where the motion must come to rest
    (a corner the path turns at to touch something, which no blend may cut)."""
    waypoints = np.asarray(waypoints, dtype=np.float64)
    if len(waypoints) < 2:
        raise ValueError("a path needs at least two waypoints")
    bounds = None
    if position_limits is not None:
        bounds = tuple(np.asarray(b, dtype=np.float64) for b in position_limits)
        _check_within(waypoints, *bounds)
    checked = is_valid is not None or first_invalid is not None
    stopped = set(stops)
    allowed = [0.0 if k in stopped else np.inf for k in range(len(waypoints))]
    corners = plan_corners(waypoints, limits, max_deviation_rad, allowed=allowed)
    timed = time_corners(waypoints, limits, corners)
    if not checked and bounds is None:
        return timed

    def find_hit(current: TimedPath) -> tuple[int, float] | None:
        """The earliest (piece, time) that collides (sampled) or leaves the position limits (exactly)."""
        hits = [first_invalid_sample(current, is_valid, first_invalid=first_invalid) if checked else None,
                first_over_limits(current, *bounds) if bounds is not None else None]
        hits = [h for h in hits if h is not None]
        return min(hits, key=lambda h: h[1]) if hits else None

    allowed = [0.0 if a <= 0.0 else c.distance_rad for c, a in zip(corners, allowed)]
    shrunk = [0] * len(waypoints)
    for _ in range(max_repairs):
        hit = find_hit(timed)
        if hit is None:
            return timed
        culprits = [k for k in _corners_of_piece(waypoints, corners, hit[0]) if not corners[k].stops]
        if not culprits:
            break  # a straight piece between stops collides: the path itself is invalid
        for k in culprits:
            shrunk[k] += 1
            allowed[k] = 0.0 if shrunk[k] > 2 else 0.5 * corners[k].distance_rad
        corners = plan_corners(waypoints, limits, max_deviation_rad, allowed=allowed)
        corners = [STOP if a <= 0.0 else c for c, a in zip(corners, allowed)]
        timed = time_corners(waypoints, limits, corners)
    hit = find_hit(timed)
    if hit is not None:
        raise ValueError(f"the timed motion collides at t = {hit[1]:.3f} s in segment {hit[0]} even when stopping "
                         "at its waypoints: the path itself is not collision-free")
    return timed
