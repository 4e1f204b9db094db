"""Kitting: where and how each loose part lies before the robot picks it.

Every part starts at rest in one of its stable poses (trimesh's ``compute_stable_poses``; whether it rests there
is :mod:`planning.stability`'s to judge) on a pedestal in the kitting area: a box under the part, inset from its
footprint like the jig pads, so that fingers can reach under a board's edge, with chocks beside a part that would
roll (:mod:`planning.pedestal`; which one each part rests on in each pose is :mod:`planning.kitting_support`'s).

The kitting area is a ring around the robot base on the table (:class:`planning.kitting_area.KittingArea`). Each
part's footprint is a rectangle turned so that its long side runs along the ring or across it; candidate places
are tried nearest to the jig first. Whether a grasp clears what is around the part at the pick is
:mod:`planning.pick_clearance`'s.

Boards may lie on boards (a stack): a board rests on a flat board assembled after it (so it is picked first),
overhanging it by :data:`STACK_OVERHANG_M` on one side so that the fingers reach under its edge there. Stacks
let a cabinet's panels fit the ring within the arm's reach.

For each part the planner takes the most probable stable pose and the first place where

- the footprint, grown by the gap, overlaps no other part's and no keep-out rectangle and lies on the table;
- some grasp works at the pick, clear of its support, the table and the neighbouring pedestals and the parts
  still there when it is picked (those assembled after it), and the same grasp works at the target
  (``grasp_ok_at_target``) and the robot reaches it (``reach``);
- each part picked before it keeps at least one of its grasp options (up to :data:`GRASP_OPTIONS` grasps that
  work at its pick and target, with arm configurations) clear of the new part and its pedestal; the options the
  new part spoils are dropped, and every part ends with its best remaining option.

Frames: every pose is in the world frame of the cell (metres, +z up, table top at ``table_z_m``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from planning.grasp import Grasp
from planning.kitting_area import (
    KittingArea,
    candidate_places,
    footprint_area_m2,
    polygons_overlap,
    quads_overlap,
    rectangle_corners,
    rectangles_corners,
    ring_area_m2,
    yaw_pose,
)
from planning.kitting_support import MAX_GROUND_POSES, SupportChoice, rest_half
from planning.pedestal import Pedestal
from planning.pick_clearance import (
    LEVEL_FINGERS,
    clear_at_pick,
    finger_tilt,
    grasp_key,
    neighbour_hand_for,
    pickable,
    picks_from_above,
    tips_under,
)
from planning.pose import Pose
from planning.stability import rests_stably, stable_rest_poses, upright_rest_pose

NEIGHBOUR_REACH_M = 0.25  # parts whose footprints are farther apart than this cannot touch each other's hand
MAX_PLACES_PER_POSE = 40  # places tried (with grasp checks) for one stable pose before the next pose
PLACE_SPACING_M = 0.08  # after a place fails, places nearer to it than this are skipped (spread the tries)
HALF_TURN_SAMPLES = 200  # surface samples that decide whether a part lying in a pose looks the same turned half a
HALF_TURN_TOLERANCE_M = 0.001  # turn about the vertical (then its kitting places are not tried turned too)
BOARD_THICKNESS_RATIO = 0.25  # a part thinner than this fraction of its middle extent is a board: it may stack
STACK_OVERHANG_M = 0.04  # a stacked board overhangs the one under it by this much on one side (for the fingers)
STACK_SUPPORT_M = 0.02  # ... and keeps its centre at least this far inside the lower board's edge
TOP_FACE_FRACTION = 0.8  # a board's flat top covers at least this fraction of its footprint
CAPACITY_FRACTION = 0.75  # rectangles in a ring pack no denser than this: fail at once above it
MAX_REST_POSES = 24  # stable poses considered per part (a round leg has one per facet, each turned about its axis)
SCORED_GRASPS = 20  # the grasps (best at the target first) that rank the rest poses
GRASP_OPTIONS = 4  # grasps (with arm configurations) kept per part, so a later neighbour may spoil some of them
LAYOUT_RETRIES = 2  # parts that find no place are laid out first in a new try of the layout, at most this many


@dataclass(frozen=True)
class KittingSlot:
    """Where one part starts: its pose (world), the pedestal under it, and the grasp to pick and place it."""

    part: str
    world_from_part: Pose
    pedestal: Pedestal | None  # None when it lies on another part (``rests_on``)
    grasp: Grasp
    stable_pose_probability: float
    footprint_world: np.ndarray  # (4, 2) corners of the footprint rectangle, world x-y, metres
    reach: object = None  # what ``Reach.at_pick`` returned (e.g. the arm configurations), for ``still_clear``
    rests_on: str | None = None  # the board it lies on (picked after it); None: on its own pedestal
    alternatives: tuple = ()  # further (grasp, reach) pairs that also work here, best first (for the motion planner)
    wedged: bool = False  # it rests in none of its poses unless wedged into its pedestal or chocks, and lies so


class Reach:
    """The robot's side of kitting (the planner stays free of robot models): override both methods.

    ``at_pick(part, grasp, world_from_part, obstacles, support)``: something truthy (e.g. the arm configurations
    that reach the grasp) when the robot reaches the grasp without touching ``obstacles`` (mesh, world pose) pairs,
    and places the part at its target without touching them or ``support`` (what the part lies on: its pedestal,
    or the board under it and that board's pedestal; the grasp planner checked the hand against them at the
    pick, and they stay in the kitting area), else None. ``still_clear(reach, obstacles)``: whether those
    configurations still touch nothing when ``obstacles`` are added next to the part.
    """

    def at_pick(self, part: str, grasp: Grasp, world_from_part: Pose,
                obstacles: list[tuple[trimesh.Trimesh, Pose]],
                support: list[tuple[trimesh.Trimesh, Pose]] = ()) -> object | None:
        return True

    def still_clear(self, reach: object, obstacles: list[tuple[trimesh.Trimesh, Pose]]) -> bool:
        return True


NO_GRASP = "no_grasp"  # KittingError.kind: the part has no grasp at all
NO_GRASP_AT_TARGET = "no_grasp_at_target"  # no grasp of the part works at its target
NO_PLACE = "no_place"  # no place in the kitting area with a grasp that works at the pick and at the target
TOO_LARGE = "too_large"  # the parts need more kitting area than there is
OUT_OF_TIME = "out_of_time"


class KittingError(RuntimeError):
    """No stable pose and grasp serve a part at both pick and place, or the parts do not fit the area.

    ``kind``: :data:`NO_GRASP`, :data:`NO_GRASP_AT_TARGET`, :data:`NO_PLACE`, :data:`TOO_LARGE` or
    :data:`OUT_OF_TIME`; ``part``: the part at fault (None for the whole layout)."""

    def __init__(self, message: str, kind: str = NO_PLACE, part: str | None = None) -> None:
        super().__init__(message)
        self.kind, self.part = kind, part


def plan_kitting(names: list[str], meshes: list[trimesh.Trimesh], candidates: dict[str, list[Grasp]],
                 grasp_ok_at_target: Callable[[str, Grasp], bool], area: KittingArea,
                 prefer_near_xy: Sequence[float] = (0.5, 0.0), reach: Reach | None = None,
                 deadline: float = float("inf"),
                 target_rotations: dict[str, np.ndarray] | None = None,
                 rests: Callable[..., bool] | None = None,
                 settles: Callable[..., list[Pose] | None] | None = None,
                 lay_out_first: Sequence[str] = ()) -> list[KittingSlot]:
    """A slot for every part (returned in the order given), the parts of ``lay_out_first`` first (in that order),
    then the largest footprints, each in the free place nearest ``prefer_near_xy`` (usually the jig). ``names``
    must be in assembly order: a part is only an obstacle to the picks of parts assembled before it (the others are
    gone by then), and a board may lie on a board assembled after it (:func:`stack_places`). Each part's
    ``candidates`` are tried in the order given (rank them for the target: the pick is usually the easier end).
    A part of ``lay_out_first`` that finds no place fails the layout at once (a caller that saw it fail before,
    e.g. with the jig placed otherwise, learns soon whether it fails again).

    ``grasp_ok_at_target(part, grasp)`` says whether a grasp (part frame) also works where the part is placed;
    ``reach`` whether the robot's arm reaches it at the pick among the parts present then (and keeps reaching
    the earlier parts once the new one lies next to them). Past ``deadline`` (``time.thread_time()``) it
    gives up. ``target_rotations`` (part -> world_from_part rotation at the target): each part is first tried
    lying as it sits in the assembly (where that is stable), so that the grasps that work at the target from
    above also work at the pick; then in its stable poses, most probable first.

    ``rests(loose, fixed, allow_wedged=False)``, when given, confirms with physics what the geometric checks judge:
    whether the ``loose`` (mesh, world_from_part) bodies stay where they lie on the ``fixed`` (mesh, world_from_body)
    ones, and, unless ``allow_wedged``, are not wedged into them (e.g. :class:`cell.resting.PhysicsRestCheck`). It
    is asked once per part and rest pose on its pedestal (the same anywhere on the flat table) and for every stack
    place; a part that rests in none of its poses unwedged is then allowed to lie wedged (a chair's frame jammed
    across its chocks; a last resort: the arm might not pull it out). ``settles(loose, fixed, allow_wedged=False)``,
    when given, says where such bodies come to rest (world_from_part each, or None when they do not, e.g.
    :meth:`cell.resting.PhysicsRestCheck.settle`): a part with no rest pose that the geometry or ``rests`` accepts on
    its pedestal is laid down on it and left to settle (a dished board tips onto the pedestal's rim, a tapered leg
    onto its chocks), and lies where it settles (:data:`planning.kitting_support.SETTLE_MAX_TILT_DEG`,
    :data:`planning.kitting_support.SETTLE_MAX_DROP_M`); so is a part none of whose resting poses gives it a place
    (a frame of tubes that rocks as laid).
    """
    reach = reach or Reach()
    layout = _Layout(names, dict(zip(names, meshes)), area, np.asarray(prefer_near_xy, dtype=np.float64), reach)
    layout.target_rotations = dict(target_rotations or {})
    layout.rests, layout.settles = rests, settles
    needed, offered = footprint_area_m2([m for m in meshes if not _is_board(m)], area.gap_m), ring_area_m2(area)
    boards = [m for m in meshes if _is_board(m)]
    needed += footprint_area_m2(sorted(boards, key=lambda m: -np.prod(np.sort(m.extents)[1:]))[:1], area.gap_m)
    if needed > CAPACITY_FRACTION * offered:
        raise KittingError(f"the parts need at least {needed:.2f} m2 of kitting area (boards stacked, gaps "
                           f"included), the kitting ring offers {offered:.2f} m2 within reach on the table: "
                           "the object is too large for this cell (use a scaled-down model of it, or a scene "
                           "with a larger kitting area)", TOO_LARGE)
    # largest footprints first (they need the roomy places, and boards are stacked on them), ties in order; a part
    # that finds no place goes first in the next try (the arm at its target may sweep over the places the larger
    # parts took near the jig; laid out first, it keeps them clear of it), at most LAYOUT_RETRIES times; a part of
    # lay_out_first that finds none fails the layout at once
    area_of = {name: float(np.prod(np.sort(mesh.extents)[1:])) for name, mesh in zip(names, meshes)}
    by_size = [names[k] for k in sorted(range(len(names)), key=lambda k: (-round(area_of[names[k]], 4), k))]
    mesh_of = dict(zip(names, meshes))
    first: list[str] = list(dict.fromkeys(n for n in lay_out_first if n in mesh_of))
    given = len(first)
    while True:
        layout.slots, layout.options = [], {}
        failed = None
        for name in first + [n for n in by_size if n not in first]:
            if time.thread_time() > deadline:
                raise KittingError(f"part {name!r}: the planning time budget ran out while laying out the kit",
                                   OUT_OF_TIME, name)
            chosen = layout.place(name, candidates[name], grasp_ok_at_target)
            if chosen is None:
                failed = name
                break
            layout.slots.append(chosen)
        if failed is None:
            break
        message, kind = _why_not(failed, mesh_of[failed], candidates[failed], grasp_ok_at_target, area,
                                 layout.prefer, failed in layout.unrested,
                                 failed in layout.tried and failed not in layout.picked)
        if (kind != NO_PLACE or failed in layout.unrested or failed in first
                or len(first) - given >= LAYOUT_RETRIES):
            raise KittingError(message, kind, failed)
        first.append(failed)
    slots = [dataclasses.replace(slot, grasp=layout.options[slot.part][0][0], reach=layout.options[slot.part][0][1],
                                 alternatives=tuple(layout.options[slot.part][1:]))
             for slot in layout.slots]  # each part's best grasp that the parts laid out after it left open
    return sorted(slots, key=lambda slot: names.index(slot.part))


def _is_board(mesh: trimesh.Trimesh) -> bool:
    extents = np.sort(mesh.extents)
    return bool(extents[0] < BOARD_THICKNESS_RATIO * extents[1])


class _Layout(SupportChoice):
    """The kitting layout being built: slots so far, and the checks of one more part's place."""

    def __init__(self, order: list[str], meshes: dict[str, trimesh.Trimesh], area: KittingArea,
                 prefer: np.ndarray, reach: Reach) -> None:
        super().__init__(meshes, area)
        self.order, self.prefer, self.reach = order, prefer, reach
        self.slots: list[KittingSlot] = []
        self.options: dict[str, list[tuple[Grasp, object]]] = {}  # per slot: (grasp, reach) still possible
        self.places_cache: dict[tuple, list] = {}
        self.half_turn_cache: dict[tuple, bool] = {}  # (part, rest pose) -> the same turned half a turn
        self.tried: set[str] = set()  # parts for which some place was tried
        self.picked: set[str] = set()  # parts that some place tried lets the hand grasp clear of their support
        self.failed_on_ground: dict[str, list] = {}  # part -> (rest pose, grasps, probability) without a place

    def rank(self, name: str) -> int:
        return self.order.index(name)

    def _near(self, slot: KittingSlot, corners: np.ndarray) -> bool:
        gaps = np.linalg.norm(slot.footprint_world[:, None] - corners[None], axis=2)
        return bool(np.min(gaps) < NEIGHBOUR_REACH_M) or polygons_overlap(slot.footprint_world, corners)

    def obstacles_at_pick(self, name: str, corners: np.ndarray) -> list[tuple[trimesh.Trimesh, Pose]]:
        """What lies near ``name`` when it is picked: every pedestal, and the parts assembled after it."""
        out = []
        for slot in self.slots:
            if not self._near(slot, corners):
                continue
            if slot.pedestal is not None:
                out.append((slot.pedestal.mesh(), slot.pedestal.world_from_pedestal))
            if self.rank(slot.part) > self.rank(name):
                out.append((self.meshes[slot.part], slot.world_from_part))
        return out

    def place(self, name: str, grasps: list[Grasp], grasp_ok_at_target) -> KittingSlot | None:
        mesh = self.meshes[name]
        poses = stable_rest_poses(mesh, max_poses=MAX_REST_POSES)
        if name in self.target_rotations:  # lying as it sits in the assembly, its target grasps work from above
            poses = [(upright_rest_pose(mesh, self.target_rotations[name]), float("nan"))] + poses
        # on the ground, the poses where more of the grasps wanted at the target pick from above come first
        ground = sorted(self._ground_poses(name, poses),
                        key=lambda pose: -picks_from_above(grasps[:SCORED_GRASPS], pose[0]))
        self.failed_on_ground[name] = []
        found = self._place_among(name, mesh, grasps, grasp_ok_at_target, poses, ground, stack_first=_is_board(mesh))
        if found is None and self.settles is not None:
            # none of the poses it rests in as laid gives a place: those it settles in (chair_ivar_0668's frame of
            # tubes, lying flat, rocks on its tubes as laid and rests only once settled, a little tilted)
            settled = [pose for pose in self._settled_poses(name, poses) if not any(
                np.allclose(pose[0], other[0]) for other in ground)]
            found = self._place_among(name, mesh, grasps, grasp_ok_at_target, poses, settled, stack_first=None)
        if found is None:  # no place anywhere on its pedestals: a bent bar, on posts that follow it
            for rest_from_part, pose_grasps, probability in self.failed_on_ground.pop(name):
                if self._onto_posts(name, rest_from_part, pose_grasps, grasp_ok_at_target):
                    found = self._first_place(name, mesh, pose_grasps, grasp_ok_at_target, rest_from_part,
                                              self._ground_places(name, rest_from_part), probability)
                    if found is not None:
                        break
        return found

    def _place_among(self, name: str, mesh: trimesh.Trimesh, grasps: list[Grasp], grasp_ok_at_target,
                     poses: list[tuple[np.ndarray, float]], ground: list[tuple[np.ndarray, float]],
                     stack_first: bool | None) -> KittingSlot | None:
        """The first place found for the part: on the boards of a stack in the first of ``poses`` and on the
        ground in those of ``ground`` (stack first when ``stack_first``, ground first when False, ground only
        when None); None when none works."""
        attempts = ("ground",) if stack_first is None else ("stack", "ground") if stack_first else ("ground", "stack")
        for attempt in attempts:
            for rest_from_part, probability in poses[:1] if attempt == "stack" else ground[:MAX_GROUND_POSES]:
                pose_grasps = grasps
                if attempt == "ground":
                    rest_from_part = self._free_fingers(name, rest_from_part, grasps, grasp_ok_at_target)
                    pose_grasps = self._leaning_grasps(name, rest_from_part, grasps) + list(grasps)
                places = (self._stack_places(name, rest_from_part) if attempt == "stack"
                          else self._ground_places(name, rest_from_part))
                slot = self._first_place(name, mesh, pose_grasps, grasp_ok_at_target, rest_from_part, places,
                                         probability)
                if slot is not None:
                    return slot
                if attempt == "ground":
                    self.failed_on_ground[name].append((rest_from_part, pose_grasps, probability))
        return None

    def _first_place(self, name: str, mesh: trimesh.Trimesh, grasps: list[Grasp], grasp_ok_at_target,
                     rest_from_part: np.ndarray, places, probability: float) -> KittingSlot | None:
        """The slot at the first of ``places`` (``_stack_places`` or ``_ground_places`` of this rest pose) where
        :meth:`_try` finds one, its options recorded; at most :data:`MAX_PLACES_PER_POSE` tried; None if none."""
        tried, failed = 0, []  # (centre_xy, heading of the rest frame's x axis) of the places that failed
        for world_from_rest, corners, pedestal, base in places:
            xy, heading = world_from_rest.position[:2], world_from_rest.rotation[:2, 0]
            if any(np.linalg.norm(xy - f) < PLACE_SPACING_M and heading @ h > 0.0 for f, h in failed):
                continue  # next to a place that failed, turned alike: most likely fails for the same reason
            tried += 1
            if tried > MAX_PLACES_PER_POSE:
                break
            failed.append((xy, heading))
            found = self._try(name, mesh, grasps, grasp_ok_at_target, world_from_rest @ Pose.from_matrix(
                rest_from_part), corners, pedestal, base, probability)
            if found is not None:
                slot, mine, surviving = found
                self.options.update(surviving)
                self.options[name] = mine
                return slot
        return None

    def _ground_places(self, name: str, rest_from_part: np.ndarray):
        at_rest = self._support(name, rest_from_part)
        if at_rest is None:
            return  # it does not rest in this pose, anywhere: try the next rest pose
        mesh_half, long_is_x = rest_half(self.meshes[name], rest_from_part)
        half_ring = np.array([max(mesh_half), min(mesh_half)])
        key = tuple(np.round(half_ring, 4))
        if key not in self.places_cache:
            self.places_cache[key] = candidate_places(self.area, half_ring, self.prefer)
        places = self.places_cache[key]
        if not places:
            return
        taken = np.zeros(len(places), dtype=bool)
        if self.slots:  # places whose footprint (grown by half the gap) meets a slot's
            grown = rectangles_corners(np.array([xy for xy, _ in places]), np.array([yaw for _, yaw in places]),
                                  half_ring + self.area.gap_m / 2)
            taken = quads_overlap(grown, np.array([s.footprint_world for s in self.slots])).any(axis=1)
        for (xy, long_yaw), skip in zip(places, taken):
            if skip:
                continue
            yaw = long_yaw if long_is_x else long_yaw - np.pi / 2  # the rest frame's long axis along long_yaw
            # and turned half a turn on the same footprint: the other edge faces the robot (chair_ivar_0668's side
            # lying flat is held at the target by an edge that faced away from the arm in every place)
            for turn in (0.0, np.pi) if not self._half_turn_alike(name, rest_from_part) else (0.0,):
                world_from_rest = Pose([xy[0], xy[1], self.area.table_z_m + self.area.pedestal_height_m],
                                       [1, 0, 0, 0]) @ yaw_pose(yaw + turn)
                pedestal = dataclasses.replace(at_rest,
                                               world_from_pedestal=world_from_rest @ at_rest.world_from_pedestal)
                yield world_from_rest, rectangle_corners(xy, long_yaw, half_ring), pedestal, None

    def _half_turn_alike(self, name: str, rest_from_part: np.ndarray) -> bool:
        """Whether the part lying in this rest pose looks the same turned half a turn about the vertical through
        its footprint's centre (surface samples land within :data:`HALF_TURN_TOLERANCE_M` of its surface): then
        the turned place is the same place."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        if key not in self.half_turn_cache:
            mesh = self.meshes[name]
            points, _ = trimesh.sample.sample_surface(mesh, HALF_TURN_SAMPLES, seed=0)
            rest = Pose.from_matrix(rest_from_part)
            turned = rest.inverse() @ Pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]) @ rest
            _, distance, _ = trimesh.proximity.closest_point(mesh, turned.apply(points))
            self.half_turn_cache[key] = bool(np.max(distance) <= HALF_TURN_TOLERANCE_M)
        return self.half_turn_cache[key]

    def _stack_places(self, name: str, rest_from_part: np.ndarray):
        """On top of a board assembled later whose top is flat and free, overhanging it on one side by
        :data:`STACK_OVERHANG_M` (room for the fingers under the edge), its centre over the board."""
        half, long_is_x = rest_half(self.meshes[name], rest_from_part)
        on_top = {s.rests_on for s in self.slots if s.rests_on}
        for base in sorted(self.slots, key=lambda s: self.rank(s.part), reverse=True):
            if self.rank(base.part) <= self.rank(name) or base.part in on_top:
                continue
            top = _flat_top(self.meshes[base.part], base.world_from_part)
            if top is None:
                continue
            top_z, base_centre, base_long_yaw, base_half = top
            half_ring = np.array([max(half), min(half)])
            along = np.array([np.cos(base_long_yaw), np.sin(base_long_yaw)])
            across = np.array([-along[1], along[0]])
            for axis, k in ((across, 1), (across, -1), (along, 1), (along, -1)):
                index = 1 if axis is across else 0
                shift = base_half[index] - half_ring[index] + STACK_OVERHANG_M
                shift = float(np.clip(shift, 0.0, base_half[index] - STACK_SUPPORT_M))
                xy = base_centre + k * shift * axis
                corners = rectangle_corners(xy, base_long_yaw, half_ring)
                lo, hi = np.asarray(self.area.table_min_xy), np.asarray(self.area.table_max_xy)
                if np.any(corners < lo) or np.any(corners > hi):
                    continue
                grown = rectangle_corners(xy, base_long_yaw, half_ring + self.area.gap_m / 2)
                stack = self._stack_of(base)
                if any(polygons_overlap(grown, s.footprint_world) for s in self.slots if s.part not in stack):
                    continue
                yaw = base_long_yaw if long_is_x else base_long_yaw - np.pi / 2
                world_from_rest = Pose([xy[0], xy[1], top_z], [1, 0, 0, 0]) @ yaw_pose(yaw)
                top_rest = world_from_rest.inverse().apply(np.column_stack([
                    rectangle_corners(base_centre, base_long_yaw, base_half), np.full(4, top_z)]))[:, :2]
                if not rests_stably(self.meshes[name], rest_from_part, top_rest):
                    continue
                if self.rests is not None and not self._stack_rests(name, world_from_rest @ Pose.from_matrix(
                        rest_from_part), stack):
                    continue
                yield world_from_rest, corners, None, base

    def _stack_rests(self, name: str, world_from_part: Pose, stack: set[str]) -> bool:
        """Whether ``name`` lying at ``world_from_part`` on the boards of ``stack`` stays there, and they stay on
        theirs, under physics (:attr:`rests`)."""
        members = [s for s in self.slots if s.part in stack]
        loose = [(self.meshes[name], world_from_part)] + [(self.meshes[s.part], s.world_from_part) for s in members]
        fixed = [(s.pedestal.mesh(), s.pedestal.world_from_pedestal) for s in members if s.pedestal is not None]
        return bool(self.rests(loose, fixed + [self._table_slab(self.area.table_z_m)]))

    def _stack_of(self, slot: KittingSlot) -> set[str]:
        members = {slot.part}
        below = slot
        while below.rests_on:
            below = next(s for s in self.slots if s.part == below.rests_on)
            members.add(below.part)
        return members

    def _try(self, name, mesh, grasps, grasp_ok_at_target, world_from_part, corners, pedestal, base,
             probability) -> tuple[KittingSlot, list, dict] | None:
        """The slot for ``name`` here, its grasp options and the earlier slots' options that survive it; None
        when no grasp works here or some earlier slot would keep no option."""
        own = [] if pedestal is None else [(pedestal.mesh(), pedestal.world_from_pedestal)]
        tips = tips_under(mesh, world_from_part)
        self.tried.add(name)
        at_pick = {grasp_key(g) for g in pickable(grasps, world_from_part, own, self.area.table_z_m,
                                                     self.obstacles_at_pick(name, corners)) if not tips(g)}
        if at_pick or (name not in self.picked and pickable(grasps, world_from_part, own, self.area.table_z_m)):
            self.picked.add(name)  # some grasp clears its support here (the other slots' bodies aside)
        # the support (own pedestal, or the board under it) is left out: the grasp check covered the hand
        present = [o for slot in self.slots if base is None or slot.part != base.part
                   for o in self._bodies(slot, name)]
        support = own + ([] if base is None else self._bodies(base, name))

        def level(grasp: Grasp) -> bool:  # the fingers close across gravity: neither tip drops onto the support
            return finger_tilt(world_from_part.rotation, grasp) <= LEVEL_FINGERS

        def steepness(grasp: Grasp) -> int:  # how far from straight down the hand approaches, in 15-degree steps
            down = -float((world_from_part.rotation @ grasp.part_from_tcp.rotation[:, 2])[2])
            return int(np.degrees(np.arccos(np.clip(down, -1.0, 1.0))) // 15.0)

        def options():  # (grasp, arm configurations): level fingers first, then the steepest approach from above
            # (the fingertips keep level above the support), else in the caller's order (best at the target first)
            usable = [g for g in grasps if grasp_key(g) in at_pick]
            for grasp in sorted(usable, key=lambda g: (not level(g), steepness(g))):
                if self._usable_at_target(name, grasp, grasp_ok_at_target):
                    reached = self.reach.at_pick(name, grasp, world_from_part, present, support)
                    if reached is not None:
                        yield grasp, reached

        own_options = options()
        first = next(own_options, None)
        if first is None:
            return None
        # the parts picked before this one must still be reachable and graspable with it (and its pedestal) by
        # at least one of their grasp options; the options it spoils are dropped
        new_part = [(mesh, world_from_part)]
        surviving = {}
        for slot in self.slots:
            added = (new_part if self.rank(slot.part) < self.rank(name) else []) + own
            if not added:
                continue
            near = self._near(slot, corners)
            kept = [(grasp, reached) for grasp, reached in self.options[slot.part]
                    if (not near or clear_at_pick([grasp], slot.world_from_part, added, None,
                                                  neighbour_hand_for(slot.world_from_part, grasp)))
                    and self.reach.still_clear(reached, added)]  # the arm reaches far beyond the hand
            if not kept:
                return None
            surviving[slot.part] = kept
        mine = [first] + [option for option, _ in zip(own_options, range(GRASP_OPTIONS - 1))]
        slot = KittingSlot(name, world_from_part, pedestal, first[0], probability, corners, first[1],
                           None if base is None else base.part, wedged=name in self.wedge_allowed)
        return slot, mine, surviving

    def _bodies(self, slot: KittingSlot, name: str) -> list[tuple[trimesh.Trimesh, Pose]]:
        """A slot's bodies present when ``name`` is picked: its pedestal always, the part if assembled later."""
        out = [] if slot.pedestal is None else [(slot.pedestal.mesh(), slot.pedestal.world_from_pedestal)]
        if self.rank(slot.part) > self.rank(name):
            out.append((self.meshes[slot.part], slot.world_from_part))
        return out


