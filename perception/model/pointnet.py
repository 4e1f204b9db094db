"""Part features: a PointNet encoder of each part cloud and the paper's context-aware 3D part feature

    f_3d = [SLP1([f_geo; f_ins]); SLP2(max over the object's parts of SLP1([f_geo; f_ins]))]

where f_geo is the PointNet feature (F1) and f_ins the instance one-hot (P_max) that tells equivalent parts apart.
"""

from __future__ import annotations

import torch
from torch import nn

from perception.config import ModelConfig
from perception.model.padding import masked_max, pack, unpack


class PointNet(nn.Module):
    """Shared per-point MLP (1x1 convolutions with batch norm) and a max-pool: (M, N, 3) -> (M, out_dim)."""

    def __init__(self, widths: tuple[int, ...], out_dim: int):
        super().__init__()
        layers: list[nn.Module] = []
        previous = 3
        for width in (*widths, out_dim):
            layers += [nn.Conv1d(previous, width, 1, bias=False), nn.BatchNorm1d(width), nn.ReLU(inplace=True)]
            previous = width
        self.points = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(out_dim, out_dim, bias=False), nn.BatchNorm1d(out_dim),
                                  nn.ReLU(inplace=True))
        self.out_dim = out_dim

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.head(self.points(points.transpose(1, 2)).max(dim=2).values)


class PartGeometry(nn.Module):
    """f_geo of every valid part: (B, P, N, 3) -> (B, P, F1), zeros in padded slots. Only the first
    ``encoder_points`` points of each cloud are used (the clouds are in farthest-point order, so any prefix is
    evenly spread)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.points = config.encoder_points
        self.pointnet = PointNet(config.pointnet_widths, config.point_feature)
        self.out_dim = config.point_feature

    def forward(self, points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        return unpack(self.pointnet(pack(points[:, :, : self.points], valid)), valid)


class PartEncoder(nn.Module):
    """Per-part features of a padded part set: ``forward`` returns ``(f_geo, f_3d)``, (B, P, F1) and
    (B, P, 2 * F2), zeros in padded slots."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.geometry = PartGeometry(config)
        self.slp1 = nn.Sequential(nn.Linear(config.point_feature + config.max_parts, config.part_feature),
                                  nn.ReLU(inplace=True))
        self.slp2 = nn.Sequential(nn.Linear(config.part_feature, config.part_feature), nn.ReLU(inplace=True))
        self.geo_dim = config.point_feature
        self.out_dim = 2 * config.part_feature

    def forward(self, points: torch.Tensor, onehot: torch.Tensor, valid: torch.Tensor):
        f_geo = self.geometry(points, valid)
        local = unpack(self.slp1(torch.cat([pack(f_geo, valid), pack(onehot, valid)], dim=-1)), valid)
        context = self.slp2(masked_max(local, valid))  # (B, F2)
        f_3d = torch.cat([local, context.unsqueeze(1).expand_as(local)], dim=-1) * valid.unsqueeze(-1)
        return f_geo, f_3d
