"""One picture and the loose parts in, every part's pose out: ``perception.predict(image, part_meshes)``.

    >>> from perception.predict import predict
    >>> prediction = predict(image, {"seat": seat_mesh, "leg_0": leg_mesh, ...})   # bundled weights
    >>> prediction.assembly_from_part["seat"]     # Pose, metres, upright assembly frame
    >>> prediction.camera_from_part["seat"]       # Pose, metres, OpenCV camera frame of the picture

``image``: (224, 224, 3) uint8 RGB, taken as the training renders are (:func:`cell.render.sample_camera`: object
centred, no roll, elevation 10-50 degrees, 35-degree vertical field of view). ``part_meshes``: a list or a
dictionary of trimesh meshes, each in its own frame, metres (at most 20). The poses map each mesh's own
coordinates into the frame named (``x_camera = camera_from_part.apply(x_part)``); ``camera_from_part ==
camera_from_assembly @ assembly_from_part`` for every part. How the network's normalised output becomes metres
and how up is found: :mod:`perception.placement`, :mod:`perception.upright`. Runs on the CPU without gradients;
never downloads anything (``checkpoint=None`` is the bundled ``perception/weights/compact.pt``).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from cell.render import FIELD_OF_VIEW_DEG, IMAGE_SIZE
from perception.data import collate
from perception.elevation import image_elevation_deg
from perception.equivalence import MAX_PART_INSTANCES, equivalence_classes, instance_onehot
from perception.normalize import NormalizedParts, normalize_parts
from perception.placement import Placement, place_parts
from perception.upright import DEFAULT_UP, UpEstimate, UpSettings
from perception.weights import INFERENCE_THREADS, MissingWeightsError, inference_threads, load_for_inference
from planning.pose import Pose

__all__ = ["predict", "Prediction", "PredictionError", "PreparedParts", "prepare_parts", "run_network"]


class PredictionError(ValueError):
    """Bad input to :func:`predict` (the message names the value) or weights that cannot be loaded."""


class MissingPredictionWeights(PredictionError, MissingWeightsError):
    """The weights file is missing (also a ``FileNotFoundError``); the message names it and how to train it."""


@dataclass(frozen=True)
class PreparedParts:
    """The network's view of the parts (computed once per set of parts, reused for every picture of them).

    normalized: canonical clouds and the way back to metres (:class:`perception.normalize.NormalizedParts`).
    classes: (N,) int64 equivalence classes. instance_onehot: (N, 20) float32."""

    meshes: list[trimesh.Trimesh]
    normalized: NormalizedParts
    classes: np.ndarray
    instance_onehot: np.ndarray


@dataclass(frozen=True)
class Prediction:
    """Every part's pose, keyed by the part's name (the dictionary's keys, or 0..N-1 for a list of meshes).

    camera_from_part: OpenCV camera frame of the picture (x right, y down, z forward), metres.
    assembly_from_part: upright assembly frame (+z up, lowest point at z = 0, origin at the footprint centre),
    metres. camera_from_assembly: the assembly frame in the camera frame. up: the up estimate, camera frame.
    quat_wxyz (N, 4) / trans_norm (N, 3): the network's raw output (canonical parts, object-centred camera frame,
    normalised units). seconds: wall time of the call. foreground: the segmentation's (224, 224) probability
    that a pixel lies on the object (:mod:`perception.agreement`), None for a model without a segmentation."""

    names: list
    camera_from_part: dict
    assembly_from_part: dict
    camera_from_assembly: Pose
    up: UpEstimate
    quat_wxyz: np.ndarray
    trans_norm: np.ndarray
    scale_per_m: float
    checkpoint: Path
    kind: str
    seconds: float
    foreground: np.ndarray | None = None  # (224, 224) float32: P(pixel on the object), None without a segmentation

    def summary(self) -> dict:
        """JSON-ready figures for reports."""
        return {"source": "image", "checkpoint": str(self.checkpoint), "model": self.kind, "parts": len(self.names),
                "seconds": round(self.seconds, 4), "up_camera": [round(float(v), 6) for v in self.up.up_camera],
                "camera_elevation_deg": round(self.up.elevation_deg, 3), "up_method": self.up.method,
                "camera_from_assembly": {"position": self.camera_from_assembly.position.tolist(),
                                         "quat_wxyz": self.camera_from_assembly.quat_wxyz.tolist()}}


def check_image(image) -> np.ndarray:
    """The image as a (224, 224, 3) uint8 array; :class:`PredictionError` naming the shape or dtype otherwise."""
    array = np.asarray(image)
    expected = (IMAGE_SIZE, IMAGE_SIZE, 3)
    if array.shape != expected:
        raise PredictionError(f"image must be an RGB array of shape {expected}, got shape {array.shape}")
    if array.dtype != np.uint8:
        raise PredictionError(f"image must have dtype uint8 (0-255), got {array.dtype}")
    return array


def _named_meshes(part_meshes) -> tuple[list, list[trimesh.Trimesh]]:
    if isinstance(part_meshes, Mapping):
        names, meshes = list(part_meshes.keys()), list(part_meshes.values())
    elif isinstance(part_meshes, Sequence) and not isinstance(part_meshes, (str, bytes)):
        names, meshes = list(range(len(part_meshes))), list(part_meshes)
    else:
        raise PredictionError(f"part_meshes must be a list or dict of trimesh meshes, got {type(part_meshes).__name__}")
    if not meshes:
        raise PredictionError("part_meshes is empty: give at least one part mesh")
    if len(meshes) > MAX_PART_INSTANCES:
        raise PredictionError(f"{len(meshes)} part meshes given; the model handles at most {MAX_PART_INSTANCES}")
    for name, mesh in zip(names, meshes):
        if not isinstance(mesh, trimesh.Trimesh):
            raise PredictionError(f"part {name!r} must be a trimesh.Trimesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all() or mesh.area <= 0:
            raise PredictionError(f"part {name!r}: the mesh is empty, degenerate or not finite "
                                  f"({len(mesh.faces)} faces, area {mesh.area:.3g} m^2)")
    return names, meshes


def prepare_parts(meshes: list[trimesh.Trimesh]) -> PreparedParts:
    """Normalise the parts and find their equivalence classes (meshes in metres, their own frames)."""
    normalized = normalize_parts(meshes)
    classes = equivalence_classes(normalized.points_norm, normalized.extents_norm)
    return PreparedParts(meshes, normalized, classes, instance_onehot(classes))


@torch.no_grad()
def run_network(model: torch.nn.Module, image: np.ndarray, parts: PreparedParts,
                max_parts: int = MAX_PART_INSTANCES, with_foreground: bool = False):
    """The network's poses for one picture: quat_wxyz (N, 4) and trans_norm (N, 3), canonical parts in the
    object-centred camera frame, normalised units. ``with_foreground``: also the (H, W) float32 probability that
    each pixel of the picture lies on the object, from the segmentation (``None`` for a model without one, the
    baselines), as a third element."""
    n = len(parts.meshes)
    sample = {"image": image, "part_labels": np.full(image.shape[:2], -1, np.int8),
              "points": parts.normalized.points_norm, "instance_onehot": parts.instance_onehot,
              "classes": parts.classes, "visible_pixels": np.zeros(n, np.int64)}
    model.eval()
    out = model(collate([sample], max_parts))
    quat, trans = out["quat"][0, :n].double().numpy(), out["trans"][0, :n].double().numpy()
    if not with_foreground:
        return quat, trans
    return quat, trans, _foreground(out, image.shape[:2])


def _foreground(out: dict, shape: tuple[int, int]) -> np.ndarray | None:
    """The segmentation's foreground probability at the picture's resolution, or None without a segmentation."""
    if "background" not in out:
        return None
    foreground = 1.0 - out["background"][:1, None].float()
    if tuple(foreground.shape[-2:]) != tuple(shape):
        foreground = torch.nn.functional.interpolate(foreground, size=shape, mode="bilinear", align_corners=False)
    return foreground[0, 0].numpy().astype(np.float32)


def predict(image, part_meshes, checkpoint: str | Path | None = None, *, threads: int | None = INFERENCE_THREADS,
            up_settings: UpSettings = DEFAULT_UP, fov_deg: float = FIELD_OF_VIEW_DEG,
            image_elevation: bool = True) -> Prediction:
    """Every part's pose from one picture (see the module docstring).

    checkpoint: a ``model.pt`` of ``python -m perception.train`` (``None``: the bundled weights).
    threads: torch CPU threads during the call (``None``: torch's setting; 1 is fastest for one picture on
    shared cores, see :data:`perception.weights.INFERENCE_THREADS`). fov_deg: the picture's vertical field of view.
    image_elevation: up from the camera elevation read from the picture (:mod:`perception.elevation`, the bundled
    weights) rather than from the predicted parts alone. Raises :class:`PredictionError` on a bad image or bad
    meshes, :class:`MissingPredictionWeights` when the weights file is missing."""
    start = time.perf_counter()
    image = check_image(image)
    names, meshes = _named_meshes(part_meshes)
    try:
        model, config, kind, path = load_for_inference(checkpoint)
    except MissingWeightsError as exc:
        raise MissingPredictionWeights(str(exc)) from None
    except (FileNotFoundError, ValueError) as exc:
        raise PredictionError(f"cannot load the perception weights: {exc}") from exc
    parts = prepare_parts(meshes)
    with inference_threads(threads):
        quat, trans, foreground = run_network(model, image, parts, config.model.max_parts, with_foreground=True)
        elevation = image_elevation_deg(image) if image_elevation else None
    placement: Placement = place_parts(quat, trans, parts.normalized, meshes, up_settings, fov_deg, elevation)
    return Prediction(
        names=names,
        camera_from_part=dict(zip(names, placement.camera_from_part)),
        assembly_from_part=dict(zip(names, placement.assembly_from_part)),
        camera_from_assembly=placement.camera_from_assembly,
        up=placement.up,
        quat_wxyz=quat,
        trans_norm=trans,
        scale_per_m=parts.normalized.scale_per_m,
        checkpoint=path,
        kind=kind,
        seconds=time.perf_counter() - start,
        foreground=foreground,
    )
