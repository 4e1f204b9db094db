"""Kitting: where and how each loose part lies before the robot picks it.

Every part starts at rest in one of its stable poses (trimesh's ``compute_stable_poses``; whether it rests there
is :mod:`planning.stability`'s to judge) on a pedestal in the kitting area: a box under the part, inset from its
footprint like the jig pads, so that fingers can reach under a board's edge, with chocks beside a part that would
roll (:mod:`planning.pedestal`).

The kitting area is a ring around the robot base on the table (:class:`KittingArea`): between an inner radius
(clear of the robot's base) and an outer radius (within reach), inside the table, outside keep-out rectangles
(the jig with the assembly growing on it, plus room for the hand). Each part's footprint is a rectangle turned
so that its long side runs along the ring (tangential). Candidate places are tried nearest to the jig first.

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

from planning.grasp import APPROACH_M, Grasp, feasible_grasps, grasp_pose_key
from planning.gripper import MAX_OPENING_M, clearance_gripper
from planning.pedestal import (
    Pedestal,
    chocks_for,
    cradle_chocks,
    cut_back,
    pedestal_for,
    posts_under,
    standing_lean_m,
    top_box,
    top_boxes,
)
from planning.pose import Pose
from planning.stability import SUPPORT_MARGIN_M, centre_of_mass, rests_stably, stable_rest_poses, upright_rest_pose

HAND_CLEARANCE_M = 0.002  # grasps keep this from pedestals and neighbours (real hands are larger) ...
TILTED_CLEARANCE_M = 0.004  # ... and this where the fingers close on a slant, sliding down a round part towards
# its support (2 mm was measured too little in simulation)
# ... and this from the other slots' parts and pedestals: the arm's approach keeps the task planner's transit
# clearance (3 mm) from them where it can, and the simulator's Panda hulls are about 1.1 mm larger than the model
# (with 2 mm, a hand coming down beside a cabinet's top lying in the kit grazed it)
NEIGHBOUR_CLEARANCE_M = 0.0035
HAND = clearance_gripper(HAND_CLEARANCE_M)
TILTED_HAND = clearance_gripper(TILTED_CLEARANCE_M)
NEIGHBOUR_HAND = clearance_gripper(NEIGHBOUR_CLEARANCE_M)
NEIGHBOUR_REACH_M = 0.25  # parts whose footprints are farther apart than this cannot touch each other's hand
MAX_PLACES_PER_POSE = 40  # places tried (with grasp checks) for one stable pose before the next pose
RADIAL_STEP_M = 0.03
PLACE_SPACING_M = 0.08  # after a place fails, places nearer to it than this are skipped (spread the tries)
HALF_TURN_SAMPLES = 200  # surface samples that decide whether a part lying in a pose looks the same turned half a
HALF_TURN_TOLERANCE_M = 0.001  # turn about the vertical (then its kitting places are not tried turned too)
BOARD_THICKNESS_RATIO = 0.25  # a part thinner than this fraction of its middle extent is a board: it may stack
STACK_OVERHANG_M = 0.04  # a stacked board overhangs the one under it by this much on one side (for the fingers)
STACK_SUPPORT_M = 0.02  # ... and keeps its centre at least this far inside the lower board's edge
TOP_FACE_FRACTION = 0.8  # a board's flat top covers at least this fraction of its footprint
CAPACITY_FRACTION = 0.75  # rectangles in a ring pack no denser than this: fail at once above it
COMFORTABLE_FRACTION = 0.6  # places beyond this fraction of the ring's depth are tried last ...
FAR_PENALTY = 3.0  # ... as if each metre beyond it were this many metres farther from the jig
ANGLE_STEP_DEG = 3.0
SETTLE_MAX_TILT_DEG = 20.0  # a part laid down that settles turned farther than this from its rest pose fell over ...
SETTLE_MAX_DROP_M = 0.02  # ... one whose centre of mass sank farther than this fell off (or through) its pedestal
SETTLE_MAX_COM_HEIGHT_RATIO = 1.0  # ... and it must lie low: its centre of mass at most this times its footprint's
# half width above the pedestal's top (it tips over only past 45 degrees)
FRAME_CUTS_M = (0.03, 0.045, 0.06, 0.08)  # a pedestal under every grasp's fingers (a frame of thin bars lying
# on it) is cut back by one of these from one side, where its bars then overhang for the fingers
LEAN_SHARES = (1.0, 0.5)  # a standing board's grasps open for these shares of its lean (widest first)
MAX_REST_POSES = 24  # stable poses considered per part (a round leg has one per facet, each turned about its axis)
MAX_GROUND_POSES = 7  # ... of which this many (the best for picking from above) are tried on the ground
SCORED_GRASPS = 20  # the grasps (best at the target first) that rank the rest poses
FROM_ABOVE = np.cos(np.radians(30.0))  # a pick from above: the approach within 30 degrees of straight down
LEVEL_FINGERS = np.sin(np.radians(10.0))  # at the pick, grasps closing within 10 degrees of level come first
# a part standing with its centre of mass higher than this many times its foot's reach from it, across the fingers'
# closing axis, tips over its foot when a hand approaching on a slant closes on it (chair_5's back slat, standing
# 24 cm tall on a 25 mm foot, tipped 4.9 degrees under fingers coming 30 degrees off vertical and was carried so)
TIPPING_HEIGHT_RATIO = 3.0
SLANTED_APPROACH = np.cos(np.radians(10.0))  # an approach more than 10 degrees off straight down is slanted
FOOT_M = 0.002  # a part's foot: its points within this height of its lowest point
GRASP_OPTIONS = 4  # grasps (with arm configurations) kept per part, so a later neighbour may spoil some of them
LAYOUT_RETRIES = 2  # parts that find no place are laid out first in a new try of the layout, at most this many


_TABLE_SLAB = trimesh.creation.box((2.0, 2.0, 0.02))  # the table under the physics check of resting parts


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


@dataclass(frozen=True)
class KittingArea:
    """The ring where parts may lie (world frame, metres).

    centre_xy: the robot base; inner_radius_m / outer_radius_m bound the footprint centres' distance from it;
    table_min_xy / table_max_xy: the table top's extent; keep_out: rectangles (min_xy, max_xy) no footprint
    may overlap (the jig and the assembly on it, with room for the hand); gap_m: free space between footprints.
    """

    centre_xy: tuple[float, float]
    inner_radius_m: float
    outer_radius_m: float
    table_min_xy: tuple[float, float]
    table_max_xy: tuple[float, float]
    table_z_m: float
    pedestal_height_m: float
    keep_out: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = ()
    gap_m: float = 0.06


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


def _yaw(angle_rad: float) -> Pose:
    return Pose([0.0, 0.0, 0.0], [np.cos(angle_rad / 2), 0.0, 0.0, np.sin(angle_rad / 2)])


_UNIT_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def _corners(centre_xy: np.ndarray, yaw_rad: float, half_xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    local = _UNIT_SQUARE * half_xy
    return local @ np.array([[c, s], [-s, c]]) + centre_xy


def _corners_many(centres_xy: np.ndarray, yaws_rad: np.ndarray, half_xy: np.ndarray) -> np.ndarray:
    """:func:`_corners` of N rectangles of the same half extents at once: (N, 4, 2)."""
    c, s = np.cos(yaws_rad)[:, None], np.sin(yaws_rad)[:, None]
    local = _UNIT_SQUARE * half_xy  # (4, 2)
    x = local[None, :, 0] * c - local[None, :, 1] * s
    y = local[None, :, 0] * s + local[None, :, 1] * c
    return np.stack([x, y], axis=-1) + np.asarray(centres_xy)[:, None, :]


def _quads_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`_polygons_overlap` of every quadrilateral of ``a`` (N, 4, 2) with every one of ``b`` (M, 4, 2):
    (N, M) bool."""
    a, b = np.asarray(a, dtype=np.float64)[:, None], np.asarray(b, dtype=np.float64)[None]
    a, b = np.broadcast_to(a, np.broadcast_shapes(a.shape, b.shape)), np.broadcast_to(b, np.broadcast_shapes(
        a.shape, b.shape))
    axes = []
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=-2) - poly
        axes.append(np.stack([-edges[..., 1], edges[..., 0]], axis=-1))
    axes = np.concatenate(axes, axis=-2)  # (N, M, 8, 2)
    pa = np.einsum("nmvj,nmaj->nmav", a, axes)  # (N, M, 8 axes, 4 vertices)
    pb = np.einsum("nmvj,nmaj->nmav", b, axes)
    separated = (pa.max(axis=-1) <= pb.min(axis=-1)) | (pb.max(axis=-1) <= pa.min(axis=-1))
    return ~separated.any(axis=-1)


