"""One training object: its normalised parts and K rendered views, as a dictionary of arrays.

Array fields (N parts, K views, P = 1000 points, H = W = 224):

    points_norm                  (N, P, 3) float32  canonical part clouds, normalised units
    extents_norm                 (N, 3)    float32  canonical box dimensions, normalised units
    equivalence_class            (N,)      int64    class of geometrically equivalent parts
    instance_onehot              (N, 20)   float32  index of the part among its class (P_max = 20)
    scale_per_m                  ()        float64  normalised units per metre
    part_from_canonical_position_m (N, 3)  float64  canonical frame in the mesh frame, metres
    part_from_canonical_quat_wxyz  (N, 4)  float64
    assembly_from_part_position_m  (N, 3)  float64  ground truth, assembly frame (+z up), metres
    assembly_from_part_quat_wxyz   (N, 4)  float64
    images                       (K, H, W, 3) uint8
    part_labels                  (K, H, W) int8     part index per pixel, -1 background
    visible_pixels               (K, N)    int32
    intrinsics                   (K, 3, 3) float64  OpenCV pinhole matrix, pixels
    camera_from_assembly_position_m (K, 3) float64  OpenCV camera (x right, y down, z forward)
    camera_from_assembly_quat_wxyz  (K, 4) float64
    centre_camera_m              (K, 3)    float64  object centre (bounds centre) in the camera frame
    pose_quat_wxyz               (K, N, 4) float32  canonical part -> object-centred camera frame (the target)
    pose_translation_norm        (K, N, 3) float32  same, translation in normalised units
    part_names                   (N,)      str

``perception.normalize.camera_from_part_metres`` maps a (quat, translation) back to metres and the mesh frame.
"""

from __future__ import annotations

import numpy as np

from cell.render import Appearance, AssemblyRenderer, sample_camera
from perception.equivalence import equivalence_classes, instance_onehot
from perception.normalize import camera_from_canonical_norm, normalize_parts
from planning.assembly import Assembly


def _poses_to_arrays(poses) -> tuple[np.ndarray, np.ndarray]:
    return np.stack([p.position for p in poses]), np.stack([p.quat_wxyz for p in poses])


def object_sample(assembly: Assembly, views: int, rng: np.random.Generator, renderer: str = "tiny",
                  materials: str = "parts") -> dict:
    """Normalise the parts of ``assembly`` and render ``views`` random views, its parts coloured as ``materials``
    says (:meth:`cell.render.Appearance.sample`). Deterministic given ``rng``."""
    parts = normalize_parts([p.mesh for p in assembly.parts])
    classes = equivalence_classes(parts.points_norm, parts.extents_norm)
    sample: dict[str, np.ndarray] = {
        "points_norm": parts.points_norm,
        "extents_norm": parts.extents_norm,
        "equivalence_class": classes,
        "instance_onehot": instance_onehot(classes),
        "scale_per_m": np.float64(parts.scale_per_m),
        "part_names": np.array(assembly.part_names),
    }
    sample["part_from_canonical_position_m"], sample["part_from_canonical_quat_wxyz"] = _poses_to_arrays(
        parts.part_from_canonical_m
    )
    sample["assembly_from_part_position_m"], sample["assembly_from_part_quat_wxyz"] = _poses_to_arrays(
        [p.assembly_from_part for p in assembly.parts]
    )
    bounds = assembly.bounds()
    centre_assembly_m = 0.5 * (bounds[0] + bounds[1])
    per_view: dict[str, list] = {k: [] for k in (
        "images", "part_labels", "visible_pixels", "intrinsics", "camera_from_assembly_position_m",
        "camera_from_assembly_quat_wxyz", "centre_camera_m", "pose_quat_wxyz", "pose_translation_norm")}
    with AssemblyRenderer(assembly, renderer=renderer) as scene:
        for _ in range(views):
            view = scene.render(sample_camera(rng, bounds), Appearance.sample(rng, len(assembly.parts), materials))
            centre_camera_m = view.camera_from_assembly.apply(centre_assembly_m)
            targets = [
                camera_from_canonical_norm(cam_from_part, canon, centre_camera_m, parts.scale_per_m)
                for cam_from_part, canon in zip(view.camera_from_part, parts.part_from_canonical_m)
            ]
            per_view["images"].append(view.rgb)
            per_view["part_labels"].append(view.part_labels.astype(np.int8))
            per_view["visible_pixels"].append(view.visible_pixels.astype(np.int32))
            per_view["intrinsics"].append(view.intrinsics)
            per_view["camera_from_assembly_position_m"].append(view.camera_from_assembly.position)
            per_view["camera_from_assembly_quat_wxyz"].append(view.camera_from_assembly.quat_wxyz)
            per_view["centre_camera_m"].append(centre_camera_m)
            per_view["pose_quat_wxyz"].append(np.stack([q for q, _ in targets]).astype(np.float32))
            per_view["pose_translation_norm"].append(np.stack([t for _, t in targets]).astype(np.float32))
    sample.update({k: np.stack(v) for k, v in per_view.items()})
    return sample
