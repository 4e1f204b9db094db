"""Joint-space motion planning with OMPL (RRTConnect by default) and a caller-given validity check.

Pure planning: the validity check is a function of the 7 joint values (e.g.
:meth:`planning.robot_collision.RobotCollisionChecker.is_valid`); the result is a path of waypoints (K, 7) in
radians. Failures are typed (:class:`MotionPlanningError` with ``kind``) so the cell can name the step.

Edges (straight joint-space segments) are checked either by OMPL's discrete motion validator, every
``check_resolution`` of the joint-space diagonal, or, when the caller passes ``segment_valid(q_from, q_to)``
(e.g. :meth:`planning.robot_collision.RobotCollisionChecker.segment_valid`, which spaces its checks by how far
the robot's points move and checks a whole edge in one vectorised batch), by that function.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

PLANNERS = ("RRTConnect", "RRT", "RRTstar", "PRM", "KPIECE1", "BKPIECE1", "LBKPIECE1", "BITstar")
# planners that check edges only with the two-state checkMotion (the one a Python motion validator overrides); the
# KPIECE family also asks for the last valid state of an edge, so it keeps OMPL's discrete validator
_SEGMENT_VALIDATOR_PLANNERS = frozenset({"RRTConnect", "RRT", "RRTstar", "PRM", "BITstar"})
# OMPL seeds every generator it makes (a planner's, its sampler's, its nearest-neighbour structure's, the
# simplifier's) from one sequence per process. A query restarts that sequence from a seed of its own and holds it
# until it ends, so that its path depends on the query alone, not on the searches made before it in the process.
_sequence_lock = threading.RLock()


class MotionPlanningError(RuntimeError):
    """``kind`` is one of "start_in_collision", "goal_in_collision", "timeout", "invalid_request"."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class MotionSettings:
    planner: str = "RRTConnect"
    # a search ends after this much of its own work: where plan_joint_path is given a count of the work done
    # (``work``, e.g. planning.robot_collision.checking_work_s), that count, the same on any machine, busy or idle;
    # else CPU seconds of the thread it runs on (cut off by the clock, searches on a machine running two plans side
    # by side failed where the same plan alone found its paths; by CPU time, they still ended at other points there)
    time_limit_s: float = 5.0
    # ... or after this many seconds by the clock, whichever comes first (None: no bound): a bound for a machine so
    # busy that the search's thread seldom runs
    wall_limit_s: float | None = 40.0
    # fraction of the joint-space diagonal between validity checks along edges (OMPL's resolution) where no
    # segment_valid is given, or for the KPIECE planners; the Panda's diagonal is about 14 rad, so 0.001 checks
    # every 0.014 rad (up to a centimetre at the hand)
    check_resolution: float = 0.001
    simplify: bool = True  # shorten the path (see _simplify)
    seed: int = 0  # with each query's start and goal, the seed of its searches (query_seed)
    # searches of time_limit_s each before a query fails, each growing new random trees: one search that runs out
    # of time through a narrow passage is no proof that there is no path
    searches: int = 2


def _ompl():
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_WARN)
    return ob, og, ou


def available_planners() -> tuple[str, ...]:
    """The planners of :data:`PLANNERS` that the installed OMPL provides (what ``MotionSettings.planner`` may
    name)."""
    _, og, _ = _ompl()
    return tuple(name for name in PLANNERS if hasattr(og, name))


def query_seed(seed: int, start_q: np.ndarray, goal_q: np.ndarray) -> int:
    """The seed of OMPL's sequence for one query: from ``seed`` (:attr:`MotionSettings.seed`) and the query's start
    and goal configurations (radians, to the last bit), in [1, 2**31 - 1], the same in every process."""
    digest = hashlib.blake2b(digest_size=8)
    digest.update(int(seed).to_bytes(8, "little", signed=True))
    for q in (start_q, goal_q):
        digest.update(np.ascontiguousarray(q, dtype="<f8").tobytes())
    return 1 + int.from_bytes(digest.digest(), "little") % (2**31 - 1)


@contextmanager
def _seeded_sequence(ou, seed: int) -> Iterator[None]:
    """OMPL's seed sequence restarted from ``seed`` and held by this thread until the block ends. (OMPL logs an
    error when its sequence is restarted after use, since generators made before it are not affected; each query
    makes its own, so that message is kept out of the log.)"""
    with _sequence_lock:
        level = ou.getLogLevel()
        ou.setLogLevel(ou.LOG_NONE)
        try:
            ou.RNG.setSeed(seed)
        finally:
            ou.setLogLevel(level)
        yield


