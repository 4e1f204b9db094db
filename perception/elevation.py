"""The camera's elevation read from the picture: which way is up, before any part is placed.

The training cameras have no roll and look down at 10-50 degrees (:func:`cell.render.sample_camera`), so up in
the camera frame is ``(0, -cos e, -sin e)`` for one unknown, the elevation ``e``
(:func:`perception.upright.up_from_elevation`). A small CNN (:class:`ElevationNet`, 0.2 M parameters) regresses
``e`` from the picture averaged down to 56x56; it needs no part pose, so its error does not grow with the pose
network's. Trained from scratch on the CPU by ``benchmarks/elevation_probe.py`` (the command is in
``perception/weights/README.md``); bundled as ``perception/weights/elevation.pt``.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch
from torch import nn

from perception.weights import WEIGHTS_DIR

ELEVATION_WEIGHTS = WEIGHTS_DIR / "elevation.pt"
BLOCK = 4  # the 224x224 picture averaged over 4x4 blocks: 56x56


def downsample(images: np.ndarray) -> np.ndarray:
    """(..., 224, 224, 3) uint8 pictures -> (..., 3, 56, 56) uint8, the network's input."""
    images = np.asarray(images)
    *lead, h, w, c = images.shape
    small = images.reshape(*lead, h // BLOCK, BLOCK, w // BLOCK, BLOCK, c).mean(axis=(-4, -2))
    return np.moveaxis(small, -1, -3).round().astype(np.uint8)


class ElevationNet(nn.Module):
    """Five stride-2 convolutions (16-32-64-96-128 channels), global average pooling, a linear head; the output is
    the elevation standardised by the training set's mean and deviation (``mean``/``scale`` in the weights file)."""

    def __init__(self):
        super().__init__()
        layers, width = [], 3
        for out in (16, 32, 64, 96, 128):
            layers += [nn.Conv2d(width, out, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(out), nn.ReLU()]
            width = out
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(width, 1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.float() / 127.5 - 1.0
        return self.head(self.features(x).mean(dim=(2, 3))).squeeze(1)


@functools.lru_cache(maxsize=2)
def _load(path: str, mtime_ns: int) -> tuple[ElevationNet, float, float]:
    saved = torch.load(path, map_location="cpu", weights_only=False)
    model = ElevationNet()
    model.load_state_dict(saved["model"])
    model.eval()
    return model, float(saved["mean"]), float(saved["scale"])


def load_elevation_model(path: str | Path | None = None) -> tuple[ElevationNet, float, float] | None:
    """(model in eval mode, mean, scale) of the weights file ``path`` (``None``: the bundled one), or ``None``
    when the bundled file is absent."""
    path = Path(path) if path is not None else ELEVATION_WEIGHTS
    if not path.is_file():
        if path == ELEVATION_WEIGHTS:
            return None
        raise FileNotFoundError(f"elevation weights {path} not found")
    return _load(str(path.resolve()), path.stat().st_mtime_ns)


@torch.no_grad()
def image_elevation_deg(image: np.ndarray, path: str | Path | None = None) -> float | None:
    """The camera elevation (degrees) the picture shows, from a (224, 224, 3) uint8 image; ``None`` without
    weights."""
    loaded = load_elevation_model(path)
    if loaded is None:
        return None
    model, mean, scale = loaded
    return float(model(torch.from_numpy(downsample(image)[None]))[0]) * scale + mean