def _polygons_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two convex quadrilaterals (4, 2)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.column_stack([-edges[:, 1], edges[:, 0]]):
            pa, pb = a @ [nx, ny], b @ [nx, ny]
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def _box_corners(lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
    return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]], dtype=np.float64)


def candidate_places(area: KittingArea, half_xy: np.ndarray,
                     prefer_near_xy: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Places (centre_xy, direction of the long side in rad) for a footprint of half extents ``half_xy`` (long
    side first), nearest to ``prefer_near_xy`` first, inside the ring and the table and outside the keep-out
    rectangles. The long side runs along the ring or, where that packs better, across it."""
    centre = np.asarray(area.centre_xy, dtype=np.float64)
    lo, hi = np.asarray(area.table_min_xy), np.asarray(area.table_max_xy)
    half_xy = np.asarray(half_xy, dtype=np.float64)
    angles = np.deg2rad(np.arange(-180.0, 180.0, ANGLE_STEP_DEG))
    keep_out = np.array([_box_corners(k_lo, k_hi) for k_lo, k_hi in area.keep_out]).reshape(-1, 4, 2)
    places = []
    for across in (False, True):
        depth = half_xy[0] if across else half_xy[1]  # half extent along the radius
        radii = np.arange(area.inner_radius_m + depth, area.outer_radius_m + 1e-9, RADIAL_STEP_M)
        radius, angle = (grid.ravel() for grid in np.meshgrid(radii, angles, indexing="ij"))
        xy = centre + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
        long_yaw = angle if across else angle + np.pi / 2
        corners = _corners_many(xy, long_yaw, half_xy)
        ok = np.all((corners >= lo) & (corners <= hi), axis=(1, 2))
        if len(keep_out) and ok.any():
            grown = _corners_many(xy[ok], long_yaw[ok], half_xy + area.gap_m / 2)
            ok[np.flatnonzero(ok)] = ~_quads_overlap(grown, keep_out).any(axis=1)
        places += [(xy[k], float(long_yaw[k])) for k in np.flatnonzero(ok)]
    # near the jig, but not at the edge of the reach, where arm configurations are awkward
    comfortable = area.inner_radius_m + COMFORTABLE_FRACTION * (area.outer_radius_m - area.inner_radius_m)
    places.sort(key=lambda p: float(np.linalg.norm(p[0] - prefer_near_xy))
                + FAR_PENALTY * max(0.0, float(np.linalg.norm(p[0] - centre)) - comfortable))
    return places


def footprint_area_m2(meshes: Sequence[trimesh.Trimesh], gap_m: float) -> float:
    """The smallest area the parts can cover lying in their most probable stable poses, each footprint grown
    by half the gap on every side (m^2)."""
    total = 0.0
    for mesh in meshes:
        rest_from_part = stable_rest_poses(mesh, max_poses=1)[0][0]
        rested = mesh.vertices @ rest_from_part[:3, :3].T
        extent = rested.max(axis=0) - rested.min(axis=0)
        total += float((extent[0] + gap_m) * (extent[1] + gap_m))
    return total


def ring_area_m2(area: KittingArea, cell_m: float = 0.01) -> float:
    """Area of the ring that lies on the table and outside the keep-out rectangles (m^2), on a grid."""
    lo, hi = np.asarray(area.table_min_xy), np.asarray(area.table_max_xy)
    xs, ys = np.arange(lo[0], hi[0], cell_m) + cell_m / 2, np.arange(lo[1], hi[1], cell_m) + cell_m / 2
    grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    radius = np.linalg.norm(grid - np.asarray(area.centre_xy), axis=1)
    keep = (radius >= area.inner_radius_m) & (radius <= area.outer_radius_m)
    for k_lo, k_hi in area.keep_out:
        keep &= ~np.all((grid >= k_lo) & (grid <= k_hi), axis=1)
    return float(keep.sum()) * cell_m**2


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
    onto its chocks), and lies where it settles (:data:`SETTLE_MAX_TILT_DEG`, :data:`SETTLE_MAX_DROP_M`); so is a
    part none of whose resting poses gives it a place (a frame of tubes that rocks as laid).
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


class _Layout:
    """The kitting layout being built: slots so far, and the checks of one more part's place."""

    def __init__(self, order: list[str], meshes: dict[str, trimesh.Trimesh], area: KittingArea,
                 prefer: np.ndarray, reach: Reach) -> None:
        self.order, self.meshes, self.area, self.prefer, self.reach = order, meshes, area, prefer, reach
        self.target_rotations: dict[str, np.ndarray] = {}
        self.slots: list[KittingSlot] = []
        self.options: dict[str, list[tuple[Grasp, object]]] = {}  # per slot: (grasp, reach) still possible
        self.usable_at_target: dict[tuple, bool] = {}
        self.places_cache: dict[tuple, list] = {}
        self.support_cache: dict[tuple, Pedestal | None] = {}
        self.half_turn_cache: dict[tuple, bool] = {}  # (part, rest pose) -> the same turned half a turn
        self.leaning_cache: dict[tuple, list[Grasp]] = {}  # (part, rest pose) -> grasps opened for its lean
        self.rests = None  # physics check (loose bodies, fixed bodies) -> bool, see plan_kitting
        self.settles = None  # physics (loose bodies, fixed bodies) -> where they come to rest, see plan_kitting
        self.unrested: set[str] = set()  # parts with no pose that rests on a pedestal
        # parts that rest on a pedestal only wedged into it or its chocks (cell.resting.WEDGED_FORCE_RATIO): the
        # physics checks of their places allow it, as the last resort
        self.wedge_allowed: set[str] = set()
        self.tried: set[str] = set()  # parts for which some place was tried
        self.picked: set[str] = set()  # parts that some place tried lets the hand grasp clear of their support
        self.fingers_freed: set[tuple] = set()  # (part, rest pose) whose pedestal :meth:`_free_fingers` checked
        self.posts_tried: set[tuple] = set()  # (part, rest pose) that :meth:`_onto_posts` tried
        self.failed_on_ground: dict[str, list] = {}  # part -> (rest pose, grasps, probability) without a place

    def rank(self, name: str) -> int:
        return self.order.index(name)

    def _near(self, slot: KittingSlot, corners: np.ndarray) -> bool:
        gaps = np.linalg.norm(slot.footprint_world[:, None] - corners[None], axis=2)
        return bool(np.min(gaps) < NEIGHBOUR_REACH_M) or _polygons_overlap(slot.footprint_world, corners)

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
                        key=lambda pose: -_picks_from_above(grasps[:SCORED_GRASPS], pose[0]))
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

    def _onto_posts(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp],
                    grasp_ok_at_target) -> bool:
        """Whether the part, having found no place on its pedestals in any rest pose (:meth:`place`), now lies on
        posts in this one (:func:`planning.pedestal.posts_under`; the pedestal for this pose replaced): a narrow
        part bent along its length, where some of ``grasps`` clear the posts but not the pedestal and work at the
        target, and which rests on the posts (the physics check, else the geometric one). Tried once per part and
        pose; the part keeps the posts in this pose in later tries of the layout. A part that finds a place on its
        pedestals never gets here: its layout is as without posts."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        pedestal = self.support_cache.get(key)
        if pedestal is None or pedestal.posts or key in self.posts_tried:
            return False
        self.posts_tried.add(key)
        mesh = self.meshes[name]
        posts = posts_under(mesh, rest_from_part, self.area.pedestal_height_m)
        if posts is None:
            return False
        if pedestal.chocks:  # the same chocks cradle it (a round bar rolls on posts as on a box)
            posts_from_pedestal = posts.world_from_pedestal.inverse() @ pedestal.world_from_pedestal
            posts = dataclasses.replace(posts, chocks=tuple((size, posts_from_pedestal @ pose)
                                                            for size, pose in pedestal.chocks))
        on_pedestal = {_grasp_key(g) for g in self._clear_of(grasps, rest_from_part, pedestal)}
        if not any(self._usable_at_target(name, g, grasp_ok_at_target)
                   for g in self._clear_of(grasps, rest_from_part, posts) if _grasp_key(g) not in on_pedestal):
            return False  # (a straight bar's posts are as wide as its pedestal: they free no grasp)
        if not (self._rests(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(posts))
                if self.rests is not None else
                rests_stably(mesh, rest_from_part, [_box_corners(lo, hi) for lo, hi in top_boxes(posts)])):
            return False
        self.support_cache[key] = posts
        return True

    def _ground_poses(self, name: str, poses: list[tuple[np.ndarray, float]]) -> list[tuple[np.ndarray, float]]:
        """The rest poses (rest_from_part, probability) in which the part rests on its pedestal as the geometry
        and the physics check judge them; and the poses it settles in under physics (:meth:`_settled`) when laid
        down as it sits in the assembly (the first of ``poses`` when it has a target rotation) and that does not
        rest as it is, or laid down in each of the first :data:`MAX_GROUND_POSES` when none rests."""
        ground = [pose for pose in poses if self._support(name, pose[0]) is not None]
        if self.settles is not None:
            upright = name in self.target_rotations and self._support(name, poses[0][0]) is None
            ground += self._settled_poses(name, poses if not ground else poses[:1] if upright else [])
        if not ground and self.rests is not None and name not in self.wedge_allowed:
            self.wedge_allowed.add(name)  # no pose rests unwedged: then wedged
            self.support_cache = {key: pedestal for key, pedestal in self.support_cache.items()
                                  if pedestal is not None or key[0] != name}
            return self._ground_poses(name, poses)
        if not ground:
            self.unrested.add(name)
        return ground

    def _settled_poses(self, name: str, poses: list[tuple[np.ndarray, float]]) -> list[tuple[np.ndarray, float]]:
        """Where the part lies once settled (:meth:`_settled`) when laid down in each of the first
        :data:`MAX_GROUND_POSES` of ``poses``, for those it settles in."""
        settled = ((self._settled(name, rest_from_part), p) for rest_from_part, p in poses[:MAX_GROUND_POSES])
        return [(rest_from_part, p) for rest_from_part, p in settled if rest_from_part is not None]

    def _rests(self, name: str, loose: list[tuple[trimesh.Trimesh, Pose]],
               fixed: list[tuple[trimesh.Trimesh, Pose]]) -> bool:
        """The physics check (:attr:`rests`) of part ``name``'s place, wedged allowed where it must be."""
        return bool(self.rests(loose, fixed, allow_wedged=name in self.wedge_allowed))

    def _settles(self, name: str, loose: list[tuple[trimesh.Trimesh, Pose]],
                 fixed: list[tuple[trimesh.Trimesh, Pose]]):
        """Where part ``name`` settles (:attr:`settles`), wedged allowed where it must be."""
        return self.settles(loose, fixed, allow_wedged=name in self.wedge_allowed)

    def _settled(self, name: str, rest_from_part: np.ndarray) -> np.ndarray | None:
        """``rest_from_part`` of the part laid down in this pose on its pedestal (cradled if elongated; else wide,
        when the part does not settle on the usual one) once it has settled there under physics
        (:attr:`settles`), centred over the same pedestal made for it as it lies, which it must rest on too;
        None when it does not settle, or tips beyond :data:`SETTLE_MAX_TILT_DEG` or its centre of mass sinks
        beyond :data:`SETTLE_MAX_DROP_M` on the way (it fell over, off or through), or it does not lie low
        (:data:`SETTLE_MAX_COM_HEIGHT_RATIO`)."""
        mesh = self.meshes[name]
        for wide in (False, True):
            pedestal = self._pedestal_at_rest(name, rest_from_part, wide)
            settled = self._settles(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(pedestal))
            if settled is None:
                continue
            lying = settled[0].matrix()
            if not _settled_low(mesh, rest_from_part, lying):
                continue
            lying[:2, 3] -= _footprint_centre(mesh, lying)  # centred in x-y, as rest poses are
            pedestal = self._pedestal_at_rest(name, lying, wide)
            if self.rests is not None and not self._rests(name, [(mesh, Pose.from_matrix(lying))],
                                                          self._fixed(pedestal)):
                continue
            self.support_cache[(name, np.round(lying, 9).tobytes())] = pedestal
            return lying
        return None

    def _leaning_grasps(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp]) -> list[Grasp]:
        """For a board standing on its edge between chocks in this rest pose: ``grasps`` opened wider at the pick
        (``Grasp.pick_opening_m``; at the target as usual: a wide open hand releasing a cabinet's top there met a
        drawer front) by twice how far its top may move (:func:`planning.pedestal.standing_lean_m`), so that a
        finger coming down beside it clears it leaning either way, then by half that (leaning onto one chock, its
        foot where it stood, as cabinet_13's drawer side did by 6 mm at its top, where a finger with 5 mm to spare
        came down on it), for where the widest opening meets a neighbour; else none. The same copies each time (the
        checks cache them)."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        if key not in self.leaning_cache:
            pedestal = self.support_cache.get(key)
            lean = (0.0 if pedestal is None else
                    standing_lean_m(self.meshes[name], rest_from_part, pedestal, self.area.pedestal_height_m))
            self.leaning_cache[key] = [] if lean <= 0.0 else [
                dataclasses.replace(g, pick_opening_m=min(g.opening_m + 2.0 * share * lean, MAX_OPENING_M))
                for share in LEAN_SHARES for g in grasps if g.opening_m < MAX_OPENING_M]
        return self.leaning_cache[key]

    def _usable_at_target(self, name: str, grasp: Grasp, grasp_ok_at_target) -> bool:
        key = (name, _grasp_key(grasp))
        if key not in self.usable_at_target:
            self.usable_at_target[key] = bool(grasp_ok_at_target(name, grasp))
        return self.usable_at_target[key]

    def _clear_of(self, grasps: Sequence[Grasp], rest_from_part: np.ndarray, pedestal: Pedestal) -> list[Grasp]:
        """The ``grasps`` whose hand clears the pedestal (rest frame) and the table, the part lying on it."""
        return _pickable(grasps, Pose.from_matrix(rest_from_part), self._fixed(pedestal)[:1],
                         -self.area.pedestal_height_m)

    def _free_fingers(self, name: str, rest_from_part: np.ndarray, grasps: Sequence[Grasp],
                      grasp_ok_at_target) -> np.ndarray:
        """The rest pose to try in place of ``rest_from_part``. Where none of the grasps that clear the part's
        pedestal in this pose works at the target (a frame of thin bars lying on it: the fingers closing on a bar
        reach down into the pedestal's top), the pedestal becomes one cut back from one side
        (:meth:`_cut_pedestals`), so that the bars there overhang: the same pose if the part rests on it as it
        is (the physics check, else the geometric one), or where it settles on it (as :meth:`_settled` accepts),
        re-centred with the pedestal; else the pose and pedestal stay."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        pedestal = self.support_cache.get(key)
        if pedestal is None or pedestal.chocks or pedestal.posts or key in self.fingers_freed:
            return rest_from_part
        self.fingers_freed.add(key)
        if any(self._usable_at_target(name, g, grasp_ok_at_target)
               for g in self._clear_of(grasps, rest_from_part, pedestal)):
            return rest_from_part
        mesh, part = self.meshes[name], Pose.from_matrix(rest_from_part)
        usable = lambda grasp: self._usable_at_target(name, grasp, grasp_ok_at_target)  # noqa: E731
        for cut in self._cut_pedestals(name, rest_from_part, pedestal, grasps, usable):
            if (self._rests(name, [(mesh, part)], self._fixed(cut)) if self.rests is not None else
                    rests_stably(mesh, rest_from_part, self._top(cut))):
                self.support_cache[key] = cut
                return rest_from_part
            settled = None if self.settles is None else self._settles(name, [(mesh, part)], self._fixed(cut))
            if settled is None or not _settled_low(mesh, rest_from_part, settled[0].matrix()):
                continue
            lying = settled[0].matrix()
            centre = _footprint_centre(mesh, lying)
            lying[:2, 3] -= centre
            cut = dataclasses.replace(cut, world_from_pedestal=Pose([-centre[0], -centre[1], 0.0], [1, 0, 0, 0])
                                      @ cut.world_from_pedestal)
            if self.rests is not None and not self._rests(name, [(mesh, Pose.from_matrix(lying))],
                                                          self._fixed(cut)):
                continue
            settled_key = (name, np.round(lying, 9).tobytes())
            self.support_cache[settled_key] = cut
            self.fingers_freed.add(settled_key)
            return lying
        return rest_from_part

    def _cut_pedestals(self, name: str, rest_from_part: np.ndarray, pedestal: Pedestal, grasps: Sequence[Grasp],
                       usable: Callable[[Grasp], bool]) -> list[Pedestal]:
        """``pedestal`` (rest frame) cut back by :data:`FRAME_CUTS_M` from one side: per side the smallest cut that
        frees some of the ``grasps`` that are ``usable`` (at the target) and leaves the part's centre of mass over
        the top, the sides freeing the most grasps first."""
        com = (rest_from_part[:3, :3] @ centre_of_mass(self.meshes[name]) + rest_from_part[:3, 3])[:2]
        found = []
        for side in ((0, 1), (0, -1), (1, 1), (1, -1)):
            for cut_m in FRAME_CUTS_M:
                cut = cut_back(pedestal, side, cut_m)
                lo, hi = top_box(cut)
                if np.any(com < lo + SUPPORT_MARGIN_M) or np.any(com > hi - SUPPORT_MARGIN_M):
                    break  # cut back past its centre of mass
                freed = sum(map(usable, self._clear_of(grasps, rest_from_part, cut)))
                if freed:
                    found.append((freed, len(found), cut))
                    break
        return [cut for _, _, cut in sorted(found, key=lambda f: (-f[0], f[1]))]

    def _pedestal_at_rest(self, name: str, rest_from_part: np.ndarray, wide: bool = False) -> Pedestal:
        """The pedestal made for the part in this rest pose (rest frame: its top at z = 0 under the footprint's
        centre), with chocks if the part is elongated."""
        mesh = self.meshes[name]
        pedestal = pedestal_for(_rest_half(mesh, rest_from_part)[0], Pose([0, 0, 0], [1, 0, 0, 0]),
                                self.area.pedestal_height_m, wide)
        return dataclasses.replace(pedestal, chocks=cradle_chocks(mesh, rest_from_part, self.area.pedestal_height_m)
                                   or ())

    def _fixed(self, pedestal: Pedestal) -> list[tuple[trimesh.Trimesh, Pose]]:
        """A rest-frame pedestal and the table under it, for the physics checks."""
        return [(pedestal.mesh(), pedestal.world_from_pedestal), self._table_slab(-self.area.pedestal_height_m)]

    def _ground_places(self, name: str, rest_from_part: np.ndarray):
        at_rest = self._support(name, rest_from_part)
        if at_rest is None:
            return  # it does not rest in this pose, anywhere: try the next rest pose
        mesh_half, long_is_x = _rest_half(self.meshes[name], rest_from_part)
        half_ring = np.array([max(mesh_half), min(mesh_half)])
        key = tuple(np.round(half_ring, 4))
        if key not in self.places_cache:
            self.places_cache[key] = candidate_places(self.area, half_ring, self.prefer)
        places = self.places_cache[key]
        if not places:
            return
        taken = np.zeros(len(places), dtype=bool)
        if self.slots:  # places whose footprint (grown by half the gap) meets a slot's
            grown = _corners_many(np.array([xy for xy, _ in places]), np.array([yaw for _, yaw in places]),
                                  half_ring + self.area.gap_m / 2)
            taken = _quads_overlap(grown, np.array([s.footprint_world for s in self.slots])).any(axis=1)
        for (xy, long_yaw), skip in zip(places, taken):
            if skip:
                continue
            yaw = long_yaw if long_is_x else long_yaw - np.pi / 2  # the rest frame's long axis along long_yaw
            # and turned half a turn on the same footprint: the other edge faces the robot (chair_ivar_0668's side
            # lying flat is held at the target by an edge that faced away from the arm in every place)
            for turn in (0.0, np.pi) if not self._half_turn_alike(name, rest_from_part) else (0.0,):
                world_from_rest = Pose([xy[0], xy[1], self.area.table_z_m + self.area.pedestal_height_m],
                                       [1, 0, 0, 0]) @ _yaw(yaw + turn)
                pedestal = dataclasses.replace(at_rest,
                                               world_from_pedestal=world_from_rest @ at_rest.world_from_pedestal)
                yield world_from_rest, _corners(xy, long_yaw, half_ring), pedestal, None

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
        half, long_is_x = _rest_half(self.meshes[name], rest_from_part)
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
                corners = _corners(xy, base_long_yaw, half_ring)
                lo, hi = np.asarray(self.area.table_min_xy), np.asarray(self.area.table_max_xy)
                if np.any(corners < lo) or np.any(corners > hi):
                    continue
                grown = _corners(xy, base_long_yaw, half_ring + self.area.gap_m / 2)
                stack = self._stack_of(base)
                if any(_polygons_overlap(grown, s.footprint_world) for s in self.slots if s.part not in stack):
                    continue
                yaw = base_long_yaw if long_is_x else base_long_yaw - np.pi / 2
                world_from_rest = Pose([xy[0], xy[1], top_z], [1, 0, 0, 0]) @ _yaw(yaw)
                top_rest = world_from_rest.inverse().apply(np.column_stack([
                    _corners(base_centre, base_long_yaw, base_half), np.full(4, top_z)]))[:, :2]
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

    def _support(self, name: str, rest_from_part: np.ndarray) -> Pedestal | None:
        """The pedestal (rest frame, see :meth:`_pedestal_at_rest`) the part rests on in this pose, the same
        anywhere: alone, or with the chocks that cradle it; None when it does not rest there (computed once per
        part and pose; :meth:`_settled` adds the poses it finds)."""
        key = (name, np.round(rest_from_part, 9).tobytes())
        if key not in self.support_cache:
            mesh = self.meshes[name]
            pedestal = pedestal_for(_rest_half(mesh, rest_from_part)[0], Pose([0, 0, 0], [1, 0, 0, 0]),
                                    self.area.pedestal_height_m)
            chocks = () if self._supported(name, rest_from_part, pedestal) else chocks_for(
                mesh, rest_from_part, self.area.pedestal_height_m, self._top(pedestal))
            pedestal = None if chocks is None else dataclasses.replace(pedestal, chocks=chocks)
            if pedestal is not None and self.rests is not None:  # and it stays there under physics
                if not self._rests(name, [(mesh, Pose.from_matrix(rest_from_part))], self._fixed(pedestal)):
                    pedestal = None
            self.support_cache[key] = pedestal
        return self.support_cache[key]

    @staticmethod
    def _table_slab(top_z_m: float) -> tuple[trimesh.Trimesh, Pose]:
        """A 2 m x 2 m table top at height ``top_z_m`` (world), for the physics check of resting parts (one shared
        mesh, so the check recognises it without hashing a new one each time)."""
        return _TABLE_SLAB, Pose([0.0, 0.0, top_z_m - 0.5 * _TABLE_SLAB.extents[2]], [1.0, 0.0, 0.0, 0.0])

    def _supported(self, name: str, rest_from_part: np.ndarray, pedestal: Pedestal) -> bool:
        return rests_stably(self.meshes[name], rest_from_part, self._top(pedestal))

    @staticmethod
    def _top(pedestal: Pedestal) -> np.ndarray:
        """The pedestal's top outline (4, 2) in the rest frame (centred under the part, or cut back off centre; its
        main box only, for a pedestal of posts)."""
        return _box_corners(*top_box(pedestal))

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
        tips = _tips_under(mesh, world_from_part)
        self.tried.add(name)
        at_pick = {_grasp_key(g) for g in _pickable(grasps, world_from_part, own, self.area.table_z_m,
                                                     self.obstacles_at_pick(name, corners)) if not tips(g)}
        if at_pick or (name not in self.picked and _pickable(grasps, world_from_part, own, self.area.table_z_m)):
            self.picked.add(name)  # some grasp clears its support here (the other slots' bodies aside)
        # the support (own pedestal, or the board under it) is left out: the grasp check covered the hand
        present = [o for slot in self.slots if base is None or slot.part != base.part
                   for o in self._bodies(slot, name)]
        support = own + ([] if base is None else self._bodies(base, name))

        def level(grasp: Grasp) -> bool:  # the fingers close across gravity: neither tip drops onto the support
            return _finger_tilt(world_from_part.rotation, grasp) <= LEVEL_FINGERS

        def steepness(grasp: Grasp) -> int:  # how far from straight down the hand approaches, in 15-degree steps
            down = -float((world_from_part.rotation @ grasp.part_from_tcp.rotation[:, 2])[2])
            return int(np.degrees(np.arccos(np.clip(down, -1.0, 1.0))) // 15.0)

        def options():  # (grasp, arm configurations): level fingers first, then the steepest approach from above
            # (the fingertips keep level above the support), else in the caller's order (best at the target first)
            usable = [g for g in grasps if _grasp_key(g) in at_pick]
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
                                                  _neighbour_hand_for(slot.world_from_part, grasp)))
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


