"""From the network's output to poses in metres: the camera frame and the upright assembly frame.

The network predicts, for each part, the pose of its canonical (PCA-framed, normalised) copy in the
*object-centred* camera frame: camera axes, origin at the object's centre, normalised units
(:mod:`perception.normalize`). Going back:

1. **Metres, mesh frames**: ``centre_from_part = Pose(trans_norm / scale_per_m, quat) @ part_from_canonical^-1``
   (``scale_per_m`` is known from the meshes: the normalisation of their longest part diagonal to 1).
2. **Up and the assembly frame** (:mod:`perception.upright`): z up, lowest point at z = 0, origin at the
   footprint centre, x along the object's main horizontal axis.
3. **Depth**: the training cameras look at the centre of the object's bounding box from the distance at which
   its bounding sphere fills the vertical field of view (:func:`cell.render.fitted_distance_m`), so the centre
   sits at ``(0, 0, d)`` in the camera frame with ``d`` from the predicted assembly's size in metres.

Then ``camera_from_part = Pose((0, 0, d)) @ centre_from_part`` and ``assembly_from_part = camera_from_assembly^-1
@ camera_from_part``, so ``camera_from_part == camera_from_assembly @ assembly_from_part`` for every part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from cell.render import FIELD_OF_VIEW_DEG, fitted_distance_m
from perception.normalize import NormalizedParts
from perception.upright import (
    DEFAULT_UP,
    UpEstimate,
    UpSettings,
    dominant_yaw_axis,
    estimate_up,
    surface_directions,
    upright_frame,
)
from planning.pose import Pose


@dataclass(frozen=True)
class Placement:
    """camera_from_part: N poses of the meshes' own frames, OpenCV camera frame, metres.
    assembly_from_part: N poses, upright assembly frame (+z up, lowest point at z = 0, footprint centre), metres.
    camera_from_assembly: the assembly frame in the camera frame, metres.
    centre_camera_m: (3,) the object centre the network's translations are relative to, camera frame, metres.
    up: the up estimate (camera frame)."""

    camera_from_part: list[Pose]
    assembly_from_part: list[Pose]
    camera_from_assembly: Pose
    centre_camera_m: np.ndarray
    up: UpEstimate


def centre_from_part_metres(quat_wxyz: np.ndarray, trans_norm: np.ndarray, parts: NormalizedParts) -> list[Pose]:
    """Each mesh frame's pose relative to the object centre, camera axes, metres. quat_wxyz: (N, 4) and
    trans_norm: (N, 3), the network's output for the canonical parts (normalised units)."""
    return [Pose(np.asarray(t, np.float64) / parts.scale_per_m, q) @ canon.inverse()
            for q, t, canon in zip(np.asarray(quat_wxyz, np.float64), trans_norm, parts.part_from_canonical_m)]


def _placed_vertices(meshes: list[trimesh.Trimesh], poses: list[Pose]) -> np.ndarray:
    return np.concatenate([pose.apply(np.asarray(mesh.vertices)) for mesh, pose in zip(meshes, poses)])


def surface_directions_camera(meshes: list[trimesh.Trimesh], camera_from_part: list[Pose],
                              extents_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every placed part's surface directions in the camera frame, (M, 3), and their weights, (M,): each part's
    area shares times its size (the canonical box diagonal), so larger parts vote more."""
    directions, weights = [], []
    for mesh, pose, extents in zip(meshes, camera_from_part, extents_norm):
        d, w = surface_directions(mesh)
        directions.append(d @ pose.rotation.T)
        weights.append(w * float(np.linalg.norm(extents)))
    return np.concatenate(directions), np.concatenate(weights)


def place_parts(quat_wxyz: np.ndarray, trans_norm: np.ndarray, parts: NormalizedParts,
                meshes: list[trimesh.Trimesh], up_settings: UpSettings = DEFAULT_UP,
                fov_deg: float = FIELD_OF_VIEW_DEG, image_elevation_deg: float | None = None) -> Placement:
    """Poses in metres in the camera and assembly frames from the network's output (see the module docstring).
    meshes: the N part meshes, metres, own frames (those ``parts`` was normalised from). image_elevation_deg: the
    camera elevation read from the picture (:mod:`perception.elevation`), which then sets up."""
    quat_wxyz = np.asarray(quat_wxyz, dtype=np.float64)
    centre_from_part = centre_from_part_metres(quat_wxyz, trans_norm, parts)
    vertices = _placed_vertices(meshes, centre_from_part)  # object-centred, camera axes, metres
    directions, weights = surface_directions_camera(meshes, centre_from_part, parts.extents_norm)
    up = estimate_up(directions, weights, vertices, up_settings, image_elevation_deg)
    x_axis = dominant_yaw_axis(directions, weights, up.up_camera)
    centred_from_assembly = upright_frame(vertices, up.up_camera, x_axis)
    local = centred_from_assembly.inverse().apply(vertices)
    distance = fitted_distance_m(np.stack([local.min(axis=0), local.max(axis=0)]), fov_deg)
    centre_camera_m = np.array([0.0, 0.0, distance])
    camera_from_centre = Pose(centre_camera_m, np.array([1.0, 0.0, 0.0, 0.0]))
    camera_from_part = [camera_from_centre @ p for p in centre_from_part]
    camera_from_assembly = camera_from_centre @ centred_from_assembly
    assembly_from_camera = camera_from_assembly.inverse()
    return Placement(
        camera_from_part=camera_from_part,
        assembly_from_part=[assembly_from_camera @ p for p in camera_from_part],
        camera_from_assembly=camera_from_assembly,
        centre_camera_m=centre_camera_m,
        up=up,
    )
