"""The paper's baselines, trained on the same data with the same pose losses (no segmentation).

- B-GRU: a GRU whose hidden state starts from the image feature; at step t it reads the image feature and the
  PointNet feature of part t (zeros past the last part) and emits pose proposal t. Of its P_max proposals, the
  first n (one per part, in input order) are the predictions; the losses then match them to the parts within
  equivalence classes, as for every model.
- B-InsOneHot: a per-part MLP from [image feature; part geometry feature; instance one-hot] to a pose.
- B-Global: B-InsOneHot plus the max-pooled global 3D feature, i.e. the MLP reads [image feature; f_3d].

Every model returns ``{"poses": [(quat, trans)], "quat": ..., "trans": ...}``.
"""

from __future__ import annotations

import torch
from torch import nn

from perception.config import ModelConfig
from perception.model.graph import PoseDecoder
from perception.model.pointnet import PartEncoder, PartGeometry
from perception.model.resnet import GlobalImageEncoder, prepare_image


class _Baseline(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        self.size = config.image_size
        self.image_encoder = GlobalImageEncoder(3, config.resnet_width, config.resnet_blocks, config.image_feature)

    def image_feature(self, batch: dict) -> torch.Tensor:
        return self.image_encoder(prepare_image(batch["image"], self.size))

    @staticmethod
    def _output(quat: torch.Tensor, trans: torch.Tensor) -> dict:
        return {"poses": [(quat, trans)], "quat": quat, "trans": trans}


def _mlp_decoder(in_dim: int, hidden: int) -> nn.Module:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden),
                         nn.ReLU(inplace=True), PoseDecoder(hidden, hidden))


class BInsOneHot(_Baseline):
    kind = "b_insonehot"

    def __init__(self, config: ModelConfig):
        super().__init__(config)
        self.geometry = PartGeometry(config)
        self.decoder = _mlp_decoder(config.image_feature + config.point_feature + config.max_parts, config.hidden)

    def forward(self, batch: dict) -> dict:
        valid = batch["valid"]
        image = self.image_feature(batch).unsqueeze(1).expand(-1, valid.shape[1], -1)
        f_geo = self.geometry(batch["points"], valid)
        return self._output(*self.decoder(torch.cat([image, f_geo, batch["instance_onehot"]], dim=-1)))


class BGlobal(_Baseline):
    kind = "b_global"

    def __init__(self, config: ModelConfig):
        super().__init__(config)
        self.parts = PartEncoder(config)
        self.decoder = _mlp_decoder(config.image_feature + self.parts.out_dim, config.hidden)

    def forward(self, batch: dict) -> dict:
        valid = batch["valid"]
        image = self.image_feature(batch).unsqueeze(1).expand(-1, valid.shape[1], -1)
        _, f_3d = self.parts(batch["points"], batch["instance_onehot"], valid)
        return self._output(*self.decoder(torch.cat([image, f_3d], dim=-1)))


class BGRU(_Baseline):
    kind = "b_gru"

    def __init__(self, config: ModelConfig):
        super().__init__(config)
        self.geometry = PartGeometry(config)
        self.init_hidden = nn.Sequential(nn.Linear(config.image_feature, config.gru_hidden), nn.Tanh())
        self.gru = nn.GRU(config.image_feature + config.point_feature, config.gru_hidden, batch_first=True)
        self.decoder = PoseDecoder(config.gru_hidden, config.hidden)

    def forward(self, batch: dict) -> dict:
        valid = batch["valid"]
        image = self.image_feature(batch)
        f_geo = self.geometry(batch["points"], valid)  # zeros past the last part
        steps = torch.cat([image.unsqueeze(1).expand(-1, valid.shape[1], -1), f_geo], dim=-1)
        hidden, _ = self.gru(steps, self.init_hidden(image).unsqueeze(0))  # causal: step t sees parts <= t
        return self._output(*self.decoder(hidden))
