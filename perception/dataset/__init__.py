"""Training data for the perception model: building (``python -m perception.dataset build``) and reading."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SPLITS = ("train", "val", "test")


def list_objects(root: str | Path, split: str) -> list[Path]:
    """The object files of one split, sorted by name."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return sorted((Path(root) / split).glob("*.npz"))


def load_object(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of one object file (fields listed in :mod:`perception.dataset.sample`)."""
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}
