"""Parallel-jaw grasps for the Panda hand, expressed in the part's mesh frame.

A :class:`Grasp` holds ``part_from_tcp``: the TCP frame of :mod:`planning.gripper` (+z approach, from the hand
towards the fingertips; +y the finger closing axis; origin between the pads) in the part's own frame, so one grasp
serves at pick (``world_from_tcp = world_from_part_in_kit @ part_from_tcp``) and at place (the same with the
part's target pose).

Pipeline
--------
1. :func:`antipodal_grasps`: sample surface points with normals (seeded), cast a ray from each point along its inward
   normal to the opposite surface (the first surface it meets and, for a part that is not convex, the last: across a
   hollow tube's outside, not only across its wall), keep pairs whose normals oppose each other within the friction
   cone (``mu = 0.5``) and whose width fits the hand (at most :data:`MAX_GRASP_WIDTH_M`). Around each contact axis
   try ``n_approaches`` approach directions; keep the poses at which the hand and fingers, opened to the contact
   width plus :data:`GRASP_CLEARANCE_M`, do not collide with the part (FCL), there nor on the straight approach of
   :data:`APPROACH_M` along the approach axis that ends there (the hand swept back, one convex check), neither the
   mesh nor its convex pieces (:func:`planning.convex.convex_pieces`: the part as the simulator and the arm's planner
   see it, which may bulge past the mesh by centimetres where it is concave), and the fingers closed to the contact
   width plus :data:`CLOSING_SLACK_M` do not touch the mesh (the pads meet the contact pair first). Score them
   part-intrinsically (near the centroid, pads fully on the surface), remove near-duplicates and keep the best
   ``max_candidates``. Results are cached per (mesh, seed, parameters).
2. :func:`rank`: rescore for a use: approach compatible with the insertion direction and top-down at the target.
3. :func:`feasible_grasps`: keep grasps whose hand is collision-free against the obstacles around the part's pose
   (and along the last centimetres of the insertion motion) and above the floor, best first.

Insertion convention: ``insertion_direction_world`` is the unit direction in which the part moves as it goes into
its target (``(0, 0, -1)`` for a leg pushed down into a seat). The hand must trail the part, not lead it: its
approach direction (hand to fingertips) should point along the insertion, ``approach . insertion >= 0``; a grasp
whose approach points against it (the hand on the side the part is heading for) is ranked low and, past
``min_insertion_alignment``, dropped by :func:`feasible_grasps`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numpy as np
import trimesh

from planning.collision import hull_edge_axes
from planning.convex import convex_pieces, mesh_key
from planning.gripper import (
    FINGER_PAD_WIDTH_M,
    HAND_FROM_TCP,
    MAX_OPENING_M,
    PAD_Z_RANGE_IN_TCP_M,
    TCP_TO_PALM_M,
    USABLE_FINGER_DEPTH_M,
    GripperCollisionModel,
    default_gripper,
    mesh_to_fcl,
)
from planning.pose import Pose
from planning.stability import centre_of_mass

__all__ = [
    "APPROACH_M",
    "CLOSING_SLACK_M",
    "FRICTION_COEFFICIENT",
    "GRASP_CLEARANCE_M",
    "MIN_SIDE_CLEARANCE_M",
    "MAX_GRASP_WIDTH_M",
    "Grasp",
    "GraspWeights",
    "NoGraspError",
    "ObstacleSet",
    "antipodal_grasps",
    "rank",
    "feasible_grasps",
    "grasp_pose_key",
    "explain_no_grasp",
    "thinnest_width_m",
    "mesh_key",
]

FRICTION_COEFFICIENT = 0.5
"""Coulomb friction assumed between pads and part: contact normals may lean atan(0.5) = 26.6 deg off the axis."""
GRASP_CLEARANCE_M = 0.01
"""The hand approaches with its fingers this much wider than the part (5 mm each side), capped at 8 cm."""
APPROACH_M = 0.08
"""The hand comes to a grasp in a straight line along its approach axis over this distance, opened to the grasp's
opening, and leaves it the same way after release; a grasp is kept only if that line is clear of the part."""
CLOSING_SLACK_M = 0.002
"""A grasp is kept only if the fingers closed to its width plus this (1 mm each side) do not touch the part:
closing, the pads meet the contact pair before anything else."""
MIN_SIDE_CLEARANCE_M = 0.0025
"""At least this gap each side while approaching, which caps the graspable width."""
MAX_GRASP_WIDTH_M = MAX_OPENING_M - 2 * MIN_SIDE_CLEARANCE_M
"""Widest part section the hand can grasp: 0.075 m."""

_RAY_INSET_M = 1e-4  # rays start this far inside the surface so they cannot hit their own face
_MIN_WIDTH_M = 5e-4
_CENTROID_SCALE_M = 0.10  # centroid_score = exp(-distance / scale)
_PROBE_HALF_THICKNESS_M = 0.0015  # a pad cell touches the surface if it passes within this of the contact plane
_PAD_CELLS_X, _PAD_CELLS_Z = 2, 2
_DEDUP_POSITION_M = 0.008
_DEDUP_DIRECTION_STEPS = 3  # direction components rounded to 1/3
_CACHE_SIZE = 128
_PAIRS_PER_CHUNK = 16
_ENOUGH_DISTINCT_FACTOR = 2  # stop checking poses once 2 x max_candidates distinct collision-free ones are found
# the best-scored candidates fill this share of the list; the rest is spread over the part, a candidate from each
# SPREAD_CELL_M cube of TCP positions in turn: best-by-score alone can put every candidate on the edge nearest the
# centre of mass (table_klubbo_0740's rails, an L of a long apron and a short leg: all 400 best lay on the apron's
# edge, which the table top's groove covers; the leg's end, the only free place at the target, had none)
BEST_SHARE = 0.7
SPREAD_CELL_M = 0.05


class NoGraspError(ValueError):
    """No parallel-jaw grasp exists for a part; the message says why (thickness, collisions)."""


@dataclass(frozen=True)
class GraspWeights:
    """Weights of the score components (each component lies in [0, 1])."""

    centroid: float = 1.0  # TCP near the part's centre of mass: less torque at the pads
    contact: float = 1.0  # both pads fully on the surface
    insertion: float = 1.5  # approach along the insertion motion (hand trails the part)
    top_down: float = 0.5  # approach pointing down (world -z) at the target


DEFAULT_WEIGHTS = GraspWeights()


@dataclass(frozen=True, eq=False)
class Grasp:
    """A parallel-jaw grasp of one part, in the part's mesh frame.

    part_from_tcp: TCP pose (see :mod:`planning.gripper`) in the part frame, metres.
    width_m: distance between the two contact points (the opening at contact), metres.
    opening_m: opening used to approach the part (``width_m + GRASP_CLEARANCE_M``, at most 0.08), metres.
    score: weighted sum of the components below (higher is better); each component lies in [0, 1]:
    centroid_score: ``exp(-d / 0.1 m)``, d the TCP's distance to the part's centre of mass;
    contact_score: fraction of the two pads' area over the part's surface (2 x 2 cells per pad);
    insertion_score: ``(1 + approach . insertion) / 2`` in the world, 0.5 when no insertion direction is given;
    top_down_score: ``(1 - approach_z) / 2`` in the world at the target, 0.5 when no target pose is given.
    contacts_part: (2, 3) the two contact points in the part frame, metres (first at -y, second at +y of the TCP).
    pick_opening_m: opening used to approach the part where it is picked, when wider than ``opening_m`` (a board
    standing between chocks may lean: :mod:`planning.kitting_support`), metres; None: ``opening_m`` there too.
    """

    part_from_tcp: Pose
    width_m: float
    opening_m: float
    score: float
    centroid_score: float
    contact_score: float
    insertion_score: float = 0.5
    top_down_score: float = 0.5
    contacts_part: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((2, 3)), repr=False)
    pick_opening_m: float | None = None

    @property
    def opening_at_pick_m(self) -> float:
        """The opening the hand approaches the part with where it is picked, metres."""
        return self.opening_m if self.pick_opening_m is None else self.pick_opening_m

    @property
    def approach_part(self) -> np.ndarray:
        """(3,) unit approach direction (hand to fingertips) in the part frame."""
        return self.part_from_tcp.rotation[:, 2]

    @property
    def closing_axis_part(self) -> np.ndarray:
        """(3,) unit finger closing axis (TCP +y) in the part frame."""
        return self.part_from_tcp.rotation[:, 1]

    def world_from_tcp(self, world_from_part: Pose) -> Pose:
        return world_from_part @ self.part_from_tcp

    def world_from_hand(self, world_from_part: Pose) -> Pose:
        """The ``panda_hand`` link pose for inverse kinematics."""
        return world_from_part @ self.part_from_tcp @ HAND_FROM_TCP.inverse()


def _total_score(c: float, p: float, i: float, t: float, w: GraspWeights) -> float:
    return w.centroid * c + w.contact * p + w.insertion * i + w.top_down * t


# ---------------------------------------------------------------------------------------------------------
# mesh helpers
# ---------------------------------------------------------------------------------------------------------


_BVH_CACHE: OrderedDict[str, fcl.BVHModel] = OrderedDict()


def _bvh(mesh: trimesh.Trimesh, key: str | None = None) -> fcl.BVHModel:
    key = key or mesh_key(mesh)
    model = _BVH_CACHE.get(key)
    if model is None:
        model = mesh_to_fcl(mesh)
        _BVH_CACHE[key] = model
        if len(_BVH_CACHE) > 4 * _CACHE_SIZE:
            _BVH_CACHE.popitem(last=False)
    else:
        _BVH_CACHE.move_to_end(key)
    return model


def thinnest_width_m(mesh: trimesh.Trimesh) -> float:
    """Smallest width of the part's convex hull over its face normals and oriented-bounding-box axes, metres."""
    try:
        hull = mesh.convex_hull
        v = np.asarray(hull.vertices)
        proj = v @ np.asarray(hull.face_normals).T
        hull_width = float(np.min(proj.max(axis=0) - proj.min(axis=0)))
    except Exception:  # qhull fails on flat or degenerate input
        hull_width = math.inf
    try:
        obb_width = float(np.min(mesh.bounding_box_oriented.primitive.extents))
    except Exception:
        obb_width = math.inf
    width = min(hull_width, obb_width)
    return width if math.isfinite(width) else float(np.min(mesh.extents))


