"""Graph message passing over an object's parts and the two-phase pose reasoning of the paper.

Phase 1 passes messages along the edges between equivalent parts (edge feature 0). Phase 2 adds, for every
part, edges to its ``knn`` nearest parts in the phase-1 predicted assembly (distance between predicted centres;
edge feature 1). Each phase runs ``iterations`` rounds; node features are f0 (input), f1 (after phase 1) and f2
(after phase 2); phase 1 decodes a pose from [f0; f1], phase 2 from [f0; f1; f2].

Graphs are dense (B, P, P) adjacency matrices restricted to valid parts, so padded parts send and receive
nothing.
"""

from __future__ import annotations

import torch
from torch import nn

from perception.model.geometry import IDENTITY_QUAT, quat_normalize


def equivalence_adjacency(classes: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, P, P) float: 1 between two distinct valid parts of the same equivalence class."""
    both = valid.unsqueeze(2) & valid.unsqueeze(1)
    same = classes.unsqueeze(2) == classes.unsqueeze(1)
    eye = torch.eye(classes.shape[1], dtype=torch.bool, device=classes.device)
    return (both & same & ~eye).float()


def knn_adjacency(centres: torch.Tensor, valid: torch.Tensor, k: int) -> torch.Tensor:
    """(B, P, P) float: row i has 1 at the ``k`` valid parts nearest to part i (itself excluded; fewer when the
    object has fewer parts). ``centres``: (B, P, 3)."""
    b, p, _ = centres.shape
    k = min(k, p - 1)
    if k <= 0:
        return centres.new_zeros(b, p, p)
    distance = torch.cdist(centres, centres)
    eye = torch.eye(p, dtype=torch.bool, device=centres.device)
    allowed = valid.unsqueeze(2) & valid.unsqueeze(1) & ~eye
    distance = distance.masked_fill(~allowed, float("inf"))
    values, index = distance.topk(k, dim=2, largest=False)
    adjacency = centres.new_zeros(b, p, p)
    adjacency.scatter_(2, index, torch.isfinite(values).to(adjacency.dtype))
    return adjacency


class EdgeConv(nn.Module):
    """One message-passing round: message m_ij = ReLU(W [h_i; h_j; e_ij]) (a linear layer split into its node
    and edge parts), mean over the neighbours j of i, then h_i' = ReLU(U [h_i; mean_j m_ij])."""

    def __init__(self, dim: int):
        super().__init__()
        self.receiver = nn.Linear(dim, dim)
        self.sender = nn.Linear(dim, dim, bias=False)
        self.edge = nn.Linear(1, dim, bias=False)
        self.update = nn.Linear(2 * dim, dim)

    def forward(self, h: torch.Tensor, graphs: list[tuple[torch.Tensor, float]]) -> torch.Tensor:
        """h: (B, P, D); graphs: (adjacency (B, P, P), edge feature) pairs, their edges pooled together."""
        node = self.receiver(h).unsqueeze(2) + self.sender(h).unsqueeze(1)  # (B, P, P, D): i receives from j
        total = torch.zeros_like(h)
        count = h.new_zeros(h.shape[:2])
        for adjacency, feature in graphs:
            edge = self.edge.weight[:, 0] * feature
            total = total + torch.einsum("bij,bijd->bid", adjacency, torch.relu(node + edge))
            count = count + adjacency.sum(dim=2)
        mean = total / count.clamp_min(1.0).unsqueeze(-1)
        return torch.relu(self.update(torch.cat([h, mean], dim=-1)))


class PoseDecoder(nn.Module):
    """MLP to a unit quaternion (w first, w >= 0; the raw output is offset by the identity before normalising)
    and a translation: (..., in_dim) -> ((..., 4), (..., 3))."""

    def __init__(self, in_dim: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(inplace=True))
        self.quat = nn.Linear(hidden, 4)
        self.trans = nn.Linear(hidden, 3)
        nn.init.zeros_(self.quat.bias)
        nn.init.zeros_(self.trans.bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.mlp(x)
        quat = quat_normalize(self.quat(h) + h.new_tensor(IDENTITY_QUAT))
        quat = torch.where(quat[..., :1] < 0, -quat, quat)  # the project's written form: w >= 0
        return quat, self.trans(h)


class AssemblyGraph(nn.Module):
    """Node features (B, P, in_dim) -> two phases of poses ``[(quat1, trans1), (quat2, trans2)]``."""

    def __init__(self, in_dim: int, hidden: int, iterations: int = 2, knn: int = 5):
        super().__init__()
        self.knn = knn
        self.embed = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(inplace=True))
        self.phase1 = nn.ModuleList(EdgeConv(hidden) for _ in range(iterations))
        self.phase2 = nn.ModuleList(EdgeConv(hidden) for _ in range(iterations))
        self.decode1 = PoseDecoder(2 * hidden, hidden)
        self.decode2 = PoseDecoder(3 * hidden, hidden)

    def forward(self, x: torch.Tensor, classes: torch.Tensor, valid: torch.Tensor):
        f0 = self.embed(x)
        equivalent = equivalence_adjacency(classes, valid)
        h = f0
        for conv in self.phase1:
            h = conv(h, [(equivalent, 0.0)])
        f1 = h
        quat1, trans1 = self.decode1(torch.cat([f0, f1], dim=-1))
        neighbours = knn_adjacency(trans1.detach(), valid, self.knn)
        for conv in self.phase2:
            h = conv(h, [(equivalent, 0.0), (neighbours, 1.0)])
        f2 = h
        quat2, trans2 = self.decode2(torch.cat([f0, f1, f2], dim=-1))
        return [(quat1, trans1), (quat2, trans2)]
