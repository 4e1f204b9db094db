"""Hungarian matching of predictions to ground-truth parts inside each class of equivalent parts.

Equivalent parts are interchangeable (a left leg predicted where the right leg stands is a correct leg), so
prediction i may be matched to any ground-truth part j of its own class; across classes nothing is exchanged.
Used by the losses (training) and the metrics (evaluation).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment


def match_within_classes(cost: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """perm (n,) int64: prediction i is matched to ground-truth part ``perm[i]``, of the same class, minimising
    the summed ``cost[i, perm[i]]`` over each class. ``cost``: (n, n) (at least; extra rows/columns are padding
    and ignored), ``classes``: (n,) class of each part."""
    classes = np.asarray(classes)
    n = len(classes)
    cost = np.asarray(cost, dtype=np.float64)[:n, :n]
    perm = np.arange(n)
    for c in np.unique(classes):
        members = np.flatnonzero(classes == c)
        if len(members) < 2:
            continue
        block = cost[np.ix_(members, members)]
        block = np.where(np.isfinite(block), block, np.finfo(np.float64).max / (4 * n))
        rows, cols = linear_sum_assignment(block)
        perm[members[rows]] = members[cols]
    return perm


def batch_match(cost: torch.Tensor, classes: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, P) long: for each object, :func:`match_within_classes` over its valid parts; padded slots map to
    themselves. ``cost`` (B, P, P) is read without gradient."""
    cost_np = cost.detach().float().cpu().numpy()
    classes_np = classes.cpu().numpy()
    valid_np = valid.cpu().numpy()
    perm = np.tile(np.arange(cost.shape[1]), (cost.shape[0], 1))
    for b in range(cost.shape[0]):
        idx = np.flatnonzero(valid_np[b])
        perm[b, idx] = idx[match_within_classes(cost_np[b][np.ix_(idx, idx)], classes_np[b, idx])]
    return torch.from_numpy(perm).to(cost.device)


def gather_parts(x: torch.Tensor, perm: torch.Tensor) -> torch.Tensor:
    """Reorder (B, P, ...) along the part axis: out[b, i] = x[b, perm[b, i]]."""
    index = perm.view(*perm.shape, *([1] * (x.dim() - 2))).expand(*perm.shape, *x.shape[2:])
    return torch.gather(x, 1, index)
