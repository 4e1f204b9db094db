"""Checkpoints: atomic writes, the full training state for resuming, and the weights-only model file.

``checkpoint.pt`` (resuming) holds the model, the optimiser, the stage and step, the early-stopping state (with
the best weights so far), the RNG states of torch, numpy and Python, the loss log and the configuration.
``model.pt`` (bundling, evaluation) holds the configuration, the model kind and the weights only.
Both carry the configuration, so :func:`perception.evaluate.load_model` rebuilds the network from either.
"""

from __future__ import annotations

import io
import os
import random
import tempfile
from pathlib import Path

import numpy as np
import torch

FORMAT = 1
CHECKPOINT = "checkpoint.pt"
MODEL = "model.pt"
LOG = "log.json"


def atomic_write_bytes(data: bytes, path: Path) -> None:
    """Write to a temporary file in the same folder, then rename it into place (never a half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_torch_save(obj, path: Path) -> None:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    atomic_write_bytes(buffer.getvalue(), path)


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def cpu_state_dict(module: torch.nn.Module) -> dict:
    """A detached CPU copy of a module's state (parameters and buffers)."""
    return {k: v.detach().to("cpu", copy=True) for k, v in module.state_dict().items()}


def load_checkpoint(path: Path) -> dict:
    # the checkpoint holds numpy RNG state and plain Python objects besides tensors: not weights_only
    return torch.load(path, map_location="cpu", weights_only=False)


def export_model(model: torch.nn.Module, kind: str, config: dict, path: Path, dtype: torch.dtype = torch.float32,
                 extra: dict | None = None) -> int:
    """Write the weights-only model file; returns its size in bytes. Floating tensors are stored as ``dtype``
    (contiguous), other buffers unchanged. The file carries no data location (it may be bundled and shipped):
    the config's ``data.paths`` are left out."""
    state = {k: (v.to(dtype) if v.is_floating_point() else v).contiguous() for k, v in cpu_state_dict(model).items()}
    config = {**config, "data": {**config.get("data", {}), "paths": []}}
    payload = {"format": FORMAT, "kind": kind, "config": config, "model": state, **(extra or {})}
    atomic_torch_save(payload, path)
    return Path(path).stat().st_size
