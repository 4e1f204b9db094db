"""Padded part sets: a batch holds P_max part slots per object and a validity mask (B, P).

Per-part networks run on the valid parts only (``pack``), and their outputs are put back into zeroed slots
(``unpack``), so whatever a padded slot holds never reaches a valid output.
"""

from __future__ import annotations

import torch


def pack(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, P, ...) -> (M, ...): the valid parts, in batch then part order."""
    return x[valid]


def unpack(x: torch.Tensor, valid: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
    """(M, ...) -> (B, P, ...): inverse of :func:`pack`, padded slots set to ``fill``."""
    out = x.new_full((*valid.shape, *x.shape[1:]), fill)
    out[valid] = x
    return out


def owner(valid: torch.Tensor) -> torch.Tensor:
    """(M,) index of the object each packed part belongs to."""
    return valid.nonzero(as_tuple=True)[0]


def masked_max(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Max-pool (B, P, F) over the valid parts -> (B, F) (zeros for an object without parts)."""
    masked = x.masked_fill(~valid.unsqueeze(-1), float("-inf")).max(dim=1).values
    return torch.where(valid.any(dim=1, keepdim=True), masked, torch.zeros_like(masked))