def _flat_top(mesh: trimesh.Trimesh, world_from_part: Pose) -> tuple[float, np.ndarray, float, np.ndarray] | None:
    """(top z, footprint centre xy, long-side direction in rad, half extents (long, short)) when the posed
    part's top is one flat face over most of its footprint (a board lying on its face), else None."""
    world = world_from_part.apply(mesh.vertices)
    top_z = float(world[:, 2].max())
    normals = mesh.face_normals @ world_from_part.rotation.T
    centres = world[mesh.faces].mean(axis=1)
    upward = (normals[:, 2] > 0.999) & (centres[:, 2] > top_z - 1e-4)
    footprint = world[:, :2]
    # the footprint's own axes: the board's edges (its two largest extents lie in the horizontal plane)
    axes = world_from_part.rotation[:2, :]
    in_plane = [k for k in range(3) if abs(world_from_part.rotation[2, k]) < 1e-3]
    if len(in_plane) < 2:
        return None
    spans = [np.ptp(footprint @ axes[:, k] / np.linalg.norm(axes[:, k])) for k in in_plane]
    long_k = in_plane[int(np.argmax(spans))]
    long_axis = axes[:, long_k] / np.linalg.norm(axes[:, long_k])
    short_axis = np.array([-long_axis[1], long_axis[0]])
    along, across = footprint @ long_axis, footprint @ short_axis
    half = 0.5 * np.array([np.ptp(along), np.ptp(across)])
    if mesh.area_faces[upward].sum() < TOP_FACE_FRACTION * 4 * half[0] * half[1]:
        return None
    if top_z - float(world[:, 2].min()) > 2.0 * half[1]:
        return None  # standing on an edge (its top is a narrow edge): nothing may rest on it
    centre = 0.5 * (along.max() + along.min()) * long_axis + 0.5 * (across.max() + across.min()) * short_axis
    return top_z, centre, float(np.arctan2(long_axis[1], long_axis[0])), half


