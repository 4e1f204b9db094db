"""Signed distances between parts, from their convex pieces with FCL (GJK/EPA).

A positive distance is a gap, a negative one a penetration depth; 0 is touching. Each part is a
:class:`ConvexPart` (pieces in the part's own frame); poses are passed per query (``world_from_part``), so one
``ConvexPart`` serves every placement. Pairs of pieces whose bounding boxes are farther apart than a query's
``cutoff`` are not measured: the box gap is returned instead, a lower bound of the true distance (safe for
conservative advancement).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import fcl
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from planning.convex import convex_hull, convex_pieces
from planning.gripper import convex_to_fcl
from planning.pose import Pose

MAX_FITTING_OVERLAP_M = 0.03
"""Two parts' convex pieces may overlap by this much (metres) at their targets and still be built: models of real
furniture draw dowels without their holes and panels into each other, and convex pieces bulge (the deepest of the
42 models in ``../shared/furniture``: 23.8 mm, where the meshes overlap by 3.7 mm). ``python -m cell.run`` accepts
given targets up to it (the simulation lets such parts fit, :mod:`cell.simulate`); a deeper overlap is a wrong pose
(a part placed at another's position, a wrong unit) or, in a prediction, parts crossed through each other, which
the repair's step 5 (:attr:`planning.repair.RepairSettings.crossing_depth_m`) then tries to undo."""


def _unique_axes(normals: np.ndarray) -> np.ndarray:
    """Face normals with duplicates and opposite pairs removed (a separating axis has no sign)."""
    canonical = normals * np.where(normals[:, [0]] < 0, -1.0, 1.0)  # not exact for x == 0, harmless
    _, keep = np.unique(np.round(canonical, 6), axis=0, return_index=True)
    return normals[np.sort(keep)]


def hull_edge_axes(vertices: np.ndarray, coplanar_rad: float = 1e-6) -> np.ndarray:
    """(E, 3) unit edge directions (sign-free, unique) of the convex hull of ``vertices`` (N, 3); the diagonals
    that triangulate a flat face are not edges. A flat or degenerate point set gives the three coordinate axes."""
    try:
        hull = ConvexHull(np.asarray(vertices, dtype=np.float64))
    except Exception:  # qhull refuses flat or degenerate input
        return np.eye(3)
    simplices, normals = hull.simplices, hull.equations[:, :3]
    # facet s and its neighbour across from its j-th vertex share the edge made of the other two vertices
    s, j = np.nonzero(hull.neighbors >= 0)
    bent = np.sum(normals[s] * normals[hull.neighbors[s, j]], axis=1) < np.cos(coplanar_rad)
    s, j = s[bent], j[bent]
    first, second = simplices[s, (j + 1) % 3], simplices[s, (j + 2) % 3]
    directions = hull.points[second] - hull.points[first]
    length = np.linalg.norm(directions, axis=1)
    directions = directions[length > 1e-12] / length[length > 1e-12, None]
    if len(directions) == 0:
        return np.eye(3)
    lead = np.argmax(np.abs(directions), axis=1)  # sign-free: the largest component made positive
    directions *= np.sign(directions[np.arange(len(directions)), lead])[:, None]
    _, keep = np.unique(np.round(directions, 6), axis=0, return_index=True)
    return directions[np.sort(keep)]


@dataclass
class ConvexPart:
    """A part's convex pieces: FCL geometry and hull vertices, part frame, metres."""

    name: str
    geometries: list
    piece_vertices: list[np.ndarray]
    piece_normals: list[np.ndarray]  # unique face-normal axes of each piece (sign-free), part frame
    vertices: np.ndarray = field(repr=False)  # all hull vertices stacked, for bounds
    _edge_axes: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    @staticmethod
    def from_mesh(name: str, mesh: trimesh.Trimesh) -> ConvexPart:
        pieces = convex_pieces(mesh)
        return ConvexPart(
            name=name,
            geometries=[convex_to_fcl(p.vertices, p.faces) for p in pieces],
            piece_vertices=[np.asarray(p.vertices) for p in pieces],
            piece_normals=[_unique_axes(p.face_normals) for p in pieces],
            vertices=np.concatenate([p.vertices for p in pieces]),
        )

    def piece_edge_axes(self, k: int) -> np.ndarray:
        """(E, 3) unit directions of the edges of piece ``k`` (part frame, sign-free, duplicates removed): the
        edges between faces that are not coplanar, computed once from the piece's hull."""
        if k not in self._edge_axes:
            self._edge_axes[k] = hull_edge_axes(self.piece_vertices[k])
        return self._edge_axes[k]

    def piece_bounds(self, world_from_part: Pose) -> np.ndarray:
        """(K, 2, 3) world bounds of each piece."""
        rotation, position = world_from_part.rotation, world_from_part.position
        out = np.empty((len(self.piece_vertices), 2, 3))
        for k, vertices in enumerate(self.piece_vertices):
            world = vertices @ rotation.T + position
            out[k, 0], out[k, 1] = world.min(axis=0), world.max(axis=0)
        return out

    def bounds(self, world_from_part: Pose) -> np.ndarray:
        world = world_from_part.apply(self.vertices)
        return np.stack([world.min(axis=0), world.max(axis=0)])


def box_gap(bounds_a: np.ndarray, bounds_b: np.ndarray) -> np.ndarray:
    """Gap between axis-aligned boxes (..., 2, 3) along the worst axis (<= 0 when they overlap)."""
    gaps = np.maximum(bounds_b[..., 0, :] - bounds_a[..., 1, :], bounds_a[..., 0, :] - bounds_b[..., 1, :])
    return gaps.max(axis=-1)


def world_bounds(mesh: trimesh.Trimesh, world_from_mesh: Pose) -> np.ndarray:
    """Axis-aligned box (2, 3) of ``mesh`` placed at ``world_from_mesh``: (min corner, max corner), metres."""
    world = world_from_mesh.apply(np.asarray(mesh.vertices, dtype=np.float64))
    return np.stack([world.min(axis=0), world.max(axis=0)])


def box_distance(bounds_a: np.ndarray, bounds_b: np.ndarray) -> float:
    """Euclidean distance between two axis-aligned boxes (2, 3) (0 when they touch or overlap): a lower bound of
    the distance between what they enclose."""
    gaps = np.maximum(0.0, np.maximum(bounds_b[0] - bounds_a[1], bounds_a[0] - bounds_b[1]))
    return float(np.linalg.norm(gaps))


@dataclass(frozen=True)
class DistanceResult:
    """Signed distance between two parts (metres), with, when measured, the witness points (world frame, when
    apart) and the direction ``normal_ab`` in which b moves away from a (world frame)."""

    distance_m: float
    point_a: np.ndarray | None = None
    point_b: np.ndarray | None = None
    normal_ab: np.ndarray | None = None
    measured: bool = True  # False: every piece pair was beyond the cutoff; distance_m is a lower bound


# Plain GJK distance only: FCL's signed distance (libccd EPA) aborts the whole process on some touching convex
# pairs ("The origin is outside of the polytope"), and no solver option avoids it in python-fcl 0.7. Overlap
# depth is measured by separating axes instead (:func:`penetration`).
_REQUEST = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=False)


