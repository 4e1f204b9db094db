"""Which way is up: gravity and the upright assembly frame from a predicted assembly in the camera frame.

The network predicts every part's pose in the camera frame (OpenCV: x right, y down, z forward), which carries
no floor. The training cameras have no roll and look down at 10-50 degrees (:func:`cell.render.sample_camera`),
so in the camera frame the true up direction is ``(0, -cos(e), -sin(e))`` for an elevation ``e``: one unknown.
It is read off the predicted assembly itself:

1. **Surfaces** (:func:`manhattan_up`): furniture is built along three axes, so nearly all of its surface faces
   up, down or sideways. Every candidate elevation is scored by the weight of the placed parts' face normals
   (:func:`surface_directions`, each part's normals weighted by their share of its area times the part's size)
   that are parallel or perpendicular to its up direction (a Gaussian kernel of width ``kernel_deg``); this holds
   for merged parts whose principal axes are tilted, and a round leg votes with its sides.
2. **Stable pose** (:func:`stable_up`): the assembly stands on the floor, so its up direction is the outward
   normal of a face of the convex hull of the placed parts, reversed. Among the hull's stable resting faces
   (``trimesh.poses.compute_stable_poses``) the one nearest the surfaces estimate, within ``snap_deg``, gives the
   final direction, projected onto the no-roll plane; without one the surfaces estimate stands.

:func:`upright_frame` then builds ``camera_from_assembly``: z along up, x along the object's dominant horizontal
axis (the one of its four directions nearest to "towards the camera"), origin at the centre of the footprint
with the lowest point at z = 0 (the assembly frame of the assembly folder format). Units: any, as long as the
points are in one unit; the frame's position comes out in that unit.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import trimesh

from cell.render import ELEVATION_RANGE_DEG
from planning.pose import Pose

# elevations searched: the training range with a margin, so a view just outside it is still recovered
SEARCH_MARGIN_DEG = 15.0
COARSE_STEP_DEG = 0.5
FINE_STEP_DEG = 0.05


@dataclass(frozen=True)
class UpSettings:
    elevation_range_deg: tuple[float, float] = ELEVATION_RANGE_DEG  # camera prior: no roll, these elevations
    # Chosen on rotations perturbed by 0-20 degrees per part (benchmarks/perception_accuracy.py, "way back"): a
    # broad kernel averages the parts' errors, and a stable face only refines an estimate already within a few
    # degrees.
    kernel_deg: float = 20.0  # width of the surface-alignment kernel
    snap_deg: float = 3.0  # a stable face within this of the surfaces estimate replaces it (0: surfaces only)
    use_stable_poses: bool = True


DEFAULT_UP = UpSettings()


@dataclass(frozen=True)
class UpEstimate:
    """up_camera: (3,) unit vector, camera frame. elevation_deg: the camera elevation it implies.
    method: "image" (the elevation read from the picture), "surfaces", "stable" (a stable face within the snap
    angle) or "prior" (no structure: mid elevation).
    surfaces_elevation_deg: the elevation the surfaces alone gave."""

    up_camera: np.ndarray
    elevation_deg: float
    method: str
    surfaces_elevation_deg: float


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


def surface_directions(mesh: trimesh.Trimesh, max_directions: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The directions of a mesh's surface in its own frame: (K, 3) unit face normals grouped (sign-free, to about
    1 degree) and (K,) weights (their share of the surface area, summing to 1); the ``max_directions`` largest."""
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    lead = np.argmax(np.abs(normals), axis=1)
    normals = normals * np.sign(normals[np.arange(len(normals)), lead])[:, None]  # n and -n: one direction
    _, group = np.unique(np.round(normals * 60.0), axis=0, return_inverse=True)
    group = group.reshape(-1)
    sums = np.zeros((group.max() + 1, 3))
    np.add.at(sums, group, normals * areas[:, None])
    weights = np.bincount(group, weights=areas)
    keep = np.argsort(weights)[::-1][:max_directions]
    keep = keep[np.linalg.norm(sums[keep], axis=1) > 0]
    directions = sums[keep] / np.linalg.norm(sums[keep], axis=1, keepdims=True)
    total = weights[keep].sum()
    return directions, weights[keep] / total if total > 0 else np.full(len(keep), 1.0 / max(len(keep), 1))


def _manhattan_scores(elevations: np.ndarray, directions: np.ndarray, weights: np.ndarray,
                      kernel_deg: float) -> np.ndarray:
    """Score of each candidate elevation: the weight of the directions parallel or perpendicular to its up."""
    cosines = np.abs(up_from_elevation(elevations) @ directions.T).clip(max=1.0)  # (G, M)
    angles = np.degrees(np.arccos(cosines))
    off = np.minimum(angles, 90.0 - angles)  # from parallel or from perpendicular
    return (weights * np.exp(-0.5 * (off / kernel_deg) ** 2)).sum(axis=1)


