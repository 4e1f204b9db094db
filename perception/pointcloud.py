"""Part point clouds: surface sampling, the canonical (PCA) part frame and the chamfer distance.

Frames: a mesh is given in its own ``part`` frame (metres). Its ``canonical`` frame has its origin at the
area-weighted surface centroid and its axes along the principal axes of the surface (largest spread first),
each axis pointing to the side where the surface is skewed (so identical meshes get identical frames whatever
their pose), right-handed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from planning.pose import Pose

if TYPE_CHECKING:  # training on a built dataset reads no mesh: a GPU host needs neither trimesh nor fpsample
    import trimesh

POINTS_PER_PART = 1000
_DENSE_SAMPLES = 8000


def surface_moments(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Exact area-weighted centroid (3,) and covariance (3, 3) of a triangle surface (any mesh, watertight
    or not), in the mesh's frame and unit."""
    triangles = mesh.triangles  # (F, 3, 3)
    areas = mesh.area_faces
    total = float(areas.sum())
    if total <= 0:
        raise ValueError("mesh has zero surface area")
    corner_sum = triangles.sum(axis=1)  # (F, 3)
    centroid = (areas[:, None] * corner_sum / 3.0).sum(axis=0) / total
    # integral of x x^T over a triangle = area / 12 * (sum_i v_i v_i^T + s s^T), s = sum_i v_i
    outer = np.einsum("fij,fik->fjk", triangles, triangles) + np.einsum("fj,fk->fjk", corner_sum, corner_sum)
    second = (areas[:, None, None] * outer).sum(axis=0) / (12.0 * total)
    return centroid, second - np.outer(centroid, centroid)


def canonical_frame(mesh: trimesh.Trimesh) -> Pose:
    """``part_from_canonical``: the PCA frame of the mesh surface, in the mesh's unit."""
    centroid, covariance = surface_moments(mesh)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    axes = eigenvectors[:, np.argsort(eigenvalues)[::-1]]  # columns: largest spread first
    face_centres = mesh.triangles_center - centroid
    skew = (mesh.area_faces[:, None] * (face_centres @ axes) ** 3).sum(axis=0)
    scale = float(np.sqrt(max(eigenvalues.max(), 1e-30)))
    significant = np.abs(skew) > 1e-6 * scale**3 * mesh.area
    signs = np.where(significant & (skew < 0), -1.0, 1.0)
    axes = axes * signs
    if np.linalg.det(axes) < 0:  # keep right-handed: flip the least skewed axis
        axes[:, int(np.argmin(np.abs(skew)))] *= -1.0
    return Pose.from_rotation(axes, centroid)


def sample_surface_fps(mesh: trimesh.Trimesh, count: int = POINTS_PER_PART, seed: int = 0) -> np.ndarray:
    """(count, 3) float64 points on the surface, spread by farthest point sampling over a dense uniform sample.
    Deterministic for a given seed."""
    import fpsample
    import trimesh

    dense, _ = trimesh.sample.sample_surface(mesh, max(_DENSE_SAMPLES, 4 * count), seed=seed)
    indices = fpsample.bucket_fps_kdline_sampling(np.ascontiguousarray(dense, dtype=np.float32), count, h=5,
                                                  start_idx=0)
    return dense[np.asarray(indices, dtype=np.int64)]


def chamfer_distance(points_a: np.ndarray, points_b: np.ndarray) -> float:
    """Symmetric chamfer distance: mean squared nearest-neighbour distance from a to b plus from b to a.
    (The convention of the paper's code: squared distances, summed over both directions.)"""
    d_ab, _ = cKDTree(points_b).query(points_a)
    d_ba, _ = cKDTree(points_a).query(points_b)
    return float(np.mean(d_ab**2) + np.mean(d_ba**2))
