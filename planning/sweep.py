"""Straight-line removal of a part: does moving it along a direction run into another part or the floor?

Whether part ``p`` moving along ``d`` is blocked by part ``b`` depends on ``p``, ``d`` and ``b`` only, not on
the other parts present (a directional blocking graph, as in Wilson and Latombe's assembly planning), so a
planner asks :func:`blocks` once per triple and combines the answers for any sub-assembly.

A sweep starts where the parts are in the target assembly. Parts that already touch or overlap there (real
furniture overlaps at its dowels) may keep that overlap, but may not go deeper than it by more than
:data:`PENETRATION_TOLERANCE_M`. The motion is checked per pair of convex pieces, continuously: the overlap depth
of two convex polytopes along any axis is piecewise linear in the distance travelled, so separating axes (the
faces of both and the cross products of their edges) give the exact stretch of the motion, if any, where the
pieces overlap too deeply (:func:`sweep_overlaps`). Pieces with very many edges (decomposed real meshes) are
checked with their face normals first, which can only overestimate the depth, and where that finds a stretch,
by conservative advancement over it: while apart the piece advances by their distance (it cannot hit anything
sooner), in contact by steps of :data:`CONTACT_STEP_M`.
"""

from __future__ import annotations

import numpy as np

from planning.collision import ConvexPart, signed_distance
from planning.pose import Pose

PENETRATION_TOLERANCE_M = 0.0005
CONTACT_STEP_M = 0.004  # below the 5 mm + 5 mm two thin parts need to pass through each other unseen
CLEARANCE_MARGIN_M = 0.005  # travel beyond the last overlap of extents before a part counts as removed
MAX_EDGE_PAIRS = 2000  # pieces with more edge-direction pairs than this are swept by conservative advancement
_CUTOFF_M = 0.05  # piece pairs farther apart than this are not measured (their box gap bounds the distance)


def travel_to_clear_m(moving_vertices_world: np.ndarray, obstacle_vertices_world: np.ndarray,
                      direction: np.ndarray) -> float:
    """Distance along ``direction`` after which the moving part lies wholly beyond the obstacle's extent."""
    return float(np.max(obstacle_vertices_world @ direction) - np.min(moving_vertices_world @ direction))


def _swept_bounds(bounds: np.ndarray, direction: np.ndarray, length_m: float) -> np.ndarray:
    end = bounds + direction * length_m
    return np.stack([np.minimum(bounds[0], end[0]), np.maximum(bounds[1], end[1])])


def blocks(moving: ConvexPart, world_from_moving: Pose, obstacle: ConvexPart, world_from_obstacle: Pose,
           direction: np.ndarray) -> bool:
    """Whether ``obstacle`` blocks ``moving`` from leaving along the unit vector ``direction`` (world frame).

    Blocked when, somewhere along the way (from the target until ``moving`` lies wholly beyond ``obstacle``
    along ``direction``, plus :data:`CLEARANCE_MARGIN_M`), a convex piece of ``moving`` overlaps a piece of
    ``obstacle`` by more than their overlap at the target plus :data:`PENETRATION_TOLERANCE_M`. Each pair of
    pieces is decided over the whole straight motion at once by separating axes (:func:`sweep_overlaps`);
    pairs of pieces with too many edges for that fall back to conservative advancement.
    """
    direction = np.asarray(direction, dtype=np.float64)
    moving_world = world_from_moving.apply(moving.vertices)
    obstacle_world = world_from_obstacle.apply(obstacle.vertices)
    length = travel_to_clear_m(moving_world, obstacle_world, direction)
    if length <= 0:
        return False
    moving_bounds = np.stack([moving_world.min(axis=0), moving_world.max(axis=0)])
    obstacle_bounds = np.stack([obstacle_world.min(axis=0), obstacle_world.max(axis=0)])
    swept = _swept_bounds(moving_bounds, direction, length)
    if _apart(swept, obstacle_bounds):
        return False  # the swept box never meets the obstacle
    start = signed_distance(moving, world_from_moving, obstacle, world_from_obstacle, _CUTOFF_M).distance_m
    allowed_depth = -min(start, 0.0) + PENETRATION_TOLERANCE_M
    travel = length + CLEARANCE_MARGIN_M
    rotation_m, rotation_o = world_from_moving.rotation, world_from_obstacle.rotation
    moving_boxes = moving.piece_bounds(world_from_moving)
    obstacle_boxes = obstacle.piece_bounds(world_from_obstacle)
    for i, box_i in enumerate(moving_boxes):
        swept_i = _swept_bounds(box_i, direction, travel)
        vertices_i = world_from_moving.apply(moving.piece_vertices[i])
        for j, box_j in enumerate(obstacle_boxes):
            if _apart(swept_i, box_j):
                continue
            edges_i, edges_j = moving.piece_edge_axes(i) @ rotation_m.T, obstacle.piece_edge_axes(j) @ rotation_o.T
            exact = len(edges_i) * len(edges_j) <= MAX_EDGE_PAIRS
            window = sweep_overlaps(
                vertices_i, moving.piece_normals[i] @ rotation_m.T,
                world_from_obstacle.apply(obstacle.piece_vertices[j]), obstacle.piece_normals[j] @ rotation_o.T,
                direction, travel, allowed_depth, (edges_i, edges_j) if exact else None)
            if window is None:
                continue
            if exact or _advance_blocked(moving, world_from_moving, i, obstacle, world_from_obstacle, j, direction,
                                         window, -allowed_depth):
                return True
    return False