def _settled_low(mesh: trimesh.Trimesh, rest_from_part: np.ndarray, lying: np.ndarray) -> bool:
    """Whether a part laid down in ``rest_from_part`` that settled in ``lying`` (both rest frames, 4x4) lies as
    :meth:`_Layout._settled` accepts: turned by at most :data:`SETTLE_MAX_TILT_DEG`, its centre of mass sunk by at
    most :data:`SETTLE_MAX_DROP_M`, and lying low (:data:`SETTLE_MAX_COM_HEIGHT_RATIO`)."""
    com = centre_of_mass(mesh)
    turned = lying[:3, :3] @ rest_from_part[:3, :3].T
    tilt = np.degrees(np.arccos(np.clip(turned[2, 2], -1.0, 1.0)))  # how far its up axis turned
    drop = float((rest_from_part[:3, :3] @ com)[2] + rest_from_part[2, 3] - (lying[:3, :3] @ com)[2] - lying[2, 3])
    moved = mesh.vertices @ lying[:3, :3].T + lying[:3, 3]
    half = 0.5 * np.ptp(moved[:, :2], axis=0)
    # lying low: untouched, a part standing on a narrow base balances, and tips over at the first nudge
    low = (lying[:3, :3] @ com)[2] + lying[2, 3] <= SETTLE_MAX_COM_HEIGHT_RATIO * half.min()
    return bool(tilt <= SETTLE_MAX_TILT_DEG and drop <= SETTLE_MAX_DROP_M and low)