def penetration(vertices_a: np.ndarray, axes_a: np.ndarray, vertices_b: np.ndarray,
                axes_b: np.ndarray) -> tuple[float, np.ndarray]:
    """Overlap depth of two convex polytopes by the separating-axis test over their face normals (world frame):
    the smallest translation of b along one axis that separates them, and that direction. Exact for face
    contacts, an upper bound where edges cross. A negative depth means separated along that axis."""
    axes = np.concatenate([axes_a, axes_b])
    proj_a, proj_b = vertices_a @ axes.T, vertices_b @ axes.T
    push_forward = proj_a.max(axis=0) - proj_b.min(axis=0)  # move b along +axis by this much
    push_backward = proj_b.max(axis=0) - proj_a.min(axis=0)  # move b along -axis by this much
    forward = push_forward <= push_backward
    depth = np.where(forward, push_forward, push_backward)
    k = int(np.argmin(depth))
    return float(depth[k]), axes[k] * (1.0 if forward[k] else -1.0)


def _piece_distance(part_a: ConvexPart, i: int, world_from_a: Pose, transform_a, part_b: ConvexPart, j: int,
                    world_from_b: Pose, transform_b) -> DistanceResult:
    """Signed distance between piece ``i`` of ``part_a`` and piece ``j`` of ``part_b`` (``transform_*``: the poses
    as FCL transforms)."""
    result = fcl.DistanceResult()
    distance = fcl.distance(
        fcl.CollisionObject(part_a.geometries[i], transform_a),
        fcl.CollisionObject(part_b.geometries[j], transform_b),
        _REQUEST,
        result,
    )
    if distance > 1e-9:
        point_a, point_b = np.array(result.nearest_points[0]), np.array(result.nearest_points[1])
        return DistanceResult(float(distance), point_a, point_b, (point_b - point_a) / distance)
    depth, normal = penetration(
        world_from_a.apply(part_a.piece_vertices[i]), part_a.piece_normals[i] @ world_from_a.rotation.T,
        world_from_b.apply(part_b.piece_vertices[j]), part_b.piece_normals[j] @ world_from_b.rotation.T,
    )
    return DistanceResult(-max(depth, 0.0), normal_ab=normal)  # GJK says they meet: at most touching