def first_invalid_on_line(is_valid: Callable[[np.ndarray], bool], q_from: np.ndarray, q_to: np.ndarray,
                          step_rad: float = 0.01) -> np.ndarray | None:
    """The first invalid configuration on the straight joint-space segment (checked every ``step_rad`` from
    ``q_from``), or None."""
    distance = float(np.max(np.abs(np.asarray(q_to) - np.asarray(q_from))))
    steps = max(1, int(np.ceil(distance / step_rad)))
    return next((q for q in (q_from + (q_to - q_from) * (k / steps) for k in range(steps + 1)) if not is_valid(q)),
                None)


def straight_line_valid(is_valid: Callable[[np.ndarray], bool], q_from: np.ndarray, q_to: np.ndarray,
                        step_rad: float = 0.01) -> bool:
    """Whether every configuration on the straight joint-space segment (checked every ``step_rad``) is valid."""
    return first_invalid_on_line(is_valid, q_from, q_to, step_rad) is None


def _segment_validator(ob, information, segment_valid: Callable[[np.ndarray, np.ndarray], bool], dof: int):
    """An OMPL motion validator that hands each edge to ``segment_valid`` (its start state is valid)."""

    class SegmentValidator(ob.MotionValidator):
        def checkMotion(self, s1, s2, *last_valid):  # OMPL's method name
            if last_valid:
                raise NotImplementedError("this motion validator does not report the last valid state")
            return bool(segment_valid(np.array([s1[i] for i in range(dof)]), np.array([s2[i] for i in range(dof)])))

    return SegmentValidator(information)


def _simplify(og, information, path) -> None:
    """Shorten ``path`` in place: drop vertices whose neighbours see each other, pull the path taut (OMPL's rope
    shortcutting), drop vertices again. Every new edge is checked by the space's motion validator. About as short as
    OMPL's full ``simplify`` (which adds B-spline smoothing and repeated passes) on the pick-and-place benchmark, at
    a third of its checks (benchmarks/motion.py)."""
    simplifier = og.PathSimplifier(information)
    simplifier.reduceVertices(path)
    simplifier.ropeShortcutPath(path)
    simplifier.reduceVertices(path)


# with a count of the work, a search also ends after this many times its limit in CPU seconds of its thread: a
# backstop for work the count leaves out
CPU_BACKSTOP = 4.0


class _SearchBudget:
    """One search's time, started by ``start()``: ``spent()`` once ``work()`` has grown by ``limit_s`` (where
    given), or its thread has worked ``limit_s`` seconds (``CPU_BACKSTOP`` times that where ``work`` is given; the
    search runs on the thread that calls OMPL's solve, its validity checks too), or ``wall_s`` seconds have passed
    by the clock (None: never). ``ended_by`` says which ended it: "work", "cpu" or "clock"."""

    def __init__(self, limit_s: float, wall_s: float | None, work: Callable[[], float] | None = None) -> None:
        self.limit_s, self.wall_s, self.work = limit_s, wall_s, work
        self.cpu_s = limit_s if work is None else CPU_BACKSTOP * limit_s
        self.start()

    def start(self) -> None:
        self.cpu_started, self.wall_started, self.ended_by = time.thread_time(), time.perf_counter(), None
        self.work_started = self.work() if self.work is not None else 0.0

    def spent(self) -> bool:
        if self.work is not None and self.work() - self.work_started > self.limit_s:
            self.ended_by = "work"
        elif time.thread_time() - self.cpu_started > self.cpu_s:
            self.ended_by = "cpu"
        elif self.wall_s is not None and time.perf_counter() - self.wall_started > self.wall_s:
            self.ended_by = "clock"
        return self.ended_by is not None

    def words(self, searches: int) -> str:
        """Within what the searches ran out, as the failure says it."""
        if self.ended_by == "clock":
            within = f"within {self.wall_s:.1f} s by the clock (the machine is busy)"
        elif self.ended_by == "work":
            within = f"within {self.limit_s:.1f} s of searching, counted in collision checks"
        else:
            within = f"within {self.cpu_s:.1f} s of searching"
        return within + (f", in each of {searches} searches" if searches > 1 else "")