def _why_not(name, mesh, grasps, grasp_ok_at_target, area, prefer, unrested: bool = False,
             unpicked: bool = False) -> tuple[str, str]:
    """(message, :class:`KittingError` kind) of why part ``name`` found no slot; ``unpicked``: at no place tried
    did any grasp clear the part's support."""
    if not grasps:
        return f"part {name!r}: no grasp at all", NO_GRASP
    if not any(grasp_ok_at_target(name, g) for g in grasps):
        return f"part {name!r}: no grasp works at its target", NO_GRASP_AT_TARGET
    rest_from_part = stable_rest_poses(mesh)[0][0]
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
    if not candidate_places(area, np.array([max(half), min(half)]), prefer):
        return (f"part {name!r}: its footprint ({2 * max(half):.2f} x {2 * min(half):.2f} m) does not fit the kitting "
                f"ring ({area.inner_radius_m:.2f}-{area.outer_radius_m:.2f} m around the robot, on the table)",
                TOO_LARGE)
    if unrested:
        return (f"part {name!r}: it rests in none of its stable poses on a pedestal (its underside does not stand on "
                "the pedestal's top, and it does not settle there), and no board to lie on takes it", NO_PLACE)
    if unpicked:
        low_m = float(np.min(mesh.extents))
        return (f"part {name!r}: at no place in the kitting ring does any of its grasps keep the hand clear of what "
                f"the part lies on (it is {low_m * 1000:.0f} mm across at its thinnest: the fingers reach below a "
                "part this low and meet its support); parts this small are not handled yet", NO_PLACE)
    return (f"part {name!r}: no free place in the kitting ring where one grasp works at the pick (reachable, clear "
            "of its neighbours) and at its target", NO_PLACE)
