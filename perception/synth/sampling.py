"""Small helpers that draw from a ``numpy.random.Generator`` and return plain Python values."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["uniform", "choice", "chance", "integer"]


def uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A float drawn uniformly from [lo, hi] (``lo`` when the range is empty)."""
    if hi <= lo:
        return float(lo)
    return float(rng.uniform(lo, hi))


def choice(rng: np.random.Generator, options: Sequence, weights: Sequence[float] | None = None):
    """One element of ``options`` (optionally weighted)."""
    if weights is None:
        return options[int(rng.integers(len(options)))]
    p = np.asarray(weights, dtype=np.float64)
    return options[int(rng.choice(len(options), p=p / p.sum()))]


def chance(rng: np.random.Generator, p: float) -> bool:
    """True with probability ``p``."""
    return bool(rng.random() < p)


def integer(rng: np.random.Generator, lo: int, hi: int) -> int:
    """An int drawn uniformly from [lo, hi] inclusive (``lo`` when ``hi < lo``)."""
    if hi <= lo:
        return int(lo)
    return int(rng.integers(lo, hi + 1))
