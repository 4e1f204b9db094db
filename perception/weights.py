"""The bundled weights and loading a checkpoint for inference (never downloads anything).

``perception/weights/compact.pt`` is the compact model (``perception/configs/compact.toml``'s network) trained on
chairs, tables and cabinets (levels 3 and mixed) on a GPU; it is package data. The commands that reproduce it
(dataset, slim copy, the two GPU runs) are in ``perception/weights/README.md``.
"""

from __future__ import annotations

import contextlib
import functools
from pathlib import Path

import torch
from torch import nn

from perception.config import Config

WEIGHTS_DIR = Path(__file__).parent / "weights"
BUNDLED_WEIGHTS = WEIGHTS_DIR / "compact.pt"
TRAIN_COMMAND = ("python -m perception.train.budget --config compact_gpu ... then --config compact_gpu_pose "
                 "(the commands are in perception/weights/README.md), and copy the weights to that path or pass "
                 "them as the checkpoint")


class MissingWeightsError(FileNotFoundError):
    """The weights file does not exist (the message names the file and the command that trains it)."""


def resolve_checkpoint(checkpoint: str | Path | None = None) -> Path:
    """The weights file to load: ``checkpoint``, or the bundled weights when ``None``. Raises
    :class:`MissingWeightsError` naming the file and the training command when it does not exist."""
    path = BUNDLED_WEIGHTS if checkpoint is None else Path(checkpoint)
    if not path.is_file():
        what = "the bundled perception weights" if checkpoint is None else "perception checkpoint"
        raise MissingWeightsError(f"{what} {path} not found; train them with: {TRAIN_COMMAND}")
    return path


@functools.lru_cache(maxsize=4)
def _load_cached(path: str, mtime_ns: int, size: int) -> tuple[nn.Module, Config, str]:
    from perception.evaluate import load_model

    return load_model(path, "cpu")


def load_for_inference(checkpoint: str | Path | None = None) -> tuple[nn.Module, Config, str, Path]:
    """(model in eval mode on the CPU, its config, its kind, the file) for ``checkpoint`` (``None``: bundled).

    Loaded once per file and kept (a file rewritten since is loaded again)."""
    path = resolve_checkpoint(checkpoint).resolve()
    stat = path.stat()
    model, config, kind = _load_cached(str(path), stat.st_mtime_ns, stat.st_size)
    return model, config, kind, path


# One object at a time is a batch of one: on this project's 2-core machine the compact network takes about 0.2 s
# on one thread and 1-4 s on two when the cores are shared (the threads wait on each other), so one is the default.
INFERENCE_THREADS = 1


@contextlib.contextmanager
def inference_threads(threads: int | None = INFERENCE_THREADS):
    """Run the body with torch's intra-op CPU threads set to ``threads`` (``None``: torch's setting), then
    restore the previous setting."""
    if threads is None:
        yield
        return
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