def _perpendicular_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unit vectors e1, e2 perpendicular to unit d (N, 3), e1 built from the axis least aligned with d."""
    helper = np.eye(3)[np.argmin(np.abs(d), axis=1)]
    e1 = helper - np.sum(helper * d, axis=1, keepdims=True) * d
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    return e1, e2


def _aabbs(points: np.ndarray) -> np.ndarray:
    """(..., N, 3) -> (..., 2, 3) min/max."""
    return np.stack([points.min(axis=-2), points.max(axis=-2)], axis=-2)


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """AABB overlap of (..., 2, 3) boxes, broadcast."""
    return np.all((a[..., 0, :] <= b[..., 1, :]) & (b[..., 0, :] <= a[..., 1, :]), axis=-1)


def _inside(inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    return np.all((inner[..., 0, :] >= outer[..., 0, :]) & (inner[..., 1, :] <= outer[..., 1, :]), axis=-1)


def _piece_poses(gripper: GripperCollisionModel, frame_from_tcp: np.ndarray, openings: np.ndarray) -> np.ndarray:
    """(N, 4, 4) TCP poses and (N,) openings -> (N, 3, 4, 4) poses of (hand, left, right) in the same frame."""
    n = len(frame_from_tcp)
    tcp_from_pieces = np.tile(gripper.tcp_from_pieces(0.0), (n, 1, 1, 1))
    half = np.clip(openings, 0.0, gripper.max_opening_m) / 2.0
    tcp_from_pieces[:, 1, 1, 3] = half
    tcp_from_pieces[:, 2, 1, 3] = -half
    return frame_from_tcp[:, None] @ tcp_from_pieces


def _piece_aabbs(gripper: GripperCollisionModel, pieces: np.ndarray) -> np.ndarray:
    """(N, 3, 4, 4) piece poses -> (N, 3, 2, 3) world AABBs of the pieces' hull vertices."""
    n = len(pieces)
    out = np.empty((n, 3, 2, 3))
    for k, v in enumerate(gripper.piece_vertices()):
        # one matrix product for all poses: (N * 3, 3) rotation rows against (3, V) vertices -> (N, 3, V)
        rotated = (pieces[:, k, :3, :3].reshape(-1, 3) @ v.T).reshape(n, 3, -1)
        out[:, k, 0] = rotated.min(axis=2) + pieces[:, k, :3, 3]
        out[:, k, 1] = rotated.max(axis=2) + pieces[:, k, :3, 3]
    return out


