"""Validity checks of arm configurations, ``q -> bool`` (radians), and their combinations, as the motion planner
(:func:`planning.motion.plan_joint_path`), the straight-line solver and the timing take them.

:class:`Validity` asks a :class:`planning.robot_collision.RobotCollisionChecker` about its world as it is (skipping
obstacles by name) and, while a part is held, whether the arm holds its weight; :class:`AllValid` and
:class:`ClearExceptNearEnds` combine checks. Each has ``first_invalid(qs)``, the same answers batched, which
:func:`dense_path_valid` uses to re-check a whole path at once.
"""

from __future__ import annotations

import numpy as np

from planning.motion import straight_line_valid
from planning.payload import JointTorques
from planning.robot_collision import RobotCollisionChecker

TORQUE_CHECK_RAD = 0.05  # joint step of the holding-torque check along a segment (the torques vary slowly)


def with_dense_check(valid, step_rad: float):
    """``valid.segment``, each edge also re-checked every ``step_rad`` (per joint) as :func:`dense_path_valid`
    re-checks a planned path."""

    def segment(q_from: np.ndarray, q_to: np.ndarray) -> bool:
        return bool(valid.segment(q_from, q_to)) and dense_path_valid(valid, np.stack([q_from, q_to]), step_rad)

    return segment


def dense_path_valid(valid, path: np.ndarray, step_rad: float) -> bool:
    """Whether every configuration on the straight joint segments of ``path`` (K, 7), checked every ``step_rad``,
    is valid; in one batched query where ``valid`` has ``first_invalid``."""
    first_invalid = getattr(valid, "first_invalid", None)
    if first_invalid is None:
        return all(straight_line_valid(valid, a, b, step_rad=step_rad) for a, b in zip(path[:-1], path[1:]))
    samples = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        steps = max(1, int(np.ceil(float(np.max(np.abs(b - a))) / step_rad)))
        samples.append(a + (b - a) * (np.arange(1, steps + 1) / steps)[:, None])
    return first_invalid(np.concatenate(samples)) is None


class Validity:
    """``q -> bool`` against a checker's world skipping ``ignore`` (and ``held_ignore`` for the held part only);
    ``segment(a, b)`` checks a straight joint segment densely (no point of the robot or the held part moves more
    than 2 mm between checks)."""

    def __init__(self, checker: RobotCollisionChecker, ignore: frozenset[str],
                 held_ignore: frozenset[str] = frozenset(), load: JointTorques | None = None,
                 hand_ignore: frozenset[str] = frozenset()) -> None:
        self.checker, self.ignore, self.held_ignore = checker, frozenset(ignore), frozenset(held_ignore)
        self.hand_ignore = frozenset(hand_ignore)
        self.load = load  # the held part's weight: a configuration must also hold it (JointTorques.within)

    def __call__(self, q) -> bool:
        q = np.asarray(q, dtype=np.float64)
        return (self.load is None or bool(self.load.within(q[None])[0])) and self.checker.is_valid(
            q, ignore=self.ignore, held_ignore=self.held_ignore, hand_ignore=self.hand_ignore)

    def segment(self, q_from, q_to) -> bool:
        q_from, q_to = np.asarray(q_from, dtype=np.float64), np.asarray(q_to, dtype=np.float64)
        if self.load is not None:
            steps = max(1, int(np.ceil(float(np.max(np.abs(q_to - q_from))) / TORQUE_CHECK_RAD)))
            if not np.all(self.load.within(q_from + (q_to - q_from) * (np.arange(steps + 1) / steps)[:, None])):
                return False
        return self.checker.segment_valid(q_from, q_to, ignore=self.ignore, held_ignore=self.held_ignore,
                                          hand_ignore=self.hand_ignore)

    def first_invalid(self, qs) -> int | None:
        """Index of the first invalid configuration of ``qs`` (N, 7), or None: the same answers as calling this
        object on each, with forward kinematics and the broad phase batched."""
        qs = np.asarray(qs, dtype=np.float64)
        end = len(qs)
        if self.load is not None:
            heavy = np.flatnonzero(~self.load.within(qs))
            end = int(heavy[0]) if len(heavy) else end
        found = self.checker.first_invalid(qs[:end], ignore=self.ignore, held_ignore=self.held_ignore,
                                           hand_ignore=self.hand_ignore)
        return found if found is not None else (end if end < len(qs) else None)


class ClearExceptNearEnds:
    """``q -> bool`` for moves whose ends lie closer to something than a clearance (a retreat that ends near a
    placed part): ``exact`` within ``radius_rad`` (joint-space distance) of either of the ``ends``, ``clear`` (the
    check with the clearance) everywhere else. ``clear`` needs ``first_invalid``."""

    def __init__(self, clear, exact, ends: tuple[np.ndarray, ...], radius_rad: float) -> None:
        self.clear, self.exact, self.radius_rad = clear, exact, radius_rad
        self.ends = np.array(ends, dtype=np.float64)

    def __call__(self, q) -> bool:
        if self.clear(q):
            return True
        near = float(np.min(np.linalg.norm(self.ends - np.asarray(q, dtype=np.float64), axis=1))) <= self.radius_rad
        return near and self.exact(q)

    def first_invalid(self, qs) -> int | None:
        """Index of the first configuration of ``qs`` (N, 7) this object rejects, or None (batched)."""
        qs = np.asarray(qs, dtype=np.float64)
        start = 0
        while (found := self.clear.first_invalid(qs[start:])) is not None:
            index = start + found
            if not self(qs[index]):
                return index
            start = index + 1
        return None


class AllValid:
    """``q -> bool``: valid for every one of ``checks`` (each a :class:`Validity` or alike, with ``first_invalid``)."""

    def __init__(self, *checks) -> None:
        self.checks = checks

    def __call__(self, q) -> bool:
        return all(check(q) for check in self.checks)

    def first_invalid(self, qs) -> int | None:
        found = [k for k in (check.first_invalid(qs) for check in self.checks) if k is not None]
        return min(found) if found else None
