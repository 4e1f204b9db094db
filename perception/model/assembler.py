"""The full model of the paper: part-instance segmentation, then per-part pose by graph reasoning.

Pose network, per part: the image feature (ResNet-18-style encoder of the image, global average pool), the mask
feature (a second ResNet-18-style encoder of the 4-channel input [image; predicted soft mask of that part], so
the mask is read in the context of the pixels it covers) and the part's own f_3d (its own PointNet and SLPs,
separate from the segmentation network's), concatenated and fed to :class:`AssemblyGraph`.

Training is in two stages (:mod:`perception.train`): the segmentation network first, then the pose network on
the masks the (then frozen) segmentation network predicts.
"""

from __future__ import annotations

import torch
from torch import nn

from perception.config import ModelConfig
from perception.model.graph import AssemblyGraph
from perception.model.padding import owner, pack, unpack
from perception.model.pointnet import PartEncoder
from perception.model.resnet import GlobalImageEncoder, prepare_image, resize_masks
from perception.model.unet import SegmentationNet


class PoseNet(nn.Module):
    """``forward(batch, masks)`` -> ``{"poses": [(quat1, trans1), (quat2, trans2)]}``, (B, P, 4) / (B, P, 3);
    ``masks``: (B, P, S, S) soft part masks."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.size = config.image_size
        self.image_encoder = GlobalImageEncoder(3, config.resnet_width, config.resnet_blocks, config.image_feature)
        self.mask_encoder = GlobalImageEncoder(3, config.mask_encoder_width, config.resnet_blocks,
                                               config.image_feature, extra_channels=1)
        self.parts = PartEncoder(config)
        in_dim = 2 * config.image_feature + self.parts.out_dim
        self.graph = AssemblyGraph(in_dim, config.hidden, config.graph_iterations, config.knn)

    def forward(self, batch: dict, masks: torch.Tensor) -> dict:
        valid = batch["valid"]
        image = prepare_image(batch["image"], self.size)
        image_feature = self.image_encoder(image)  # (B, F)
        part_masks = resize_masks(masks, self.size)
        mask_feature = unpack(self.mask_encoder.forward_split(image, owner(valid), pack(part_masks, valid)
                                                              .unsqueeze(1)), valid)
        _, f_3d = self.parts(batch["points"], batch["instance_onehot"], valid)
        nodes = torch.cat([image_feature.unsqueeze(1).expand(-1, valid.shape[1], -1), mask_feature, f_3d], dim=-1)
        return {"poses": self.graph(nodes, batch["classes"], valid)}


class AssemblyNet(nn.Module):
    """Segmentation + pose. ``forward(batch)`` returns the segmentation outputs (``masks``, ``background``,
    ``mask_logits``) and ``poses`` (phase 1 and phase 2); ``quat``/``trans`` are the final (phase-2) poses."""

    kind = "ours"

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.segmentation = SegmentationNet(config)
        self.pose = PoseNet(config)

    def forward(self, batch: dict, masks: torch.Tensor | None = None) -> dict:
        out = self.segmentation(batch) if masks is None else {"masks": masks}
        out.update(self.pose(batch, out["masks"]))
        out["quat"], out["trans"] = out["poses"][-1]
        return out
