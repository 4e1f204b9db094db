"""Torch geometry for the model and its losses: quaternions (w first), posing point clouds, chamfer distance.

The chamfer distance follows :func:`perception.pointcloud.chamfer_distance`: mean squared nearest-neighbour
distance from a to b plus from b to a.
"""

from __future__ import annotations

import torch

IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)


def quat_normalize(quat: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Unit quaternions (..., 4), w first."""
    return quat / quat.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices of quaternions (..., 4), w first (normalised here)."""
    w, x, y, z = quat_normalize(quat).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*quat.shape[:-1], 3, 3)


def rotate(points: torch.Tensor, quat: torch.Tensor) -> torch.Tensor:
    """Rotate clouds (..., N, 3) by quaternions (..., 4): ``R @ p`` for every point."""
    return points @ quat_to_matrix(quat).transpose(-1, -2)


def pose_points(points: torch.Tensor, quat: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """``R(quat) @ p + trans`` for clouds (..., N, 3), quaternions (..., 4), translations (..., 3)."""
    return rotate(points, quat) + trans.unsqueeze(-2)


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Symmetric chamfer distance between clouds a (..., N, 3) and b (..., M, 3): (...,)."""
    d = squared_distances(a, b)
    return d.min(dim=-1).values.mean(dim=-1) + d.min(dim=-2).values.mean(dim=-1)


def masked_chamfer(a: torch.Tensor, a_valid: torch.Tensor, b: torch.Tensor, b_valid: torch.Tensor) -> torch.Tensor:
    """Chamfer distance (B,) between clouds a (B, N, 3) and b (B, M, 3) counting only their valid points
    (``a_valid`` (B, N), ``b_valid`` (B, M) booleans)."""
    d = squared_distances(a, b)
    big = torch.finfo(d.dtype).max
    d_ab = d.masked_fill(~b_valid[:, None, :], big).min(dim=-1).values  # (B, N)
    d_ba = d.masked_fill(~a_valid[:, :, None], big).min(dim=-2).values  # (B, M)
    a_w, b_w = a_valid.to(d.dtype), b_valid.to(d.dtype)
    return ((d_ab * a_w).sum(-1) / a_w.sum(-1).clamp_min(1) + (d_ba * b_w).sum(-1) / b_w.sum(-1).clamp_min(1))


def squared_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., N, M) squared distances as |a|^2 + |b|^2 - 2 a.b (one matrix product; clamped at 0)."""
    d = a.pow(2).sum(-1).unsqueeze(-1) + b.pow(2).sum(-1).unsqueeze(-2) - 2.0 * (a @ b.transpose(-1, -2))
    return d.clamp_min(0.0)