def _piece_centres(gripper: GripperCollisionModel, pieces: np.ndarray) -> np.ndarray:
    """(N, 3, 4, 4) piece poses -> (N, 3, 3) a point inside each piece (its hull vertices' mean)."""
    centres = np.array([v.mean(axis=0) for v in gripper.piece_vertices()])  # (3, 3)
    return np.einsum("nkij,kj->nki", pieces[..., :3, :3], centres) + pieces[..., :3, 3]


# ---------------------------------------------------------------------------------------------------------
# candidates on the part
# ---------------------------------------------------------------------------------------------------------


@dataclass
class _Stats:
    samples: int = 0
    hits: int = 0
    in_cone: int = 0
    min_cone_width_m: float = math.inf
    pairs: int = 0
    poses: int = 0
    collision_free: int = 0


def _first_hits(mesh: trimesh.Trimesh, origins: np.ndarray,
                directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First surface hit of each ray (part frame, metres): (H, 3) locations, (H,) ray indices (ascending) and
    (H, 3) face normals there. Closed convex meshes are intersected plane by plane (the ray's entry, or its exit
    when it starts inside); other meshes through trimesh's ray engine."""
    planes = _convex_planes(mesh)
    if planes is None:
        locations, ray_index, tri_index = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
        order = np.argsort(ray_index, kind="stable")  # deterministic order, whatever the ray engine returns
        # without a hit the ray engine gives a flat (0,) array of locations: keep the (H, 3) shape
        return (locations.reshape(-1, 3)[order], ray_index[order],
                np.asarray(mesh.face_normals)[tri_index[order]].reshape(-1, 3))
    normals, offsets = planes
    rate = directions @ normals.T  # (R, F): how fast the ray approaches each face plane
    room = offsets - origins @ normals.T  # (R, F): >= 0 on the inner side
    with np.errstate(divide="ignore", invalid="ignore"):
        t = room / rate
    t_exit = np.where(rate > 1e-12, t, np.inf)
    t_enter = np.where(rate < -1e-12, t, -np.inf)
    exit_face, enter_face = np.argmin(t_exit, axis=1), np.argmax(t_enter, axis=1)
    rows = np.arange(len(origins))
    t_out, t_in = t_exit[rows, exit_face], t_enter[rows, enter_face]
    parallel_outside = np.any((np.abs(rate) <= 1e-12) & (room < 0), axis=1)
    meets = (t_in <= t_out) & (t_out > 0) & ~parallel_outside
    from_outside = t_in > 0
    distance = np.where(from_outside, t_in, t_out)
    face = np.where(from_outside, enter_face, exit_face)
    ray_index = np.flatnonzero(meets)
    locations = origins[ray_index] + distance[ray_index, None] * directions[ray_index]
    return locations, ray_index, normals[face[ray_index]]


def _last_hits(mesh: trimesh.Trimesh, origins: np.ndarray,
               directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Like :func:`_first_hits`, the last surface hit of each ray that meets the surface more than once (the far
    side of a hollow or concave part), for meshes that are not closed and convex."""
    locations, ray_index, tri_index = mesh.ray.intersects_location(origins, directions, multiple_hits=True)
    if len(ray_index) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    distance = np.einsum("ij,ij->i", locations - origins[ray_index], directions[ray_index])
    order = np.lexsort((-distance, ray_index))  # per ray, farthest first; rays ascending
    rays, first = np.unique(ray_index[order], return_index=True)
    counts = np.bincount(ray_index, minlength=len(origins))[rays]
    chosen = order[first[counts > 1]]
    chosen = chosen[np.argsort(ray_index[chosen], kind="stable")]
    return locations[chosen], ray_index[chosen], np.asarray(mesh.face_normals)[tri_index[chosen]]


def _antipodal_pairs(
    mesh: trimesh.Trimesh, seed: int, n_samples: int, friction: float, stats: _Stats
) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) first contacts and (P, 3) second contacts of antipodal pairs within the hand's width."""
    points, face_index = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    normals = np.asarray(mesh.face_normals)[face_index]
    ok = np.linalg.norm(normals, axis=1) > 0.5  # degenerate faces have zero normals
    points, normals = points[ok], normals[ok]
    stats.samples = len(points)
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    origins = points - normals * _RAY_INSET_M
    locations, ray_index, n2 = _first_hits(mesh, origins, -normals)
    if _convex_planes(mesh) is None:  # and where the ray leaves the part for good: across a hollow tube
        far, far_index, far_normals = _last_hits(mesh, origins, -normals)
        locations, ray_index, n2 = (np.concatenate([locations, far]), np.concatenate([ray_index, far_index]),
                                    np.concatenate([n2, far_normals]))
    stats.hits = len(ray_index)
    if len(ray_index) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    p1, p2 = points[ray_index], locations
    axis = p2 - p1
    width = np.linalg.norm(axis, axis=1)
    good = width > _MIN_WIDTH_M
    axis[good] /= width[good, None]
    cos_cone = math.cos(math.atan(friction))
    in_cone = good & (np.sum(n2 * axis, axis=1) >= cos_cone) & (np.sum(-normals[ray_index] * axis, axis=1) >= cos_cone)
    stats.in_cone = int(np.count_nonzero(in_cone))
    if stats.in_cone:
        stats.min_cone_width_m = float(np.min(width[in_cone]))
    keep = in_cone & (width <= MAX_GRASP_WIDTH_M)
    stats.pairs = int(np.count_nonzero(keep))
    return p1[keep], p2[keep]


def _candidate_poses(p1: np.ndarray, p2: np.ndarray, n_approaches: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 4, 4) part_from_tcp, (N,) widths and (N,) pair index for every pair and approach direction."""
    d = p2 - p1
    width = np.linalg.norm(d, axis=1)
    d = d / width[:, None]
    e1, e2 = _perpendicular_basis(d)
    angles = 2.0 * np.pi * np.arange(n_approaches) / n_approaches
    z = np.cos(angles)[None, :, None] * e1[:, None] + np.sin(angles)[None, :, None] * e2[:, None]  # (P, K, 3)
    y = np.broadcast_to(d[:, None], z.shape)
    x = np.cross(y, z)
    poses = np.tile(np.eye(4), (len(d), n_approaches, 1, 1))
    poses[..., :3, 0], poses[..., :3, 1], poses[..., :3, 2] = x, y, z
    poses[..., :3, 3] = ((p1 + p2) / 2.0)[:, None]
    pair = np.repeat(np.arange(len(d)), n_approaches)
    return poses.reshape(-1, 4, 4), np.repeat(width, n_approaches), pair


@functools.lru_cache(maxsize=4)
def _probe_points(gripper: GripperCollisionModel) -> tuple[np.ndarray, ...]:
    """Per piece (hand, left, right), (P, 3) points strictly inside its hull, in its link frame: the hull's vertex
    mean, and for the hand a few points on its axis just behind the palm (where a part edge meets the hand)."""
    out = []
    for k, vertices in enumerate(gripper.piece_vertices()):
        points = [vertices.mean(axis=0)]
        if k == 0:
            palm_z = float(vertices[:, 2].max())
            points += [np.array([0.0, 0.0, palm_z - dz]) for dz in (0.002, 0.01, 0.025)]
        points = np.array(points)
        hull = trimesh.convex.convex_hull(vertices)
        depth = points @ hull.face_normals.T - np.sum(hull.face_normals * hull.triangles[:, 0], axis=1)
        out.append(points[np.all(depth < -1e-4, axis=1)])
    return tuple(out)


def _surely_inside_convex(gripper: GripperCollisionModel, mesh: trimesh.Trimesh, pieces: np.ndarray,
                          near: np.ndarray) -> np.ndarray:
    """(N,) bool: a point inside some hand piece lies strictly inside ``mesh`` (part frame), so the piece overlaps
    the part: FCL would report the collision, or the enclosed-piece test would. Decided only for convex closed
    meshes (a point is inside when it lies behind every face plane); all False otherwise."""
    hits = np.zeros(len(pieces), dtype=bool)
    planes = _convex_planes(mesh) if near.any() else None
    if planes is None:
        return hits
    normals, offsets = planes
    for k, probes in enumerate(_probe_points(gripper)):
        rows = np.flatnonzero(near[:, k] & ~hits)
        if len(probes) == 0 or len(rows) == 0:
            continue
        points = np.einsum("nij,pj->npi", pieces[rows, k, :3, :3], probes) + pieces[rows, k, None, :3, 3]
        inside = np.all(points @ normals.T - offsets < -1e-4, axis=2)  # (rows, P)
        hits[rows[inside.any(axis=1)]] = True
    return hits


def _free_of_part(
    gripper: GripperCollisionModel,
    mesh: trimesh.Trimesh,
    bvh: fcl.BVHModel,
    poses: np.ndarray,
    openings: np.ndarray,
) -> np.ndarray:
    """(N,) bool: the hand at each pose (part frame) and opening does not touch the part."""
    pieces = _piece_poses(gripper, poses, openings)
    boxes = _piece_aabbs(gripper, pieces)
    part_box = np.asarray(mesh.bounds)
    near = _overlap(boxes, part_box)  # (N, 3)
    free = ~_surely_inside_convex(gripper, mesh, pieces, near)  # exact shortcut: no narrow phase needed there
    part = fcl.CollisionObject(bvh, fcl.Transform())
    objects = gripper.collision_objects()
    request = fcl.CollisionRequest()
    check_order = (1, 2, 0)  # fingers first: they are the likeliest to touch
    for i in np.flatnonzero(free & near.any(axis=1)):
        for k in check_order:
            if not near[i, k]:
                continue
            p = pieces[i, k]
            objects[k].setTransform(fcl.Transform(p[:3, :3], p[:3, 3]))
            if fcl.collide(objects[k], part, request, fcl.CollisionResult()):
                free[i] = False
                break
    # a piece wholly inside the part touches no triangle; only possible when its box lies inside the part's
    enclosed = free[:, None] & _inside(boxes, part_box)
    if np.any(enclosed):
        idx, piece = np.nonzero(enclosed)
        centres = _piece_centres(gripper, pieces)[idx, piece]
        inside = _contains(mesh, centres)
        free[idx[inside]] = False
    return free


def _pad_probe_offsets() -> np.ndarray:
    """(2 * cells, 3) centres of the pad cells in the TCP frame at unit half-opening (y = +/-1 scaled later)."""
    xs = (np.arange(_PAD_CELLS_X) + 0.5) / _PAD_CELLS_X * FINGER_PAD_WIDTH_M - FINGER_PAD_WIDTH_M / 2
    z0, z1 = PAD_Z_RANGE_IN_TCP_M
    zs = z0 + (np.arange(_PAD_CELLS_Z) + 0.5) / _PAD_CELLS_Z * (z1 - z0)
    cells = np.array([(x, z) for x in xs for z in zs])
    left = np.column_stack([cells[:, 0], np.ones(len(cells)), cells[:, 1]])
    right = np.column_stack([cells[:, 0], -np.ones(len(cells)), cells[:, 1]])
    return np.concatenate([left, right])


def _contains(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """(N,) bool: which points (mesh frame) lie inside ``mesh``. Closed convex meshes: behind every face plane;
    other closed meshes: generalised winding number >= 1/2 (exact for closed surfaces, shells may overlap);
    open meshes: trimesh's ray test."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    planes = _convex_planes(mesh)
    if planes is not None:
        return np.all(points @ planes[0].T <= planes[1], axis=1)
    if not mesh.is_watertight:
        return mesh.contains(points)
    triangles = np.asarray(mesh.triangles)
    winding = np.zeros(len(points))
    chunk = max(1, 200_000 // max(1, len(triangles)))
    for start in range(0, len(points), chunk):
        corners = triangles[None] - points[start:start + chunk, None, None]  # (P, T, 3, 3)
        a, b, c = corners[:, :, 0], corners[:, :, 1], corners[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
        det = np.sum(a * np.cross(b, c), axis=2)
        dots = np.sum(a * b, axis=2) * lc + np.sum(b * c, axis=2) * la + np.sum(c * a, axis=2) * lb
        # solid angle of each triangle seen from the point (Van Oosterom and Strackee)
        winding[start:start + chunk] = np.sum(2.0 * np.arctan2(det, la * lb * lc + dots), axis=1) / (4.0 * np.pi)
    return winding >= 0.5


def _convex_planes(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray] | None:
    """(F, 3) outward face normals and (F,) plane offsets of a closed convex mesh (``n . x <= offset`` inside),
    or None when the mesh is not closed and convex."""
    if not (mesh.is_watertight and mesh.is_convex):
        return None
    normals = np.asarray(mesh.face_normals)
    offsets = np.sum(normals * np.asarray(mesh.triangles)[:, 0], axis=1)
    _, keep = np.unique(np.round(normals, 9), axis=0, return_index=True)  # coplanar triangles: one plane
    return normals[keep], offsets[keep]


def _contact_scores_convex(mesh: trimesh.Trimesh, planes: tuple[np.ndarray, np.ndarray], poses: np.ndarray,
                           widths: np.ndarray) -> np.ndarray:
    """:func:`_contact_scores` for a closed convex part, vectorised: a pad cell (a thin box) touches the surface
    when it overlaps the solid (separating axes: the box's axes, the part's face normals, their edges' cross
    products; exact for two convex polytopes) without lying wholly inside it."""
    z0, z1 = PAD_Z_RANGE_IN_TCP_M
    half = np.array([FINGER_PAD_WIDTH_M / _PAD_CELLS_X, 2 * _PROBE_HALF_THICKNESS_M, (z1 - z0) / _PAD_CELLS_Z]) / 2
    rotations = poses[:, :3, :3]  # (N, 3, 3): columns are the cells' box axes in the part frame
    local = _pad_probe_offsets()[None] * np.column_stack([np.ones(len(widths)), widths / 2, np.ones(len(widths))])[
        :, None]  # (N, C, 3)
    centres = np.einsum("nij,ncj->nci", rotations, local) + poses[:, None, :3, 3]
    normals, offsets = planes
    vertices = np.asarray(mesh.vertices)
    box_axes = np.swapaxes(rotations, 1, 2)  # (N, 3, 3): rows are the box axes
    edges = hull_edge_axes(vertices)
    cross = np.cross(edges[None, :, None], box_axes[:, None]).reshape(len(poses), -1, 3)
    length = np.linalg.norm(cross, axis=2, keepdims=True)
    cross = np.where(length > 1e-9, cross / np.maximum(length, 1e-12), 0.0)  # parallel pairs: a null axis
    moving_axes = np.concatenate([box_axes, cross], axis=1)  # (N, A, 3), per pose
    proj = moving_axes @ vertices.T  # (N, A, V)
    n_faces = (len(poses), len(normals))
    lo = np.concatenate([proj.min(axis=2), np.broadcast_to((normals @ vertices.T).min(axis=1), n_faces)], axis=1)
    hi = np.concatenate([proj.max(axis=2), np.broadcast_to(offsets, n_faces)], axis=1)  # convex: the face planes
    axes = np.concatenate([moving_axes, np.broadcast_to(normals, (len(poses), *normals.shape))], axis=1)
    radius = np.abs(axes @ rotations) @ half  # (N, A): the box's half extent along each axis
    centre_proj = centres @ np.swapaxes(axes, 1, 2)  # (N, C, A)
    overlaps = np.all((centre_proj - radius[:, None] <= hi[:, None]) & (centre_proj + radius[:, None] >= lo[:, None]),
                      axis=2)  # (N, C)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners = centres[:, :, None] + np.einsum("nij,sj->nsi", rotations, signs * half)[:, None]  # (N, C, 8, 3)
    inside = np.all(corners @ normals.T <= offsets, axis=(2, 3))  # every corner behind every face plane
    return np.mean(overlaps & ~inside, axis=1)


def _contact_scores(bvh: fcl.BVHModel, poses: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """(N,) fraction of pad cells (both pads) that lie over the part's surface at the contact width."""
    z0, z1 = PAD_Z_RANGE_IN_TCP_M
    box = fcl.Box(FINGER_PAD_WIDTH_M / _PAD_CELLS_X, 2 * _PROBE_HALF_THICKNESS_M, (z1 - z0) / _PAD_CELLS_Z)
    probe = fcl.CollisionObject(box, fcl.Transform())
    part = fcl.CollisionObject(bvh, fcl.Transform())
    offsets = _pad_probe_offsets()
    request = fcl.CollisionRequest()
    out = np.zeros(len(poses))
    for i, (pose, width) in enumerate(zip(poses, widths)):
        local = offsets * np.array([1.0, width / 2.0, 1.0])
        centres = local @ pose[:3, :3].T + pose[:3, 3]
        rotation = pose[:3, :3]
        hits = 0
        for c in centres:
            probe.setTransform(fcl.Transform(rotation, c))
            hits += fcl.collide(probe, part, request, fcl.CollisionResult()) > 0
        out[i] = hits / len(offsets)
    return out


def _spread(order: np.ndarray, positions: np.ndarray, count: int) -> np.ndarray:
    """``count`` indices picked from ``order`` (indices, best first) for spread: the best :data:`BEST_SHARE` of
    ``count`` as they come, then, round and round the :data:`SPREAD_CELL_M` cubes of ``positions`` (rows indexed
    like ``order``'s entries) that the rest fall in, the best remaining candidate of each cube in turn (the cubes in
    the order of their best)."""
    keep = min(len(order), int(round(BEST_SHARE * count)))
    head, rest = list(order[:keep]), order[keep:]
    queues: dict[tuple, list[int]] = {}
    for i in rest:
        queues.setdefault(tuple(np.floor(positions[i] / SPREAD_CELL_M).astype(int)), []).append(int(i))
    lanes = list(queues.values())
    depth = 0
    while len(head) < count and any(depth < len(lane) for lane in lanes):
        head += [lane[depth] for lane in lanes if depth < len(lane)][: count - len(head)]
        depth += 1
    return np.asarray(head, dtype=np.int64)


def _dedup_keys(poses: np.ndarray) -> np.ndarray:
    pos = np.floor(poses[:, :3, 3] / _DEDUP_POSITION_M)
    approach = np.round(poses[:, :3, 2] * _DEDUP_DIRECTION_STEPS)
    axis = poses[:, :3, 1]
    # the hand is symmetric under a half turn about its approach axis: +y and -y are the same grasp
    lead = np.argmax(np.abs(axis), axis=1)
    sign = np.sign(axis[np.arange(len(axis)), lead])
    axis = np.round(axis * sign[:, None] * _DEDUP_DIRECTION_STEPS)
    return np.concatenate([pos, approach, axis], axis=1).astype(np.int64)


_CANDIDATE_CACHE: OrderedDict[tuple, tuple[tuple[Grasp, ...], _Stats]] = OrderedDict()


def _compute_candidates(
    mesh: trimesh.Trimesh,
    seed: int,
    max_candidates: int,
    n_samples: int,
    n_approaches: int,
    friction: float,
    clearance_m: float,
    gripper: GripperCollisionModel,
    approach_m: float = APPROACH_M,
) -> tuple[tuple[Grasp, ...], _Stats]:
    key_mesh = mesh_key(mesh)
    key = (key_mesh, seed, max_candidates, n_samples, n_approaches, friction, clearance_m, id(gripper), approach_m)
    cached = _CANDIDATE_CACHE.get(key)
    if cached is not None:
        _CANDIDATE_CACHE.move_to_end(key)
        return cached
    stats = _Stats()
    p1, p2 = _antipodal_pairs(mesh, seed, n_samples, friction, stats)
    grasps: tuple[Grasp, ...] = ()
    if len(p1):
        poses, widths, pair = _candidate_poses(p1, p2, n_approaches)
        openings = np.minimum(widths + clearance_m, gripper.max_opening_m)
        bvh = _bvh(mesh, key_mesh)
        swept = gripper.swept_back(approach_m) if approach_m > 0 else gripper
        # the simulator's (and the arm planner's) part is its convex pieces, which may bulge past the mesh
        pieces = [(piece, _bvh(piece)) for piece in convex_pieces(mesh)]
        # pairs come in random (sampling) order: check them in chunks and stop once there are plenty of distinct
        # collision-free poses, which keeps simple parts fast without losing spread over the part
        free = np.zeros(len(poses), dtype=bool)
        seen: set[tuple[int, ...]] = set()
        chunk = _PAIRS_PER_CHUNK * n_approaches
        for start in range(0, len(poses), chunk):
            part = slice(start, start + chunk)
            free[part] = _free_of_part(gripper, mesh, bvh, poses[part], openings[part])
            # the straight approach to the pose (and the retreat from it) clear too, of the mesh and of the pieces
            for body, body_bvh in [(mesh, bvh), *pieces]:
                rows = start + np.flatnonzero(free[part])
                if len(rows):
                    free[rows] = _free_of_part(swept, body, body_bvh, poses[rows], openings[rows])
            # closing, the pads meet the contact pair first: nothing thicker lies between them (a thin lip beside a
            # thick body)
            rows = start + np.flatnonzero(free[part])
            if CLOSING_SLACK_M is not None and len(rows):
                free[rows] = _free_of_part(gripper, mesh, bvh, poses[rows], widths[rows] + CLOSING_SLACK_M)
            stats.poses = min(start + chunk, len(poses))
            seen.update(map(tuple, _dedup_keys(poses[part][free[part]])))
            if len(seen) >= _ENOUGH_DISTINCT_FACTOR * max_candidates:
                break
        stats.collision_free = int(np.count_nonzero(free))
        poses, widths, openings, pair = poses[free], widths[free], openings[free], pair[free]
        if len(poses):
            com = centre_of_mass(mesh)
            centroid = np.exp(-np.linalg.norm(poses[:, :3, 3] - com, axis=1) / _CENTROID_SCALE_M)
            order = np.argsort(-centroid, kind="stable")
            _, first = np.unique(_dedup_keys(poses[order]), axis=0, return_index=True)
            distinct = order[np.sort(first)]
            chosen = _spread(distinct, poses[:, :3, 3], _ENOUGH_DISTINCT_FACTOR * max_candidates)
            planes = _convex_planes(mesh)
            if planes is not None:
                contact = _contact_scores_convex(mesh, planes, poses[chosen], widths[chosen])
            else:
                contact = _contact_scores(bvh, poses[chosen], widths[chosen])
            w = DEFAULT_WEIGHTS
            total = np.array([_total_score(c, p, 0.5, 0.5, w) for c, p in zip(centroid[chosen], contact)])
            best = _spread(np.argsort(-total, kind="stable"), poses[chosen][:, :3, 3], max_candidates)
            best = best[np.argsort(-total[best], kind="stable")]  # best first, whichever way it was chosen
            out = []
            for j in best:
                i = chosen[j]
                contacts = np.stack([p1[pair[i]], p2[pair[i]]])
                contacts.flags.writeable = False  # grasps are shared through the cache
                out.append(
                    Grasp(
                        part_from_tcp=Pose.from_rotation(poses[i, :3, :3], poses[i, :3, 3]),
                        width_m=float(widths[i]),
                        opening_m=float(openings[i]),
                        score=float(total[j]),
                        centroid_score=float(centroid[i]),
                        contact_score=float(contact[j]),
                        contacts_part=contacts,
                    )
                )
            grasps = tuple(out)
    result = (grasps, stats)
    _CANDIDATE_CACHE[key] = result
    if len(_CANDIDATE_CACHE) > _CACHE_SIZE:
        _CANDIDATE_CACHE.popitem(last=False)
    return result


def _check_mesh(mesh: trimesh.Trimesh) -> None:
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
        raise ValueError("mesh has no triangles or has non-finite vertices")


def antipodal_grasps(
    mesh: trimesh.Trimesh,
    rng: np.random.Generator,
    max_candidates: int = 100,
    *,
    n_samples: int = 200,
    n_approaches: int = 12,
    friction: float = FRICTION_COEFFICIENT,
    clearance_m: float = GRASP_CLEARANCE_M,
    gripper: GripperCollisionModel | None = None,
    strict: bool = False,
    part_name: str = "part",
) -> list[Grasp]:
    """Antipodal parallel-jaw grasps on ``mesh`` (metres, part frame), best first by part-intrinsic score.

    rng: draws exactly one integer (the sampling seed), so the result is a function of the rng's state.
    max_candidates: at most this many grasps, near-duplicates (8 mm, about 20 degrees) removed.
    n_samples: surface points sampled; n_approaches: approach directions tried around each contact axis.
    Returns an empty list when there is none (see :func:`explain_no_grasp`), or raises :class:`NoGraspError`
    with that explanation when ``strict``.
    """
    _check_mesh(mesh)
    if max_candidates < 1 or n_samples < 1 or n_approaches < 1:
        raise ValueError(
            f"max_candidates ({max_candidates}), n_samples ({n_samples}) and n_approaches ({n_approaches}) must be >= 1"
        )
    seed = int(rng.integers(0, 2**31 - 1))
    grasps, _ = _compute_candidates(
        mesh, seed, max_candidates, n_samples, n_approaches, friction, clearance_m, gripper or default_gripper()
    )
    if not grasps and strict:
        raise NoGraspError(explain_no_grasp(mesh, part_name=part_name, seed=seed))
    return list(grasps)


def explain_no_grasp(
    mesh: trimesh.Trimesh,
    part_name: str = "part",
    seed: int = 0,
    *,
    n_samples: int = 200,
    n_approaches: int = 12,
    friction: float = FRICTION_COEFFICIENT,
    clearance_m: float = GRASP_CLEARANCE_M,
) -> str:
    """One sentence saying why ``mesh`` has no grasp (or how many it has), e.g. "part is 9.2 cm thick in its
    thinnest direction; the Panda hand opens 8 cm"."""
    _check_mesh(mesh)
    grasps, stats = _compute_candidates(
        mesh, seed, 100, n_samples, n_approaches, friction, clearance_m, default_gripper()
    )
    hand = (
        f"the Panda hand opens {MAX_OPENING_M * 100:.0f} cm ({MAX_GRASP_WIDTH_M * 100:.1f} cm usable, keeping "
        f"{MIN_SIDE_CLEARANCE_M * 1000:.1f} mm clearance each side)"
    )
    if grasps:
        return f"{part_name} has {len(grasps)} grasps (best across {grasps[0].width_m * 100:.1f} cm)"
    thinnest = min(thinnest_width_m(mesh), stats.min_cone_width_m)
    if thinnest > MAX_GRASP_WIDTH_M:
        return f"{part_name} is {thinnest * 100:.1f} cm thick in its thinnest direction; {hand}"
    if stats.pairs == 0:
        return (
            f"{part_name} is {thinnest * 100:.1f} cm thick in its thinnest direction, but none of {stats.samples} "
            f"sampled surface points has an opposite surface within {MAX_GRASP_WIDTH_M * 100:.1f} cm whose normal "
            f"lies in the friction cone (mu = {friction}); check that the mesh's face normals point outwards"
        )
    return (
        f"{part_name}: {stats.pairs} antipodal contact pairs fit between the fingers, but at all "
        f"{stats.poses} hand poses tried ({n_approaches} approach directions each) the hand or fingers collide with "
        f"the part there or on the straight {APPROACH_M * 100:.0f} cm approach to it: a contact must lie within "
        f"{TCP_TO_PALM_M * 100:.1f} cm of an edge (the fingers are "
        f"{USABLE_FINGER_DEPTH_M * 100:.1f} cm deep) with room for the fingertips beside it"
    )


# ---------------------------------------------------------------------------------------------------------
# ranking for a use
# ---------------------------------------------------------------------------------------------------------


def _unit(v: np.ndarray | Sequence[float], name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    n = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
    if v.shape != (3,) or not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"{name} must be a non-zero 3-vector, got {v.tolist()}")
    return v / n


def rank(
    grasps: Sequence[Grasp],
    world_from_part: Pose | None = None,
    insertion_direction_world: np.ndarray | None = None,
    weights: GraspWeights = DEFAULT_WEIGHTS,
) -> list[Grasp]:
    """Rescore grasps for a use and sort them best first (stable).

    world_from_part: the part's pose where the grasp is used (its target); None means the part frame is the world.
    insertion_direction_world: (3,) direction of the part's motion into its target (world frame), or None.
    Components kept from :func:`antipodal_grasps`: centroid and contact; recomputed: insertion and top-down.
    """
    rotation = np.eye(3) if world_from_part is None else world_from_part.rotation
    u = None if insertion_direction_world is None else _unit(insertion_direction_world, "insertion_direction_world")
    out = []
    for g in grasps:
        approach = rotation @ g.approach_part
        insertion = 0.5 if u is None else float((1.0 + approach @ u) / 2.0)
        top_down = 0.5 if world_from_part is None else float((1.0 - approach[2]) / 2.0)
        score = _total_score(g.centroid_score, g.contact_score, insertion, top_down, weights)
        out.append(dataclasses.replace(g, insertion_score=insertion, top_down_score=top_down, score=score))
    order = sorted(range(len(out)), key=lambda i: -out[i].score)
    return [out[i] for i in order]


# ---------------------------------------------------------------------------------------------------------
# feasibility in the world
# ---------------------------------------------------------------------------------------------------------


class ObstacleSet:
    """Obstacle meshes posed in the world, prepared once for many collision queries.

    obstacles: (mesh in its own frame, metres; world_from_mesh) pairs.
    """

    def __init__(self, obstacles: Sequence[tuple[trimesh.Trimesh, Pose]]):
        self.meshes: list[trimesh.Trimesh] = []
        self.world_from_mesh: list[np.ndarray] = []
        self.objects: list[fcl.CollisionObject] = []
        boxes = []
        for index, (mesh, pose) in enumerate(obstacles):
            if not isinstance(mesh, trimesh.Trimesh) or not isinstance(pose, Pose):
                raise TypeError(
                    f"obstacle {index}: expected (trimesh.Trimesh, Pose), got ({type(mesh).__name__}, "
                    f"{type(pose).__name__})"
                )
            _check_mesh(mesh)
            m = pose.matrix()
            self.meshes.append(mesh)
            self.world_from_mesh.append(m)
            self.objects.append(fcl.CollisionObject(_bvh(mesh), pose.to_fcl()))
            boxes.append(_aabbs(np.asarray(mesh.vertices) @ m[:3, :3].T + m[:3, 3]))
        self.boxes = np.array(boxes).reshape(-1, 2, 3)

    def __len__(self) -> int:
        return len(self.meshes)

    def contains(self, index: int, points_world: np.ndarray) -> np.ndarray:
        """(N,) bool: which world points lie inside obstacle ``index`` (see :func:`_contains`)."""
        m = self.world_from_mesh[index]
        return _contains(self.meshes[index], (np.asarray(points_world) - m[:3, 3]) @ m[:3, :3])  # R^T (p - t)


def _translations(offsets: np.ndarray) -> np.ndarray:
    t = np.tile(np.eye(4), (len(offsets), 1, 1))
    t[:, :3, 3] = offsets
    return t


def feasible_grasps(
    grasps: Sequence[Grasp],
    world_from_part: Pose,
    obstacles: Sequence[tuple[trimesh.Trimesh, Pose]] | ObstacleSet,
    insertion_direction_world: np.ndarray | None,
    floor_z: float | None = 0.0,
    *,
    insertion_sweep_m: float = 0.03,
    sweep_step_m: float = 0.005,
    retreat_m: float = 0.0,
    floor_margin_m: float = 0.001,
    min_insertion_alignment: float = -0.3,
    weights: GraspWeights = DEFAULT_WEIGHTS,
    gripper: GripperCollisionModel | None = None,
    closed_gripper: GripperCollisionModel | None = None,
) -> list[Grasp]:
    """The grasps usable with the part at ``world_from_part``, ranked (see :func:`rank`), best first.

    A grasp is kept when the hand and fingers, opened to ``grasp.opening_m``:
    - do not overlap any obstacle (meshes with world poses, e.g. the parts already placed around the target);
    - stay at least ``floor_margin_m`` above ``floor_z`` (no floor check when ``floor_z`` is None);
    - with an insertion direction: stay clear at the poses the hand passes through while the part travels the
      last ``insertion_sweep_m`` into its target (sampled every ``sweep_step_m``), and do not lead the part:
      ``approach . insertion >= min_insertion_alignment``;
    - with ``retreat_m > 0``: stay clear while backing off along -approach by up to ``retreat_m``;
    - with a ``closed_gripper`` model: that hand, closed to ``grasp.width_m`` on the part, is clear too at the part's
      pose and along the insertion sweep (the fingers hold the part there; not on the retreat, made open). A
      neighbour flush with a gripped face can lie where a closed finger is and the opened one is not: a chair's
      back panel against its back post.

    At pick (the part lying in the kitting area) pass ``insertion_direction_world=None``: no sweep, and the
    ranking then only prefers top-down approaches.
    """
    if not isinstance(world_from_part, Pose):
        raise TypeError(f"world_from_part must be a planning.pose.Pose, got {type(world_from_part).__name__}")
    gripper = gripper or default_gripper()
    obstacle_set = obstacles if isinstance(obstacles, ObstacleSet) else ObstacleSet(obstacles)
    ranked = rank(grasps, world_from_part, insertion_direction_world, weights)
    if not ranked:
        return []
    u = None if insertion_direction_world is None else _unit(insertion_direction_world, "insertion_direction_world")
    if u is not None:
        ranked = [
            g for g in ranked if float((world_from_part.rotation @ g.approach_part) @ u) >= min_insertion_alignment
        ]
        if not ranked:
            return []

    # every hand pose to check, per grasp: the target pose, then the insertion sweep, then the retreat
    world_from_tcp = world_from_part.matrix()[None] @ np.array([g.part_from_tcp.matrix() for g in ranked])
    shifts = [np.zeros((1, 3))]
    if u is not None and insertion_sweep_m > 0:
        steps = max(1, int(math.ceil(insertion_sweep_m / sweep_step_m)))
        shifts.append(-np.linspace(insertion_sweep_m / steps, insertion_sweep_m, steps)[:, None] * u)
    world_shifts = np.concatenate(shifts)  # (S, 3)
    poses = _translations(world_shifts)[None] @ world_from_tcp[:, None]  # (G, S, 4, 4)
    if retreat_m > 0:
        steps = max(1, int(math.ceil(retreat_m / sweep_step_m)))
        back = _translations(
            np.column_stack([np.zeros(steps), np.zeros(steps), -np.linspace(0, retreat_m, steps + 1)[1:]])
        )
        poses = np.concatenate([poses, world_from_tcp[:, None] @ back[None]], axis=1)
    n_grasps, n_steps = poses.shape[:2]
    openings = np.repeat([g.opening_m for g in ranked], n_steps)
    pieces = _piece_poses(gripper, poses.reshape(-1, 4, 4), openings).reshape(n_grasps, n_steps, 3, 4, 4)
    # every step is a translation of the grasp's pose at the target: its boxes are the target's boxes, shifted
    target_boxes = _piece_aabbs(gripper, pieces[:, 0])  # (G, 3, 2, 3)
    step_shifts = poses[:, :, :3, 3] - poses[:, :1, :3, 3]  # (G, S, 3)
    boxes = target_boxes[:, None] + step_shifts[:, :, None, None, :]

    ok = np.ones(n_grasps, dtype=bool)
    if floor_z is not None:
        ok &= np.all(boxes[..., 0, 2] >= floor_z + floor_margin_m, axis=(1, 2))
    if len(obstacle_set):
        near = _overlap(boxes[:, :, :, None], obstacle_set.boxes[None, None, None])  # (G, S, 3, O)
        # a piece wholly inside an obstacle touches no triangle: test the centres of pieces whose box lies inside
        # an obstacle's box, all at once per obstacle
        enclosed = ok[:, None, None, None] & _inside(boxes[:, :, :, None], obstacle_set.boxes[None, None, None])
        if np.any(enclosed):
            centres = _piece_centres(gripper, pieces.reshape(-1, 3, 4, 4)).reshape(n_grasps, n_steps, 3, 3)
            for o in np.unique(np.nonzero(enclosed)[3]):
                where = np.nonzero(enclosed[..., o])
                enclosed[(*where, o)] = obstacle_set.contains(o, centres[where])
        objects = gripper.collision_objects()
        request = fcl.CollisionRequest()
        for gi in np.flatnonzero(ok & near.any(axis=(1, 2, 3))):
            hit = False
            for si in range(n_steps):
                for k in range(3):
                    targets = np.flatnonzero(near[gi, si, k])
                    if len(targets) == 0:
                        continue
                    p = pieces[gi, si, k]
                    objects[k].setTransform(fcl.Transform(p[:3, :3], p[:3, 3]))
                    for o in targets:
                        if enclosed[gi, si, k, o] or fcl.collide(objects[k], obstacle_set.objects[o], request,
                                                                 fcl.CollisionResult()):
                            hit = True
                            break
                    if hit:
                        break
                if hit:
                    break
            ok[gi] = not hit
    kept = [g for g, keep in zip(ranked, ok) if keep]
    if closed_gripper is None or not kept:
        return kept
    closed = feasible_grasps([dataclasses.replace(g, opening_m=g.width_m) for g in kept], world_from_part,
                             obstacle_set, insertion_direction_world, floor_z, insertion_sweep_m=insertion_sweep_m,
                             sweep_step_m=sweep_step_m, floor_margin_m=floor_margin_m,
                             min_insertion_alignment=min_insertion_alignment, weights=weights, gripper=closed_gripper)
    holding = {grasp_pose_key(g) for g in closed}
    return [g for g in kept if grasp_pose_key(g) in holding]


def grasp_pose_key(grasp: Grasp) -> tuple:
    """Where the grasp holds the part, whatever its opening and ranking scores."""
    return grasp.part_from_tcp.key()