def sweep_overlaps(vertices_a: np.ndarray, normals_a: np.ndarray, vertices_b: np.ndarray, normals_b: np.ndarray,
                   direction: np.ndarray, travel_m: float, allowed_depth_m: float,
                   edges: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float] | None:
    """When convex polytope a, translated by ``t * direction`` for ``0 <= t <= travel_m``, overlaps convex
    polytope b deeper than ``allowed_depth_m``: the interval of ``t`` (metres), or None if it never does.

    vertices_*: (N, 3) world frame, metres; normals_*: (K, 3) unit face normals (sign-free); ``edges``: the unit
    edge directions of a and of b. The overlap depth along an axis is the shorter push separating the two
    projections, linear in ``t`` on each side, and the depth is its minimum over the axes, so the interval is
    exact (one linear program in ``t``). With the edges, the axes are complete (faces of both, edge-edge cross
    products) and the depth is the true penetration depth; without them (face normals and ``direction`` only),
    the depth is an upper bound, and None still proves the motion free.
    """
    axes = [normals_a, normals_b, direction[None]]
    if edges is not None:
        cross = np.cross(edges[0][:, None], edges[1][None]).reshape(-1, 3)
        norm = np.linalg.norm(cross, axis=1)
        axes.append(cross[norm > 1e-9] / norm[norm > 1e-9, None])
    axes = np.concatenate(axes)
    proj_a, proj_b = vertices_a @ axes.T, vertices_b @ axes.T
    rate = axes @ direction
    # overlap along each axis: min(forward + rate * t, backward - rate * t) must exceed allowed_depth_m
    offsets = np.concatenate([proj_a.max(axis=0) - proj_b.min(axis=0), proj_b.max(axis=0) - proj_a.min(axis=0)])
    slopes = np.concatenate([rate, -rate])
    excess = offsets - allowed_depth_m  # line k exceeds the allowed depth where excess_k + slope_k * t > 0
    flat = np.abs(slopes) < 1e-12
    if np.any(excess[flat] <= 0.0):
        return None
    rising, falling = slopes > 0, slopes < 0
    lo = max(0.0, float(np.max(-excess[rising] / slopes[rising], initial=-np.inf)))
    hi = min(travel_m, float(np.min(-excess[falling] / slopes[falling], initial=np.inf)))
    return (lo, hi) if lo < hi else None


def _advance_blocked(moving: ConvexPart, world_from_moving: Pose, i: int, obstacle: ConvexPart,
                     world_from_obstacle: Pose, j: int, direction: np.ndarray, window: tuple[float, float],
                     allowed_m: float) -> bool:
    """Conservative advancement of piece ``i`` of ``moving`` past piece ``j`` of ``obstacle`` over ``window``
    (metres along ``direction``): True if their signed distance falls below ``allowed_m`` (negative)."""
    one_a = ConvexPart(moving.name, [moving.geometries[i]], [moving.piece_vertices[i]], [moving.piece_normals[i]],
                       moving.piece_vertices[i])
    one_b = ConvexPart(obstacle.name, [obstacle.geometries[j]], [obstacle.piece_vertices[j]],
                       [obstacle.piece_normals[j]], obstacle.piece_vertices[j])
    travelled = window[0]
    while True:
        moved = Pose(world_from_moving.position + travelled * direction, world_from_moving.quat_wxyz)
        distance = signed_distance(one_a, moved, one_b, world_from_obstacle, _CUTOFF_M).distance_m
        if distance < allowed_m:
            return True
        if travelled >= window[1]:
            return False
        travelled = min(travelled + max(distance, CONTACT_STEP_M), window[1])


def _apart(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.any(a[1] < b[0] - 1e-9) or np.any(b[1] < a[0] - 1e-9))


def leaves_above_floor(moving: ConvexPart, world_from_moving: Pose, direction: np.ndarray, travel_m: float,
                       floor_z_m: float = 0.0) -> bool:
    """Whether the part stays above the floor plane (within tolerance) over ``travel_m`` along ``direction``."""
    lowest = float(world_from_moving.apply(moving.vertices)[:, 2].min())
    allowed = min(lowest - floor_z_m, 0.0) - PENETRATION_TOLERANCE_M
    return lowest + travel_m * min(float(direction[2]), 0.0) - floor_z_m >= allowed
