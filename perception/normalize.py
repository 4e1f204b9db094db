"""The perception model's view of a set of parts: normalised canonical point clouds, and the way back.

Each part's points are centred, put in their PCA (canonical) frame, and the whole shape is scaled by one factor
``scale_per_m`` so that the longest canonical bounding-box diagonal among its parts is 1 ("normalised units").

Returning to metres and to each mesh's own frame::

    points_part_m = part_from_canonical_m[i].apply(points_norm[i] / scale_per_m)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from perception.pointcloud import POINTS_PER_PART, canonical_frame, sample_surface_fps
from planning.pose import Pose


@dataclass
class NormalizedParts:
    """points_norm: (N, P, 3) float32, normalised units, each part in its canonical frame.
    part_from_canonical_m: N poses, canonical frame (metres) to the mesh's own frame (metres).
    scale_per_m: normalised units per metre (the same for every part of the shape).
    extents_norm: (N, 3) float32, canonical axis-aligned box dimensions, normalised units.
    """

    points_norm: np.ndarray
    part_from_canonical_m: list[Pose]
    scale_per_m: float
    extents_norm: np.ndarray

    def __len__(self) -> int:
        return len(self.part_from_canonical_m)


def normalize_parts(meshes: list[trimesh.Trimesh], points_per_part: int = POINTS_PER_PART,
                    seed: int = 0) -> NormalizedParts:
    """Sample and normalise the parts of one shape. Meshes in metres, each in its own frame."""
    frames = []
    points_canonical_m = []
    for index, mesh in enumerate(meshes):
        part_from_canonical = canonical_frame(mesh)
        points_part = sample_surface_fps(mesh, points_per_part, seed=seed + index)
        frames.append(part_from_canonical)
        points_canonical_m.append(part_from_canonical.inverse().apply(points_part))
    # extents from the mesh vertices, so that sampling noise does not change the scale
    extents_m = np.stack([np.ptp(f.inverse().apply(m.vertices), axis=0) for f, m in zip(frames, meshes)])
    longest_diagonal_m = float(np.max(np.linalg.norm(extents_m, axis=1)))
    if longest_diagonal_m <= 0:
        raise ValueError("all parts are degenerate (zero size)")
    scale = 1.0 / longest_diagonal_m
    return NormalizedParts(
        points_norm=(np.stack(points_canonical_m) * scale).astype(np.float32),
        part_from_canonical_m=frames,
        scale_per_m=scale,
        extents_norm=(extents_m * scale).astype(np.float32),
    )


def camera_from_canonical_norm(camera_from_part_m: Pose, part_from_canonical_m: Pose, centre_camera_m: np.ndarray,
                               scale_per_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The perception target: (quat_wxyz (4,), translation_norm (3,)) of the canonical part in the
    object-centred camera frame (camera axes, origin at the object's centre, normalised units)."""
    camera_from_canonical = camera_from_part_m @ part_from_canonical_m
    return camera_from_canonical.quat_wxyz, (camera_from_canonical.position - centre_camera_m) * scale_per_m


def camera_from_part_metres(quat_wxyz: np.ndarray, translation_norm: np.ndarray, part_from_canonical_m: Pose,
                            centre_camera_m: np.ndarray, scale_per_m: float) -> Pose:
    """Inverse of :func:`camera_from_canonical_norm`: the mesh frame's pose in the camera frame, metres."""
    camera_from_canonical = Pose(np.asarray(translation_norm) / scale_per_m + centre_camera_m, quat_wxyz)
    return camera_from_canonical @ part_from_canonical_m.inverse()
