"""The kitting ring and the rectangles laid out in it (world frame, metres, +z up).

The kitting area is a ring around the robot base on the table (:class:`KittingArea`): between an inner radius
(clear of the robot's base) and an outer radius (within reach), inside the table, outside keep-out rectangles
(the jig with the assembly growing on it, plus room for the hand). Each part's footprint is a rectangle turned
so that its long side runs along the ring (tangential) or across it; :func:`candidate_places` lists the places
nearest the jig first. The rectangle tests are separating-axis tests written with numpy, thousands of candidate
places against every slot at once: convex quadrilaterals need nothing more, so no polygon library is required.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from planning.pose import Pose
from planning.stability import stable_rest_poses

RADIAL_STEP_M = 0.03  # candidate places: rings this far apart ...
ANGLE_STEP_DEG = 3.0  # ... and this many degrees apart about the robot base
COMFORTABLE_FRACTION = 0.6  # places beyond this fraction of the ring's depth are tried last ...
FAR_PENALTY = 3.0  # ... as if each metre beyond it were this many metres farther from the jig


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


def yaw_pose(angle_rad: float) -> Pose:
    return Pose([0.0, 0.0, 0.0], [np.cos(angle_rad / 2), 0.0, 0.0, np.sin(angle_rad / 2)])


_UNIT_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def rectangle_corners(centre_xy: np.ndarray, yaw_rad: float, half_xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    local = _UNIT_SQUARE * half_xy
    return local @ np.array([[c, s], [-s, c]]) + centre_xy


def rectangles_corners(centres_xy: np.ndarray, yaws_rad: np.ndarray, half_xy: np.ndarray) -> np.ndarray:
    """:func:`rectangle_corners` of N rectangles of the same half extents at once: (N, 4, 2)."""
    c, s = np.cos(yaws_rad)[:, None], np.sin(yaws_rad)[:, None]
    local = _UNIT_SQUARE * half_xy  # (4, 2)
    x = local[None, :, 0] * c - local[None, :, 1] * s
    y = local[None, :, 0] * s + local[None, :, 1] * c
    return np.stack([x, y], axis=-1) + np.asarray(centres_xy)[:, None, :]


def quads_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`polygons_overlap` of every quadrilateral of ``a`` (N, 4, 2) with every one of ``b`` (M, 4, 2):
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


def polygons_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two convex quadrilaterals (4, 2)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.column_stack([-edges[:, 1], edges[:, 0]]):
            pa, pb = a @ [nx, ny], b @ [nx, ny]
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def box_corners(lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
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
    keep_out = np.array([box_corners(k_lo, k_hi) for k_lo, k_hi in area.keep_out]).reshape(-1, 4, 2)
    places = []
    for across in (False, True):
        depth = half_xy[0] if across else half_xy[1]  # half extent along the radius
        radii = np.arange(area.inner_radius_m + depth, area.outer_radius_m + 1e-9, RADIAL_STEP_M)
        radius, angle = (grid.ravel() for grid in np.meshgrid(radii, angles, indexing="ij"))
        xy = centre + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
        long_yaw = angle if across else angle + np.pi / 2
        corners = rectangles_corners(xy, long_yaw, half_xy)
        ok = np.all((corners >= lo) & (corners <= hi), axis=(1, 2))
        if len(keep_out) and ok.any():
            grown = rectangles_corners(xy[ok], long_yaw[ok], half_xy + area.gap_m / 2)
            ok[np.flatnonzero(ok)] = ~quads_overlap(grown, keep_out).any(axis=1)
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
