"""Assembly sequence planning by disassembly (as in ASAP, Tian et al. 2023).

Starting from the full target assembly, repeatedly take out a part that

1. leaves along a collision-free straight line (:mod:`planning.sweep`; the floor counts as an obstacle),
2. leaves the rest stable: every remaining part keeps a path of contacts to the floor (parts that touch are
   fastened once placed, standing for the connectors; targets where a part has no such path to begin with, a
   predicted part in mid air, are refused before any search, naming those parts), and
3. can be grasped at its target among the parts that remain (those placed before it), by a caller-given check.

Reversed, this is an assembly order with an insertion direction (minus the removal direction) and a grasp per
part. The search is depth-first with heuristics (top-most parts first, fewest contacts first), remembers
sub-assemblies that failed, and stops at a time budget. When no sequence exists it says why, for the smallest
sub-assembly it could not take apart: which part is blocked by which, which removal would leave parts
unsupported, which part has no grasp.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from planning.collision import ConvexPart, box_gap, overlapping_pieces, signed_distance
from planning.contact import FLOOR, all_grounded, contact_graph, pieces, support_graph, ungrounded
from planning.pose import Pose
from planning.sweep import PENETRATION_TOLERANCE_M, blocks, leaves_above_floor, travel_to_clear_m

MAX_DIRECTIONS_PER_GRASP = 4  # free insertion directions tried for a grasp before giving up on a part
# a direction along which a part stays inside a neighbour it overlaps at its target (a back panel drawn into the
# groove of a side) for longer than this comes after the others: a robot's straight insertion (8 cm) must start
# where the part is clear of it, and a 60 cm side slid down the whole groove cannot
OVERLAP_EXIT_M = 0.06

# why a part could not be taken out (SequenceResult.blocking_kind)
BLOCKED = "blocked"  # every removal direction runs into a part or the floor
NO_GRASP = "no grasp"  # no grasp at its target among the parts placed before it
UNSUPPORTING = "unsupporting"  # taking it out would leave parts without support (follows from the others)
OFF_FLOOR = "off the floor"  # no path of contacts to the floor at its target: refused before any search

# a grasp check: (part name, names of the parts present around it, insertion direction) -> a grasp or None
GraspCheck = Callable[[str, frozenset, np.ndarray], object | None]


def removal_directions(extra_axes: np.ndarray | None = None) -> np.ndarray:
    """Candidate removal directions (unit, world frame), in order of preference: up, the four horizontal axes,
    the diagonals that rise, then ``extra_axes`` (e.g. a tilted part's own axes) and the rest of the 26 box
    directions; straight down last (a part that must go in from below is the hardest for a robot)."""
    preferred = [(0, 0, 1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]
    grid = [(x, y, z) for z in (1, 0, -1) for x in (-1, 0, 1) for y in (-1, 0, 1) if (x, y, z) != (0, 0, 0)]
    grid.sort(key=lambda v: (-v[2], sum(abs(c) for c in v)))
    ordered = [np.array(v, dtype=np.float64) for v in preferred]
    if extra_axes is not None:
        ordered.extend(np.asarray(extra_axes, dtype=np.float64))
    ordered.extend(np.array(v, dtype=np.float64) for v in grid if v not in preferred and v != (0, 0, -1))
    ordered.append(np.array([0.0, 0.0, -1.0]))
    unique: list[np.ndarray] = []
    for v in ordered:
        v = v / np.linalg.norm(v)
        if all(np.dot(v, u) < 1 - 1e-6 for u in unique):
            unique.append(v)
    return np.array(unique)


@dataclass(frozen=True)
class SequenceStep:
    """One assembly step: ``part`` goes in along ``insertion_direction`` (unit, world frame)."""

    part: str
    insertion_direction: np.ndarray
    grasp: object | None
    fastened_to: tuple[str, ...]  # parts placed before it that it touches (the floor included)
    rests_on: tuple[str, ...]  # of those, the ones it rests on under gravity


@dataclass
class SequenceResult:
    """Assembly order (first placed first) or the reason there is none."""

    steps: list[SequenceStep]
    success: bool
    reason: str = ""
    blocking: dict[str, str] = field(default_factory=dict)  # part -> why it could not be taken out
    seconds: float = 0.0
    states_expanded: int = 0  # 0: refused before any search (parts off the floor)
    blocking_kind: dict[str, str] = field(default_factory=dict)  # part -> BLOCKED, NO_GRASP, UNSUPPORTING, OFF_FLOOR

    @property
    def order(self) -> list[str]:
        return [s.part for s in self.steps]


class _Planner:
    def __init__(self, parts: list[ConvexPart], poses: list[Pose], grasp_check: GraspCheck | None,
                 floor_z_m: float, time_budget_s: float, max_overlap_exit_m: float | None = None) -> None:
        self.parts = {p.name: p for p in parts}
        self.max_overlap_exit_m = max_overlap_exit_m
        self.poses = {p.name: pose for p, pose in zip(parts, poses)}
        self.names = [p.name for p in parts]
        self.contacts = contact_graph(parts, poses, floor_z_m)
        self.support = support_graph(self.contacts)
        self.grasp_check = grasp_check
        self.floor_z_m = floor_z_m
        self.deadline = time.thread_time() + time_budget_s
        self.directions = {name: removal_directions(self._own_axes(name)) for name in self.names}
        self.top_z = {n: float(self.parts[n].bounds(self.poses[n])[1, 2]) for n in self.names}
        self.world_vertices = {n: self.poses[n].apply(self.parts[n].vertices) for n in self.names}
        bounds = {n: self.parts[n].bounds(self.poses[n]) for n in self.names}
        self.gap = {a: {b: float(box_gap(bounds[a], bounds[b])) for b in self.names} for a in self.names}
        self._blocked: dict[tuple[str, int, str], bool] = {}
        self._overlap_partners: dict[str, tuple[str, ...]] = {}
        self._overlap_regions: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
        self._floor_ok: dict[tuple[str, int], bool] = {}
        self._grasps: dict[tuple, object | None] = {}
        self.failed: set[frozenset] = set()
        self.expanded = 0
        # the smallest sub-assembly the search could not take apart: part -> (kind, why)
        self.smallest_failure: tuple[frozenset, dict[str, tuple[str, str]]] | None = None
        self.timed_out = False

    def _own_axes(self, name: str) -> np.ndarray:
        rotation = self.poses[name].rotation
        axes = np.concatenate([rotation.T, -rotation.T])  # rows: the part's axes in the world frame
        return axes[np.abs(axes[:, 2]) < 0.999]  # world +-z are in the list already

    # --- the three tests ---------------------------------------------------------------------------------
    def blocked_by(self, name: str, k: int, obstacle: str) -> bool:
        key = (name, k, obstacle)
        if key not in self._blocked:
            self._blocked[key] = blocks(self.parts[name], self.poses[name], self.parts[obstacle],
                                        self.poses[obstacle], self.directions[name][k])
        return self._blocked[key]

    def clears_floor(self, name: str, k: int, present: frozenset) -> bool:
        key = (name, k)
        if key not in self._floor_ok:
            direction = self.directions[name][k]
            others = [self.world_vertices[n] for n in self.names if n != name]
            travel = max([travel_to_clear_m(self.world_vertices[name], o, direction) for o in others] + [0.0])
            self._floor_ok[key] = leaves_above_floor(self.parts[name], self.poses[name], direction, travel,
                                                     self.floor_z_m)
        return self._floor_ok[key]

    def overlap_partners(self, name: str) -> tuple[str, ...]:
        """The parts ``name`` overlaps at the targets by more than the sweep's penetration tolerance."""
        if name not in self._overlap_partners:
            self._overlap_partners[name] = tuple(
                other for other in self.names
                if other != name and self.gap[name][other] <= 0.0
                and signed_distance(self.parts[name], self.poses[name], self.parts[other], self.poses[other],
                                    cutoff_m=0.0).distance_m < -PENETRATION_TOLERANCE_M)
        return self._overlap_partners[name]

    def overlap_regions(self, name: str, other: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """Where ``name`` overlaps ``other`` at the targets: the world vertices of each pair of their convex pieces
        (``name``'s, ``other``'s) that overlap by more than the sweep's penetration tolerance; the whole parts'
        where no pair does."""
        key = (name, other)
        if key not in self._overlap_regions:
            part, obstacle = self.parts[name], self.parts[other]
            pose, obstacle_pose = self.poses[name], self.poses[other]
            pairs = overlapping_pieces(part, pose, obstacle, obstacle_pose, PENETRATION_TOLERANCE_M)
            self._overlap_regions[key] = [
                (pose.apply(part.piece_vertices[i]), obstacle_pose.apply(obstacle.piece_vertices[j]))
                for i, j in pairs] or [(self.world_vertices[name], self.world_vertices[other])]
        return self._overlap_regions[key]

    def overlap_exit(self, name: str, k: int, present: frozenset) -> tuple[float, str | None]:
        """How far ``name`` moves along its removal direction ``k`` until each of its convex pieces that overlaps
        a piece of a part of ``present`` at the targets lies beyond that piece, and the part it leaves last ((0,
        None) when it overlaps none). A panel drawn into a groove along its whole length leaves it at the groove's
        end; two frames crossed at a joint, whose pieces overlap only there, leave each other as soon as the
        pieces at the joint part (not once the whole frames lie beyond each other)."""
        direction = self.directions[name][k]
        # by travel only: a partner it leaves at once (travel 0, a flat piece flush with it) ties with (0, None)
        return max([(max(travel_to_clear_m(moving, obstacle, direction)
                         for moving, obstacle in self.overlap_regions(name, other)), other)
                    for other in self.overlap_partners(name) if other in present] + [(0.0, None)],
                   key=lambda exit_and_part: exit_and_part[0])

    def free_directions(self, name: str, present: frozenset,
                        limit: int) -> tuple[list[int], dict[int, list[str]]]:
        """Up to ``limit`` removal directions free of the parts in ``present`` (in order of preference, those
        that stay inside a part it overlaps for more than :data:`OVERLAP_EXIT_M` last; those that stay inside it
        for more than ``max_overlap_exit_m`` are blocked by it), and for each direction tried and found blocked, the
        first blocker found (nearest parts are tried first)."""
        free: list[int] = []
        long_exit: list[int] = []
        blockers: dict[int, list[str]] = {}
        obstacles = sorted(present - {name}, key=lambda o: (self.gap[name][o], o))
        for k in range(len(self.directions[name])):
            if not self.clears_floor(name, k, present):
                blockers[k] = [FLOOR]
                continue
            hit = next((o for o in obstacles if self.blocked_by(name, k, o)), None)
            if hit is not None:
                blockers[k] = [hit]
                continue
            exit_m, inside = self.overlap_exit(name, k, present)
            if self.max_overlap_exit_m is not None and exit_m > self.max_overlap_exit_m:
                blockers[k] = [inside]
                continue
            if exit_m > OVERLAP_EXIT_M:
                long_exit.append(k)
                continue
            free.append(k)
            if len(free) >= limit:
                break
        return (free + long_exit)[:limit], blockers

    def grasp(self, name: str, present: frozenset, direction: np.ndarray) -> object | None:
        if self.grasp_check is None:
            return True
        neighbours = frozenset(n for n in present if n != name)
        key = (name, neighbours, tuple(np.round(direction, 6)))
        if key not in self._grasps:
            self._grasps[key] = self.grasp_check(name, neighbours, -direction)
        return self._grasps[key]

    # --- search -----------------------------------------------------------------------------------------
    def candidates(self, present: frozenset) -> list[str]:
        degree = {n: sum(1 for m in self.contacts.neighbors(n) if m in present) for n in present}
        return sorted(present, key=lambda n: (-round(self.top_z[n], 3), degree[n], n))

    def search(self, present: frozenset) -> list[tuple[str, int, object]] | None:
        """Removal sequence (part, direction index, grasp) taking ``present`` apart, or None."""
        if not present:
            return []
        if present in self.failed:
            return None
        if time.thread_time() > self.deadline:
            self.timed_out = True
            return None
        self.expanded += 1
        reasons: dict[str, tuple[str, str]] = {}
        for name in self.candidates(present):
            rest = present - {name}
            if not all_grounded(self.contacts, set(rest)):
                lost = sorted(rest - set(nx.node_connected_component(self.contacts.subgraph(rest | {FLOOR}), FLOOR)))
                reasons[name] = UNSUPPORTING, f"taking it out first leaves {', '.join(lost)} without support"
                continue
            free, blockers = self.free_directions(name, present, MAX_DIRECTIONS_PER_GRASP)
            if not free:
                reasons[name] = BLOCKED, "blocked in every direction (" + "; ".join(
                    f"{_direction_label(self.directions[name][i])} by {', '.join(b)}"
                    for i, b in list(blockers.items())[:6]) + ")"
                continue
            tried = free
            grasp, k = None, tried[0]
            for k in tried:
                grasp = self.grasp(name, rest, self.directions[name][k])
                if grasp is not None:
                    break
            if grasp is None:
                reasons[name] = NO_GRASP, (
                    f"no collision-free grasp at its target among {len(rest)} placed parts "
                    f"(inserted {', '.join(_direction_label(-self.directions[name][i]) for i in tried)})")
                continue
            tail = self.search(rest)
            if tail is not None:
                return [(name, k, grasp), *tail]
            if self.timed_out:
                return None
        self.failed.add(present)
        if reasons and (self.smallest_failure is None or len(present) <= len(self.smallest_failure[0])):
            self.smallest_failure = (present, reasons)
        return None


def _falling_reason(contacts, falling: set[str]) -> str:
    """Why no order exists for targets where ``falling`` parts touch nothing that leads to the floor."""
    groups = [piece for piece in pieces(contacts) if piece <= falling]
    described = "; ".join(", ".join(sorted(group)) + (" (touching each other)" if len(group) > 1 else "")
                          for group in groups)
    return (f"{len(falling)} part(s) at their targets touch neither the floor nor any part that leads to it, so no "
            f"order can place them (each part must rest on the floor or on parts fastened to it): {described}")


def _direction_label(direction: np.ndarray) -> str:
    names = {(0, 0, 1): "+z", (0, 0, -1): "-z", (1, 0, 0): "+x", (-1, 0, 0): "-x", (0, 1, 0): "+y", (0, -1, 0): "-y"}
    key = tuple(int(v) for v in np.round(direction).astype(int))
    if np.allclose(direction, key):
        return names.get(key, str(key))
    return "(" + ", ".join(f"{v:+.2f}" for v in direction) + ")"


def plan_sequence(parts: list[ConvexPart], poses: list[Pose], grasp_check: GraspCheck | None = None,
                  floor_z_m: float = 0.0, time_budget_s: float = 10.0,
                  max_overlap_exit_m: float | None = None) -> SequenceResult:
    """Plan an assembly order for parts (convex pieces, part frames) at target poses ``assembly_from_part``.

    ``grasp_check(part, parts_present, insertion_direction)`` returns a grasp or None; without it grasps are
    not checked (``SequenceStep.grasp`` is then True). The search gives up after ``time_budget_s`` seconds of its own
    work (CPU time of the calling thread: the same search on a busy machine as on an idle one).
    ``max_overlap_exit_m``: a part that overlaps a neighbour at the targets may not go in along a direction on which
    it stays inside that neighbour for more than this (metres; None: no limit), e.g. the robot's straight
    insertion plus its longest lead-in, which must start where the part is clear of it.
    """
    start = time.perf_counter()
    planner = _Planner(parts, poses, grasp_check, floor_z_m, time_budget_s, max_overlap_exit_m)
    falling = ungrounded(planner.contacts, set(planner.names))
    if falling:
        return SequenceResult([], False, _falling_reason(planner.contacts, falling), {
            name: "no path of contacts to the floor at its target" for name in sorted(falling)},
            time.perf_counter() - start, 0, {name: OFF_FLOOR for name in sorted(falling)})
    removal = planner.search(frozenset(planner.names))
    seconds = time.perf_counter() - start
    if removal is None:
        if planner.timed_out:
            reason = f"no sequence found within the time budget of {time_budget_s:.1f} s"
        else:
            reason = "no part can be taken out of the assembly in any order"
        stuck = planner.smallest_failure[1] if planner.smallest_failure else {}
        if planner.smallest_failure and len(planner.smallest_failure[0]) < len(planner.names):
            reason += (f"; stuck with {len(planner.smallest_failure[0])} parts left: "
                       f"{', '.join(sorted(planner.smallest_failure[0]))}")
        return SequenceResult([], False, reason, {name: why for name, (_, why) in stuck.items()}, seconds,
                              planner.expanded, {name: kind for name, (kind, _) in stuck.items()})
    steps = []
    placed: set[str] = set()
    for name, k, grasp in reversed(removal):
        touching = tuple(sorted(n for n in planner.contacts.neighbors(name) if n in placed or n == FLOOR))
        rests_on = tuple(sorted(n for n in planner.support.predecessors(name) if n in placed or n == FLOOR))
        steps.append(SequenceStep(name, -planner.directions[name][k], grasp, touching, rests_on))
        placed.add(name)
    return SequenceResult(steps, True, "", {}, seconds, planner.expanded)