def signed_distance(part_a: ConvexPart, world_from_a: Pose, part_b: ConvexPart, world_from_b: Pose,
                    cutoff_m: float = np.inf) -> DistanceResult:
    """Minimum signed distance between the pieces of two posed parts (negative: deepest penetration)."""
    bounds_a, bounds_b = part_a.piece_bounds(world_from_a), part_b.piece_bounds(world_from_b)
    gaps = box_gap(bounds_a[:, None], bounds_b[None, :])
    candidates = np.argwhere(gaps <= cutoff_m)
    if len(candidates) == 0:
        return DistanceResult(float(gaps.min()), measured=False)
    transform_a, transform_b = world_from_a.to_fcl(), world_from_b.to_fcl()
    best = DistanceResult(np.inf)
    for i, j in candidates:
        result = _piece_distance(part_a, i, world_from_a, transform_a, part_b, j, world_from_b, transform_b)
        if result.distance_m < best.distance_m:
            best = result
    return best


def overlapping_pieces(part_a: ConvexPart, world_from_a: Pose, part_b: ConvexPart, world_from_b: Pose,
                       min_depth_m: float = 0.0) -> list[tuple[int, int]]:
    """The pairs (piece of ``part_a``, piece of ``part_b``) that overlap by more than ``min_depth_m`` (metres) where
    the two parts are posed: where two parts overlap, not only how deep."""
    bounds_a, bounds_b = part_a.piece_bounds(world_from_a), part_b.piece_bounds(world_from_b)
    candidates = np.argwhere(box_gap(bounds_a[:, None], bounds_b[None, :]) <= 0.0)
    transform_a, transform_b = world_from_a.to_fcl(), world_from_b.to_fcl()
    return [(int(i), int(j)) for i, j in candidates
            if _piece_distance(part_a, i, world_from_a, transform_a, part_b, j, world_from_b,
                               transform_b).distance_m < -min_depth_m]


def overlapping_pairs(parts: Sequence[ConvexPart], poses: Sequence[Pose],
                      min_depth_m: float = 0.0) -> list[tuple[str, str, float]]:
    """Pairs of the posed parts (``poses[k]`` places ``parts[k]``) whose convex pieces overlap by more than
    ``min_depth_m``: (name a, name b, depth in metres), deepest first."""
    pairs = []
    for i in range(len(parts)):
        for j in range(i + 1, len(parts)):
            depth = -signed_distance(parts[i], poses[i], parts[j], poses[j], 0.0).distance_m
            if depth > min_depth_m:
                pairs.append((parts[i].name, parts[j].name, float(depth)))
    return sorted(pairs, key=lambda pair: -pair[2])


def shrunk(part: ConvexPart, margin_m: float) -> ConvexPart:
    """``part`` with every convex piece pulled in by about ``margin_m`` on each side (out when negative), scaled
    about its centre along the part frame's axes (exact for axis-aligned boxes). A held part checked this way
    may slide along the faces it touches at its target without counting as a collision, while still colliding
    with anything it would cut into by more than the margin."""
    pieces = []
    for vertices in part.piece_vertices:
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        centre, extent = 0.5 * (low + high), high - low
        scale = np.clip((extent - 2.0 * margin_m) / np.maximum(extent, 1e-12), 0.05, None)
        pieces.append(convex_hull((vertices - centre) * scale + centre))
    return ConvexPart(
        name=part.name,
        geometries=[convex_to_fcl(p.vertices, p.faces) for p in pieces],
        piece_vertices=[np.asarray(p.vertices) for p in pieces],
        piece_normals=[_unique_axes(p.face_normals) for p in pieces],
        vertices=np.concatenate([p.vertices for p in pieces]),
    )