def _footprint_centre(mesh: trimesh.Trimesh, rest_from_part: np.ndarray) -> np.ndarray:
    """Centre (x, y) of the posed part's bounding box in the rest frame."""
    moved = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    return 0.5 * (moved.min(axis=0) + moved.max(axis=0))[:2]


def _rest_half(mesh: trimesh.Trimesh, rest_from_part: np.ndarray) -> tuple[np.ndarray, bool]:
    """Half extents (x, y) of the part's footprint in its rest frame, and whether x is the long side."""
    rested = mesh.vertices @ rest_from_part[:3, :3].T
    half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
    return half, bool(half[0] >= half[1])


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


def _finger_tilt(world_from_part_rotation: np.ndarray, grasp: Grasp) -> float:
    """|sin| of the angle between the fingers' closing axis and the horizontal, the part turned as given."""
    return abs(float((world_from_part_rotation @ grasp.part_from_tcp.rotation[:, 1])[2]))


def _slanted(world_from_part: Pose, grasp: Grasp) -> bool:
    """Whether the fingers close neither level nor vertically at this pose of the part."""
    return LEVEL_FINGERS < _finger_tilt(world_from_part.rotation, grasp) < np.cos(np.radians(10.0))


def _tips_under(mesh: trimesh.Trimesh, world_from_part: Pose):
    """``tips(grasp)``: whether the part, standing at ``world_from_part``, would tip over its foot as the hand of
    ``grasp`` closes on it: the approach is slanted (:data:`SLANTED_APPROACH`), the fingers close level
    (:data:`LEVEL_FINGERS`), and along the horizontal direction across the closing axis (the fingers' flat pads
    leave a turn about that axis free; chocks hold a standing board along it) the foot straddles the centre of
    mass but reaches less than 1 / :data:`TIPPING_HEIGHT_RATIO` of its height from it. A foot (the points within
    :data:`FOOT_M` of the lowest) to one side of the centre of mass is not all the part rests on (chair_agne_0010's
    curved frame lying flat, which the rest check found stable): not judged."""
    rotation = world_from_part.rotation
    points = mesh.vertices @ rotation.T
    low = float(points[:, 2].min())
    foot = points[points[:, 2] <= low + FOOT_M]
    com = rotation @ centre_of_mass(mesh)
    height = float(com[2]) - low

    def tips(grasp: Grasp) -> bool:
        tcp = rotation @ grasp.part_from_tcp.rotation
        if -float(tcp[2, 2]) >= SLANTED_APPROACH:
            return False
        if abs(float(tcp[2, 1])) > LEVEL_FINGERS:
            return False  # the fingers close on a tilt: not a part standing between level fingers
        across = np.cross(tcp[:, 1], [0.0, 0.0, 1.0])
        along = (foot - com) @ (across / np.linalg.norm(across))
        lever = min(float(along.max()), float(-along.min()))
        return 0.0 <= lever and lever * TIPPING_HEIGHT_RATIO < height

    return tips


