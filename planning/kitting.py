"""Kitting: where and how each loose part lies before the robot picks it.

Every part starts at rest in one of its stable poses (trimesh's ``compute_stable_poses``) on a pedestal in the
kitting area. A pedestal is a box under the part, inset from its footprint like the jig pads
(:mod:`planning.fixture`), so that fingers can reach under a board's edge.

The kitting area is a ring around the robot base on the table (:class:`KittingArea`): between an inner radius
(clear of the robot's base) and an outer radius (within reach), inside the table, outside keep-out rectangles
(the jig with the assembly growing on it, plus room for the hand). Each part's footprint is a rectangle turned
so that its long side runs along the ring (tangential). Candidate places are tried nearest to the jig first.

For each part the planner takes the most probable stable pose and the first place where

- the footprint, grown by the gap, overlaps no other part's and no keep-out rectangle and lies on the table;
- some grasp works at the pick, clear of its pedestal, the table and the neighbouring parts and pedestals, and
  the same grasp works at the target (``grasp_ok_at_target``) and the robot reaches it (``reachable``);
- the grasps already chosen for the neighbours stay clear of the new part.

Frames: every pose is in the world frame of the cell (metres, +z up, table top at ``table_z_m``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from planning.fixture import FINGER_CLEARANCE_M, MIN_PAD_FRACTION
from planning.grasp import Grasp, feasible_grasps
from planning.pose import Pose

NEIGHBOUR_REACH_M = 0.25  # parts whose footprints are farther apart than this cannot touch each other's hand
MAX_PLACES_PER_POSE = 40  # places tried (with grasp checks) for one stable pose before the next pose
RADIAL_STEP_M = 0.03
CAPACITY_FRACTION = 0.75  # rectangles in a ring pack no denser than this: fail at once above it
ANGLE_STEP_DEG = 3.0


@dataclass(frozen=True)
class Pedestal:
    size_m: tuple[float, float, float]
    world_from_pedestal: Pose  # box centre

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.creation.box(self.size_m)


@dataclass(frozen=True)
class KittingSlot:
    """Where one part starts: its pose (world), the pedestal under it, and the grasp to pick and place it."""

    part: str
    world_from_part: Pose
    pedestal: Pedestal
    grasp: Grasp
    stable_pose_probability: float
    footprint_world: np.ndarray  # (4, 2) corners of the footprint rectangle, world x-y, metres
    reach: object = None  # what ``Reach.at_pick`` returned (e.g. the arm configurations), for ``still_clear``


class Reach:
    """The robot's side of kitting (the planner stays free of robot models): override both methods.

    ``at_pick(part, grasp, world_from_part, obstacles)``: something truthy (e.g. the arm configurations that
    reach the grasp) when the robot reaches the grasp without touching ``obstacles`` (mesh, world pose) pairs,
    else None. ``still_clear(reach, obstacles)``: whether those configurations still touch nothing when
    ``obstacles`` are added next to the part.
    """

    def at_pick(self, part: str, grasp: Grasp, world_from_part: Pose,
                obstacles: list[tuple[trimesh.Trimesh, Pose]]) -> object | None:
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


class KittingError(RuntimeError):
    """No stable pose and grasp serve a part at both pick and place, or the parts do not fit the area."""


def stable_rest_poses(mesh: trimesh.Trimesh, max_poses: int = 6) -> list[tuple[np.ndarray, float]]:
    """(rest_from_part 4x4, probability), most probable first: the part resting on z = 0, centred in x-y."""
    transforms, probabilities = trimesh.poses.compute_stable_poses(mesh, n_samples=1, threshold=0.0)
    out = []
    for transform, probability in sorted(zip(transforms, probabilities), key=lambda tp: -tp[1])[:max_poses]:
        moved = mesh.vertices @ transform[:3, :3].T + transform[:3, 3]
        centre = 0.5 * (moved.min(axis=0) + moved.max(axis=0))
        shift = np.eye(4)
        shift[:3, 3] = [-centre[0], -centre[1], -moved[:, 2].min()]
        out.append((shift @ transform, float(probability)))
    return out


def pedestal_for(half_extent_xy: np.ndarray, world_from_rest: Pose, height_m: float) -> Pedestal:
    """A pedestal under a footprint of half extents ``half_extent_xy`` centred in the ``rest`` frame (whose x-y
    plane is the pedestal's top), inset for the fingers."""
    extent = 2.0 * np.asarray(half_extent_xy, dtype=np.float64)
    inset = np.minimum(FINGER_CLEARANCE_M, 0.5 * (1.0 - MIN_PAD_FRACTION) * extent)
    size = np.maximum(extent - 2 * inset, 1e-3)
    rest_from_pedestal = Pose([0.0, 0.0, -0.5 * height_m], [1.0, 0.0, 0.0, 0.0])
    return Pedestal((float(size[0]), float(size[1]), height_m), world_from_rest @ rest_from_pedestal)


def _yaw(angle_rad: float) -> Pose:
    return Pose([0.0, 0.0, 0.0], [np.cos(angle_rad / 2), 0.0, 0.0, np.sin(angle_rad / 2)])


def _corners(centre_xy: np.ndarray, yaw_rad: float, half_xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half_xy
    return local @ np.array([[c, s], [-s, c]]) + centre_xy


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
    places = []
    for across in (False, True):
        depth = half_xy[0] if across else half_xy[1]  # half extent along the radius
        for radius in np.arange(area.inner_radius_m + depth, area.outer_radius_m + 1e-9, RADIAL_STEP_M):
            for angle in np.deg2rad(np.arange(-180.0, 180.0, ANGLE_STEP_DEG)):
                xy = centre + radius * np.array([np.cos(angle), np.sin(angle)])
                long_yaw = angle if across else angle + np.pi / 2
                corners = _corners(xy, long_yaw, half_xy)
                if np.any(corners < lo) or np.any(corners > hi):
                    continue
                grown = _corners(xy, long_yaw, half_xy + area.gap_m / 2)
                if any(_polygons_overlap(grown, _box_corners(k_lo, k_hi)) for k_lo, k_hi in area.keep_out):
                    continue
                places.append((xy, float(long_yaw)))
    places.sort(key=lambda p: float(np.linalg.norm(p[0] - prefer_near_xy)))
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
                 prefer_near_xy: Sequence[float] = (0.5, 0.0), reach: Reach | None = None) -> list[KittingSlot]:
    """A slot for every part (returned in the order given), the largest footprints laid out first, each in the
    free place nearest ``prefer_near_xy`` (usually the jig). Each part's ``candidates`` are tried in the order
    given (rank them for the target: the pick is usually the easier end).

    ``grasp_ok_at_target(part, grasp)`` says whether a grasp (part frame) also works where the part is placed;
    ``reach`` whether the robot's arm reaches it at the pick among the parts already laid out (and keeps
    reaching the earlier parts once the new one lies next to them).
    """
    reach = reach or Reach()
    slots: list[KittingSlot] = []
    placed_meshes: dict[str, trimesh.Trimesh] = {}
    prefer = np.asarray(prefer_near_xy, dtype=np.float64)
    needed, offered = footprint_area_m2(meshes, area.gap_m), ring_area_m2(area)
    if needed > CAPACITY_FRACTION * offered:
        raise KittingError(f"the parts need about {needed:.2f} m2 of kitting area lying on their largest faces "
                           f"(gaps included), the kitting ring offers {offered:.2f} m2 within reach on the table: "
                           "the object is too large for this cell (use a scaled-down model of it, or a scene "
                           "with a larger kitting area)")
    # largest footprints first (they need the roomy places), ties in the order given
    area_of = {name: float(np.prod(np.sort(mesh.extents)[1:])) for name, mesh in zip(names, meshes)}
    by_size = sorted(range(len(names)), key=lambda k: (-round(area_of[names[k]], 4), k))
    for name, mesh in ((names[k], meshes[k]) for k in by_size):
        chosen = _place_one(name, mesh, candidates[name], grasp_ok_at_target, area, prefer, reach, slots,
                            placed_meshes)
        if chosen is None:
            raise KittingError(_why_not(name, mesh, candidates[name], grasp_ok_at_target, area, prefer))
        slots.append(chosen)
        placed_meshes[name] = mesh
    return sorted(slots, key=lambda slot: names.index(slot.part))


def _obstacles_near(slots: list[KittingSlot], corners: np.ndarray,
                    meshes: dict[str, trimesh.Trimesh]) -> list[tuple[trimesh.Trimesh, Pose]]:
    near = []
    for slot in slots:
        if np.min(np.linalg.norm(slot.footprint_world[:, None] - corners[None], axis=2)) < NEIGHBOUR_REACH_M:
            near.append((meshes[slot.part], slot.world_from_part))
            near.append((slot.pedestal.mesh(), slot.pedestal.world_from_pedestal))
    return near


def _place_one(name, mesh, grasps, grasp_ok_at_target, area, prefer, reach, slots,
               meshes) -> KittingSlot | None:
    occupied = [s.footprint_world for s in slots]
    usable_at_target: dict[int, bool] = {}
    for rest_from_part, probability in stable_rest_poses(mesh):
        rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
        half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
        long_is_x = half[0] >= half[1]
        half_ring = np.array([max(half), min(half)])  # along the ring, across it
        tried = 0
        for xy, long_yaw in candidate_places(area, half_ring, prefer):
            yaw = long_yaw if long_is_x else long_yaw - np.pi / 2  # the rest frame's long axis along long_yaw
            corners = _corners(xy, long_yaw, half_ring)
            grown = _corners(xy, long_yaw, half_ring + area.gap_m / 2)
            if any(_polygons_overlap(grown, other) for other in occupied):
                continue
            tried += 1
            if tried > MAX_PLACES_PER_POSE:
                break
            world_from_rest = Pose([xy[0], xy[1], area.table_z_m + area.pedestal_height_m], [1, 0, 0, 0]) @ _yaw(yaw)
            world_from_part = world_from_rest @ Pose.from_matrix(rest_from_part)
            pedestal = pedestal_for(half, world_from_rest, area.pedestal_height_m)
            own = [(pedestal.mesh(), pedestal.world_from_pedestal)]
            obstacles = own + _obstacles_near(slots, corners, meshes)
            chosen, reached = None, None
            at_pick = {_grasp_key(g) for g in feasible_grasps(grasps, world_from_part, obstacles, None,
                                                              floor_z=area.table_z_m)}
            for grasp in (g for g in grasps if _grasp_key(g) in at_pick):  # caller's order (best at target first)
                key = id(grasp)
                if key not in usable_at_target:
                    usable_at_target[key] = bool(grasp_ok_at_target(name, grasp))
                if not usable_at_target[key]:
                    continue
                others = [o for s in slots for o in ((meshes[s.part], s.world_from_part),
                                                               (s.pedestal.mesh(), s.pedestal.world_from_pedestal))]
                reached = reach.at_pick(name, grasp, world_from_part, others)
                if reached is not None:
                    chosen = grasp
                    break
            if chosen is None:
                continue
            if not _neighbours_still_graspable(slots, mesh, world_from_part, pedestal, corners, area):
                continue
            new = [(mesh, world_from_part), (pedestal.mesh(), pedestal.world_from_pedestal)]
            if not all(reach.still_clear(s.reach, new) for s in slots):
                continue
            return KittingSlot(name, world_from_part, pedestal, chosen, probability, corners, reached)
    return None


def _grasp_key(grasp: Grasp) -> tuple:
    """The same grasp whatever its ranking scores (ranking returns re-scored copies)."""
    return (tuple(np.round(grasp.part_from_tcp.position, 9)), tuple(np.round(grasp.part_from_tcp.quat_wxyz, 9)),
            round(grasp.opening_m, 9))


def _neighbours_still_graspable(slots, mesh, world_from_part, pedestal, corners, area) -> bool:
    for slot in slots:
        if np.min(np.linalg.norm(slot.footprint_world[:, None] - corners[None], axis=2)) >= NEIGHBOUR_REACH_M:
            continue
        obstacles = [(mesh, world_from_part), (pedestal.mesh(), pedestal.world_from_pedestal),
                     (slot.pedestal.mesh(), slot.pedestal.world_from_pedestal)]
        if not feasible_grasps([slot.grasp], slot.world_from_part, obstacles, None, floor_z=area.table_z_m):
            return False
    return True


def _why_not(name, mesh, grasps, grasp_ok_at_target, area, prefer) -> str:
    if not grasps:
        return f"part {name!r}: no grasp at all"
    if not any(grasp_ok_at_target(name, g) for g in grasps):
        return f"part {name!r}: no grasp works at its target"
    rest_from_part = stable_rest_poses(mesh)[0][0]
    rested = mesh.vertices @ rest_from_part[:3, :3].T + rest_from_part[:3, 3]
    half = 0.5 * (rested.max(axis=0) - rested.min(axis=0))[:2]
    if not candidate_places(area, np.array([max(half), min(half)]), prefer):
        return (f"part {name!r}: its footprint ({2 * max(half):.2f} x {2 * min(half):.2f} m) does not fit the kitting "
                f"ring ({area.inner_radius_m:.2f}-{area.outer_radius_m:.2f} m around the robot, on the table)")
    return (f"part {name!r}: no free place in the kitting ring where one grasp works at the pick (reachable, clear "
            "of its neighbours) and at its target")
