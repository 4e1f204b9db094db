"""Which way is up: gravity and the upright assembly frame from a predicted assembly in the camera frame.

The network predicts every part's pose in the camera frame (OpenCV: x right, y down, z forward), which carries
no floor. The training cameras have no roll and look down at 10-50 degrees (:func:`cell.render.sample_camera`),
so in the camera frame the true up direction is ``(0, -cos(e), -sin(e))`` for an elevation ``e``: one unknown.
It is read off the predicted assembly itself:

1. **Axes** (:func:`axes_up`): furniture is built along three axes, so most parts have one of their canonical
   (PCA) axes vertical. Every candidate elevation is scored by how many part axes lie near its up direction (a
   Gaussian kernel of width ``kernel_deg``, each part counting its best axis once, weighted by part size).
2. **Stable pose** (:func:`stable_up`): the assembly stands on the floor, so its up direction is the outward
   normal of a face of the convex hull of the placed parts, reversed. Among the hull's stable resting faces
   (``trimesh.poses.compute_stable_poses``) the one nearest the axes estimate, within ``snap_deg``, gives the
   final direction, projected onto the no-roll plane; without one the axes estimate stands.

:func:`upright_frame` then builds ``camera_from_assembly``: z along up, x along the object's dominant horizontal
axis (the one of its four directions nearest to "towards the camera"), origin at the centre of the footprint
with the lowest point at z = 0 (the assembly frame of the assembly folder format). Units: any, as long as the
points are in one unit; the frame's position comes out in that unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from cell.render import ELEVATION_RANGE_DEG
from planning.pose import Pose

# elevations searched: the training range with a margin, so a view just outside it is still recovered
SEARCH_MARGIN_DEG = 15.0
GRID_STEP_DEG = 0.25


@dataclass(frozen=True)
class UpSettings:
    elevation_range_deg: tuple[float, float] = ELEVATION_RANGE_DEG  # camera prior: no roll, these elevations
    kernel_deg: float = 10.0  # width of the axis-alignment kernel
    snap_deg: float = 6.0  # a stable face within this of the axes estimate replaces it (0: axes only)
    use_stable_poses: bool = True


DEFAULT_UP = UpSettings()


@dataclass(frozen=True)
class UpEstimate:
    """up_camera: (3,) unit vector, camera frame. elevation_deg: the camera elevation it implies.
    method: "axes", "stable" (a stable face within the snap angle) or "prior" (no structure: mid elevation)."""

    up_camera: np.ndarray
    elevation_deg: float
    method: str
    axes_elevation_deg: float


def up_from_elevation(elevation_deg: np.ndarray | float) -> np.ndarray:
    """(..., 3) up direction in the camera frame of a camera with no roll at the given elevation(s)."""
    e = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    return np.stack([np.zeros_like(e), -np.cos(e), -np.sin(e)], axis=-1)


def elevation_of(up_camera: np.ndarray) -> float:
    """Camera elevation (degrees) implied by an up direction in the camera frame (its roll ignored)."""
    return float(np.degrees(np.arctan2(-up_camera[2], -up_camera[1])))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions, degrees."""
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _search_grid(settings: UpSettings) -> np.ndarray:
    lo, hi = settings.elevation_range_deg
    return np.arange(lo - SEARCH_MARGIN_DEG, hi + SEARCH_MARGIN_DEG + 1e-9, GRID_STEP_DEG)


def axes_up(rotations: np.ndarray, weights: np.ndarray | None = None,
            settings: UpSettings = DEFAULT_UP) -> tuple[float, float]:
    """(elevation in degrees, score) of the no-roll up direction best aligned with the parts' axes.

    rotations: (N, 3, 3) camera_from_part rotations (columns: each part's axes in the camera frame; any frame
    fixed to the part works, its canonical PCA frame works best). weights: (N,) (default: all 1).
    The score is the weighted number of parts with an axis on the chosen direction (0 when there is none)."""
    rotations = np.asarray(rotations, dtype=np.float64)
    weights = np.ones(len(rotations)) if weights is None else np.asarray(weights, dtype=np.float64)
    grid = _search_grid(settings)
    ups = up_from_elevation(grid)  # (G, 3)
    cosines = np.abs(np.einsum("gi,nik->gnk", ups, rotations)).clip(max=1.0)  # (G, N, 3)
    angles = np.degrees(np.arccos(cosines.max(axis=2)))  # (G, N): each part's best axis
    scores = (weights * np.exp(-0.5 * (angles / settings.kernel_deg) ** 2)).sum(axis=1)
    best = int(np.argmax(scores))
    return float(grid[best]), float(scores[best])