def _picks_from_above(grasps: Sequence[Grasp], rest_from_part: np.ndarray) -> int:
    """How many ``grasps`` approach from above with level fingers when the part lies in this rest pose."""
    rotation = rest_from_part[:3, :3]
    return sum(float((rotation @ grasp.part_from_tcp.rotation[:, 2])[2]) <= -FROM_ABOVE
               and _finger_tilt(rotation, grasp) <= LEVEL_FINGERS for grasp in grasps)


def clear_at_pick(grasps: Sequence[Grasp], world_from_part: Pose, obstacles, floor_z: float,
                  gripper, approach_m: float = 0.0) -> list[Grasp]:
    """The ``grasps`` (in their order) whose hand is clear of ``obstacles`` both opened to its opening at the pick
    (``Grasp.opening_at_pick_m``), as it arrives (over the last ``approach_m`` of its straight approach too), and
    closed to ``width_m`` on the part, as it lifts: a closing fingertip that reaches below a board's edge moves
    towards the pedestal under it (5 mm per finger), which the open hand alone does not show."""
    arriving = [dataclasses.replace(g, opening_m=g.opening_at_pick_m) for g in grasps]
    kept = {_grasp_key(g) for g in feasible_grasps(arriving, world_from_part, obstacles, None, floor_z=floor_z,
                                                   retreat_m=approach_m, gripper=gripper, closed_gripper=gripper)}
    return [g for g, at_pick in zip(grasps, arriving) if _grasp_key(at_pick) in kept]