def plan_joint_path(is_valid: Callable[[np.ndarray], bool], start_q: np.ndarray, goal_q: np.ndarray,
                    lower: np.ndarray, upper: np.ndarray, settings: MotionSettings = MotionSettings(),
                    segment_valid: Callable[[np.ndarray, np.ndarray], bool] | None = None,
                    work: Callable[[], float] | None = None) -> np.ndarray:
    """A collision-free path (K, 7) from ``start_q`` to ``goal_q`` within [lower, upper], or raise.

    ``is_valid(q)``: whether one configuration (7,) radians is free. ``segment_valid(q_from, q_to)``, optional:
    whether the straight segment between two configurations is free (``q_from`` known valid); when given it checks
    the straight start-goal shortcut and every edge of the planners that allow it (RRTConnect, RRT, RRTstar, PRM,
    BITstar), instead of single states every ``settings.check_resolution``. ``work()``, optional: the work done so
    far on this thread, in seconds as a reference machine takes for it (e.g.
    :func:`planning.robot_collision.checking_work_s`); when given, each search ends after ``settings.time_limit_s``
    of it, so that the same query plans the same path on any machine however busy (the seeds alike), rather than
    after as many CPU seconds. The searches are seeded from ``settings.seed`` and the query (:func:`query_seed`): the
    same query in the same world plans the same path, whatever was planned before it in the process."""
    start_q, goal_q = np.asarray(start_q, dtype=np.float64), np.asarray(goal_q, dtype=np.float64)
    if settings.planner not in PLANNERS:
        raise MotionPlanningError("invalid_request", f"unknown planner {settings.planner!r}; choose one of {PLANNERS}")
    for label, q in (("start", start_q), ("goal", goal_q)):
        if np.any(q < lower - 1e-9) or np.any(q > upper + 1e-9):
            raise MotionPlanningError("invalid_request", f"{label} configuration {np.round(q, 3).tolist()} is "
                                                         "outside the joint limits")
    if not is_valid(start_q):
        raise MotionPlanningError("start_in_collision", "the start configuration is in collision")
    if not is_valid(goal_q):
        raise MotionPlanningError("goal_in_collision", "the goal configuration is in collision")
    direct = segment_valid(start_q, goal_q) if segment_valid else straight_line_valid(is_valid, start_q, goal_q)
    if direct:
        return np.stack([start_q, goal_q])
    ob, og, ou = _ompl()
    with _seeded_sequence(ou, query_seed(settings.seed, start_q, goal_q)):
        return _search(ob, og, is_valid, start_q, goal_q, lower, upper, settings, segment_valid, work)


def _search(ob, og, is_valid: Callable[[np.ndarray], bool], start_q: np.ndarray, goal_q: np.ndarray,
            lower: np.ndarray, upper: np.ndarray, settings: MotionSettings,
            segment_valid: Callable[[np.ndarray, np.ndarray], bool] | None,
            work: Callable[[], float] | None) -> np.ndarray:
    """:func:`plan_joint_path`'s OMPL search, once the query is known valid and its straight segment blocked."""
    dof = len(start_q)
    space = ob.RealVectorStateSpace(dof)
    bounds = ob.RealVectorBounds(dof)
    for i in range(dof):
        bounds.setLow(i, float(lower[i]))
        bounds.setHigh(i, float(upper[i]))
    space.setBounds(bounds)
    setup = og.SimpleSetup(space)
    setup.setStateValidityChecker(lambda state: bool(is_valid(np.array([state[i] for i in range(dof)]))))
    information = setup.getSpaceInformation()
    information.setStateValidityCheckingResolution(settings.check_resolution)
    validator = None  # this name keeps the Python validator alive while OMPL uses it
    if segment_valid is not None and settings.planner in _SEGMENT_VALIDATOR_PLANNERS:
        validator = _segment_validator(ob, information, segment_valid, dof)
        information.setMotionValidator(validator)
    start, goal = space.allocState(), space.allocState()
    for i in range(dof):
        start[i], goal[i] = float(start_q[i]), float(goal_q[i])
    setup.setStartAndGoalStates(start, goal)
    setup.setPlanner(getattr(og, settings.planner)(information))
    budget = _SearchBudget(settings.time_limit_s, settings.wall_limit_s, work)
    for _ in range(max(1, settings.searches)):
        budget.start()
        solved = setup.solve(ob.PlannerTerminationCondition(budget.spent))
        if solved and "Exact" in str(solved):
            break
        # the next search grows its trees afresh, with a new planner: its random numbers come from a seed of their
        # own, not from where this search's stream stopped (which depends on how far it got in its time)
        setup.clear()
        setup.setPlanner(getattr(og, settings.planner)(information))
    else:
        raise MotionPlanningError("timeout", f"{settings.planner} found no path {budget.words(settings.searches)}")
    path = setup.getSolutionPath()
    if settings.simplify:
        _simplify(og, information, path)
    waypoints = np.array([[path.getState(k)[i] for i in range(dof)] for k in range(path.getStateCount())])
    waypoints[0], waypoints[-1] = start_q, goal_q
    return waypoints