def stable_up(points_camera: np.ndarray, near: np.ndarray, snap_deg: float) -> np.ndarray | None:
    """The up direction of the stable resting face of the points' convex hull nearest to ``near`` (within
    ``snap_deg``), projected onto the no-roll plane (x = 0); ``None`` if there is none. points_camera: (M, 3)."""
    try:
        hull = trimesh.convex.convex_hull(np.asarray(points_camera, dtype=np.float64))
        transforms, _ = trimesh.poses.compute_stable_poses(hull)
    except Exception:  # degenerate (flat or collinear) point sets have no hull to rest on
        return None
    best, best_angle = None, snap_deg
    for transform in transforms:
        up = transform[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # world +z in the hull's (camera) frame
        up = np.array([0.0, up[1], up[2]])
        if np.linalg.norm(up) < 1e-6:
            continue
        up /= np.linalg.norm(up)
        angle = angle_deg(up, near)
        if angle <= best_angle:
            best, best_angle = up, angle
    return best


def estimate_up(rotations: np.ndarray, points_camera: np.ndarray, weights: np.ndarray | None = None,
                settings: UpSettings = DEFAULT_UP) -> UpEstimate:
    """The up direction of a predicted assembly in the camera frame (see the module docstring).

    rotations: (N, 3, 3) each part's canonical axes in the camera frame. points_camera: (M, 3) points of the
    placed parts (any unit). weights: (N,) per-part weights of the axes vote (default 1)."""
    elevation, score = axes_up(rotations, weights, settings)
    if score < 1e-3:  # no part has an axis near any admissible up direction
        mid = 0.5 * sum(settings.elevation_range_deg)
        return UpEstimate(up_from_elevation(mid), mid, "prior", mid)
    up, method = up_from_elevation(elevation), "axes"
    if settings.use_stable_poses and settings.snap_deg > 0:
        stable = stable_up(points_camera, up, settings.snap_deg)
        if stable is not None:
            up, method = stable, "stable"
    return UpEstimate(up, elevation_of(up), method, elevation)


def dominant_yaw_axis(rotations: np.ndarray, up: np.ndarray, weights: np.ndarray | None = None,
                      kernel_deg: float = 6.0) -> np.ndarray:
    """(3,) unit horizontal direction (perpendicular to ``up``) of the object's main horizontal axis, chosen among
    its four quarter turns as the one nearest to "towards the camera" (-z of the camera, made horizontal).

    The horizontal directions of the parts' axes vote modulo 90 degrees (kernel ``kernel_deg``, weight: part
    weight times the axis's horizontal length, squared). Falls back to "towards the camera" alone."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    towards_camera = np.array([0.0, 0.0, -1.0]) - up * -up[2]
    if np.linalg.norm(towards_camera) < 1e-6:  # looking straight down: any horizontal reference
        towards_camera = np.array([1.0, 0.0, 0.0]) - up * up[0]
    e1 = towards_camera / np.linalg.norm(towards_camera)
    e2 = np.cross(up, e1)
    rotations = np.asarray(rotations, dtype=np.float64)
    weights = np.ones(len(rotations)) if weights is None else np.asarray(weights, dtype=np.float64)
    axes = rotations.transpose(0, 2, 1).reshape(-1, 3)  # every part's three axes
    axis_weights = np.repeat(weights, 3)
    x, y = axes @ e1, axes @ e2
    horizontal = x**2 + y**2
    phase = np.arctan2(y, x) * 4.0  # quarter turns fold together
    grid = np.radians(np.arange(-45.0, 45.0, GRID_STEP_DEG))
    difference = np.angle(np.exp(1j * (grid[:, None] * 4.0 - phase[None, :]))) / 4.0
    scores = (axis_weights * horizontal**2 * np.exp(-0.5 * (np.degrees(difference) / kernel_deg) ** 2)).sum(1)
    if scores.max() < 1e-6:
        return e1
    yaw = grid[int(np.argmax(scores))]  # in [-45, 45): the quarter turn nearest e1
    return np.cos(yaw) * e1 + np.sin(yaw) * e2


def upright_frame(points_camera: np.ndarray, up_camera: np.ndarray, x_axis_camera: np.ndarray) -> Pose:
    """``camera_from_assembly`` of the upright assembly frame: z along ``up_camera``, x along ``x_axis_camera``
    (made perpendicular to up), origin at the centre of the footprint of ``points_camera`` ((M, 3), camera frame)
    with their lowest point at z = 0. Positions in the unit of the points."""
    z = np.asarray(up_camera, dtype=np.float64) / np.linalg.norm(up_camera)
    x = np.asarray(x_axis_camera, dtype=np.float64) - z * float(np.dot(x_axis_camera, z))
    x /= np.linalg.norm(x)
    camera_from_assembly_rotation = np.stack([x, np.cross(z, x), z], axis=1)
    local = np.asarray(points_camera, dtype=np.float64) @ camera_from_assembly_rotation  # assembly axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    origin_local = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    return Pose.from_rotation(camera_from_assembly_rotation, camera_from_assembly_rotation @ origin_local)