def _neighbour_hand_for(world_from_part: Pose, grasp: Grasp):
    """The hand model a grasp at the pick is checked with against other slots' bodies: :data:`TILTED_HAND` where
    its fingers close on a slant, else :data:`NEIGHBOUR_HAND`."""
    return TILTED_HAND if _slanted(world_from_part, grasp) else NEIGHBOUR_HAND


def _pickable(grasps: Sequence[Grasp], world_from_part: Pose, support, floor_z: float,
              neighbours=()) -> list[Grasp]:
    """The ``grasps`` clear at the pick (:func:`clear_at_pick`) of the ``support`` (the part's pedestal) and the
    floor with :data:`HAND`, along the whole straight approach (the arm's motion does not check the hand against
    them), and of the ``neighbours`` (other slots' bodies; for a board lying on a board, the one under it too) with
    :data:`NEIGHBOUR_HAND`; those whose fingers close on a slant checked with :data:`TILTED_HAND` against both."""
    feasible = clear_at_pick(grasps, world_from_part, support, floor_z, HAND, approach_m=APPROACH_M)
    if neighbours and feasible:
        feasible = clear_at_pick(feasible, world_from_part, list(neighbours), None, NEIGHBOUR_HAND)
    slanted = [g for g in feasible if _slanted(world_from_part, g)]
    spoiled = {_grasp_key(g) for g in slanted} - {_grasp_key(g) for g in clear_at_pick(
        slanted, world_from_part, list(support) + list(neighbours), floor_z, TILTED_HAND)}
    return [g for g in feasible if _grasp_key(g) not in spoiled]


def _grasp_key(grasp: Grasp) -> tuple:
    """The same grasp whatever its ranking scores (ranking returns re-scored copies), at the same openings."""
    return grasp_pose_key(grasp) + (round(grasp.opening_m, 9), round(grasp.opening_at_pick_m, 9))


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