def manhattan_up(directions: np.ndarray, weights: np.ndarray, settings: UpSettings = DEFAULT_UP) -> tuple[float, float]:
    """(elevation in degrees, score) of the no-roll up direction that makes the most surface of the predicted
    assembly horizontal or vertical. directions: (M, 3) unit directions in the camera frame (the parts' face
    normals as placed); weights: (M,). The score is the weight of the directions that agree (at most their sum)."""
    directions = np.asarray(directions, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    lo, hi = settings.elevation_range_deg
    coarse = np.arange(lo - SEARCH_MARGIN_DEG, hi + SEARCH_MARGIN_DEG + 1e-9, COARSE_STEP_DEG)
    scores = _manhattan_scores(coarse, directions, weights, settings.kernel_deg)
    centre = coarse[int(np.argmax(scores))]
    fine = np.arange(centre - COARSE_STEP_DEG, centre + COARSE_STEP_DEG + 1e-9, FINE_STEP_DEG)
    scores = _manhattan_scores(fine, directions, weights, settings.kernel_deg)
    best = int(np.argmax(scores))
    return float(fine[best]), float(scores[best])


def stable_up(points_camera: np.ndarray, near: np.ndarray, snap_deg: float) -> np.ndarray | None:
    """The up direction of the stable resting face of the points' convex hull nearest to ``near`` (within
    ``snap_deg``), projected onto the no-roll plane (x = 0); ``None`` if there is none. points_camera: (M, 3)."""
    try:
        hull = trimesh.convex.convex_hull(np.asarray(points_camera, dtype=np.float64))
        with warnings.catch_warnings(), np.errstate(all="ignore"):  # sliver faces of the hull: harmless
            warnings.simplefilter("ignore", RuntimeWarning)
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


def estimate_up(directions: np.ndarray, weights: np.ndarray, points_camera: np.ndarray,
                settings: UpSettings = DEFAULT_UP, image_elevation_deg: float | None = None) -> UpEstimate:
    """The up direction of a predicted assembly in the camera frame (see the module docstring).

    directions: (M, 3) unit surface directions of the placed parts, camera frame; weights: (M,) their weights.
    points_camera: (K, 3) points of the placed parts (any unit), for the stable resting faces.
    image_elevation_deg: the elevation read from the picture (:mod:`perception.elevation`); given, it sets up
    (method "image"): it does not depend on the predicted parts, whose rotation errors mislead the surfaces."""
    elevation, score = manhattan_up(directions, weights, settings)
    if image_elevation_deg is not None:
        lo, hi = settings.elevation_range_deg
        image = float(np.clip(image_elevation_deg, lo - SEARCH_MARGIN_DEG, hi + SEARCH_MARGIN_DEG))
        return UpEstimate(up_from_elevation(image), image, "image", elevation)
    if score <= 1e-3 * max(float(np.sum(weights)), 1e-12):  # no surface agrees with any admissible up direction
        mid = 0.5 * sum(settings.elevation_range_deg)
        return UpEstimate(up_from_elevation(mid), mid, "prior", mid)
    up, method = up_from_elevation(elevation), "surfaces"
    if settings.use_stable_poses and settings.snap_deg > 0:
        stable = stable_up(points_camera, up, settings.snap_deg)
        if stable is not None:
            up, method = stable, "stable"
    return UpEstimate(up, elevation_of(up), method, elevation)


def dominant_yaw_axis(directions: np.ndarray, weights: np.ndarray, up: np.ndarray,
                      kernel_deg: float = 6.0) -> np.ndarray:
    """(3,) unit horizontal direction (perpendicular to ``up``) of the object's main horizontal axis, chosen among
    its four quarter turns as the one nearest to "towards the camera" (-z of the camera, made horizontal).

    The horizontal parts of the surface directions vote modulo 90 degrees (kernel ``kernel_deg``, weight: the
    direction's weight times its horizontal length, squared). Falls back to "towards the camera" alone."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    towards_camera = np.array([0.0, 0.0, -1.0]) - up * -up[2]
    if np.linalg.norm(towards_camera) < 1e-6:  # looking straight down: any horizontal reference
        towards_camera = np.array([1.0, 0.0, 0.0]) - up * up[0]
    e1 = towards_camera / np.linalg.norm(towards_camera)
    e2 = np.cross(up, e1)
    directions = np.asarray(directions, dtype=np.float64)
    x, y = directions @ e1, directions @ e2
    horizontal = x**2 + y**2
    phase = np.arctan2(y, x) * 4.0  # quarter turns fold together
    grid = np.radians(np.arange(-45.0, 45.0, FINE_STEP_DEG))
    difference = np.angle(np.exp(1j * (grid[:, None] * 4.0 - phase[None, :]))) / 4.0
    scores = (np.asarray(weights) * horizontal**2 * np.exp(-0.5 * (np.degrees(difference) / kernel_deg) ** 2)).sum(1)
    if scores.max() < 1e-9:
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
