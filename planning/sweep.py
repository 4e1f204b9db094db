"""Straight-line removal of a part: does moving it along a direction run into another part or the floor?

Whether part ``p`` moving along ``d`` is blocked by part ``b`` depends on ``p``, ``d`` and ``b`` only, not on
the other parts present (a directional blocking graph, as in Wilson and Latombe's assembly planning), so a
planner asks :func:`blocks` once per triple and combines the answers for any sub-assembly.

A sweep starts where the parts are in the target assembly. Parts that already touch or overlap there (real
furniture overlaps at its dowels) may keep that overlap, but may not go deeper than it by more than
:data:`PENETRATION_TOLERANCE_M`. The motion is checked by conservative advancement: while the parts are apart
the moving one advances by their distance (it cannot hit anything sooner), and in contact by small steps of
:data:`CONTACT_STEP_M`.
"""

from __future__ import annotations

import numpy as np

from planning.collision import ConvexPart, signed_distance
from planning.pose import Pose

PENETRATION_TOLERANCE_M = 0.0005
CONTACT_STEP_M = 0.004  # below the 5 mm + 5 mm two thin parts need to pass through each other unseen
CLEARANCE_MARGIN_M = 0.005  # travel beyond the last overlap of extents before a part counts as removed
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
    """Whether ``obstacle`` blocks ``moving`` from leaving along the unit vector ``direction`` (world frame)."""
    direction = np.asarray(direction, dtype=np.float64)
    moving_world = world_from_moving.apply(moving.vertices)
    obstacle_world = world_from_obstacle.apply(obstacle.vertices)
    length = travel_to_clear_m(moving_world, obstacle_world, direction)
    if length <= 0:
        return False
    moving_bounds = np.stack([moving_world.min(axis=0), moving_world.max(axis=0)])
    obstacle_bounds = np.stack([obstacle_world.min(axis=0), obstacle_world.max(axis=0)])
    swept = _swept_bounds(moving_bounds, direction, length)
    if np.any(swept[1] < obstacle_bounds[0] - 1e-9) or np.any(obstacle_bounds[1] < swept[0] - 1e-9):
        return False  # the swept box never meets the obstacle
    start = signed_distance(moving, world_from_moving, obstacle, world_from_obstacle, _CUTOFF_M).distance_m
    allowed = min(start, 0.0) - PENETRATION_TOLERANCE_M
    travelled, distance = 0.0, start
    while travelled < length + CLEARANCE_MARGIN_M:
        # apart: nothing can be hit before covering the distance (a lower bound beyond the cutoff)
        travelled += max(distance, CONTACT_STEP_M)
        moved = Pose(world_from_moving.position + travelled * direction, world_from_moving.quat_wxyz)
        distance = signed_distance(moving, moved, obstacle, world_from_obstacle, _CUTOFF_M).distance_m
        if distance < allowed:
            return True
    return False


def leaves_above_floor(moving: ConvexPart, world_from_moving: Pose, direction: np.ndarray, travel_m: float,
                       floor_z_m: float = 0.0) -> bool:
    """Whether the part stays above the floor plane (within tolerance) over ``travel_m`` along ``direction``."""
    lowest = float(world_from_moving.apply(moving.vertices)[:, 2].min())
    allowed = min(lowest - floor_z_m, 0.0) - PENETRATION_TOLERANCE_M
    return lowest + travel_m * min(float(direction[2]), 0.0) - floor_z_m >= allowed
