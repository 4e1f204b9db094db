"""Part-instance segmentation: a U-Net conditioned on each part's 3D feature.

The image goes through a ResNet-18-style encoder once (down to a 512x7x7 bottleneck for a 224 input at width
1). For every valid part, its f_3d is tiled over the bottleneck and concatenated to it, and a decoder with skip
links to every encoder scale (and the input image at full resolution) produces one mask logit map per part.
A constant zero logit stands for the background; a softmax over the object's part logits and the background
gives each pixel's distribution over "part i" and "background", so a pixel belongs to at most one part.

Each convolution over a concatenation ``[per-part tensor; per-image tensor]`` is written as the sum of two
convolutions (it is linear), the per-image half computed once per image instead of once per part: the same
function as the literal concatenation, several times cheaper with 20 parts.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from perception.config import ModelConfig
from perception.model.padding import owner, pack, unpack
from perception.model.pointnet import PartEncoder
from perception.model.resnet import ResNetEncoder, channels, prepare_image


class SplitConv(nn.Module):
    """3x3 convolution of ``[x; skip[index]]`` (channel concatenation), batch norm and ReLU, with the skip half
    computed once per image."""

    def __init__(self, cin: int, cskip: int, cout: int, kernel: int = 3, cond_dim: int = 0):
        super().__init__()
        self.conv_x = nn.Conv2d(cin, cout, kernel, 1, kernel // 2, bias=False)
        self.conv_skip = nn.Conv2d(cskip, cout, kernel, 1, kernel // 2, bias=False) if cskip else None
        # the part's conditioning vector tiled over the map and concatenated: constant per part, so its
        # convolution is a per-part bias (exact away from the zero-padded border)
        self.cond = nn.Linear(cond_dim, cout, bias=False) if cond_dim else None
        if self.cond is not None:  # starts as the paper's decoder: weights trained without it can be fine-tuned
            nn.init.zeros_(self.cond.weight)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None, index: torch.Tensor,
                cond: torch.Tensor | None = None) -> torch.Tensor:
        y = self.conv_x(x)
        if self.conv_skip is not None:
            y = y + self.conv_skip(skip)[index]
        if self.cond is not None:
            y = y + self.cond(cond)[:, :, None, None]
        return F.relu(self.bn(y), inplace=True)


class UpBlock(nn.Module):
    """Bilinear upsampling to the skip's size, conv over [up; skip], conv."""

    def __init__(self, cin: int, cskip: int, cout: int, cond_dim: int = 0):
        super().__init__()
        self.fuse = SplitConv(cin, cskip, cout, cond_dim=cond_dim)
        self.conv = nn.Sequential(nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout),
                                  nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor, skip: torch.Tensor, index: torch.Tensor,
                cond: torch.Tensor | None = None) -> torch.Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.conv(self.fuse(x, skip, index, cond))


class ConditionalDecoder(nn.Module):
    """Decoder of one mask per (image, part) pair from the encoder pyramid and the part's conditioning vector."""

    def __init__(self, encoder_channels: list[int], cond_dim: int, width: float, every_scale: bool = False):
        super().__init__()
        widths = [channels(width, base) for base in (256, 128, 64, 32, 32)]
        bottleneck = encoder_channels[-1]
        # bottleneck fusion: a 1x1 convolution of [bottleneck; tiled f_3d] = per-image map + per-part vector
        self.bottleneck_image = nn.Conv2d(bottleneck, widths[0], 1, bias=False)
        self.bottleneck_part = nn.Linear(cond_dim, widths[0], bias=False)
        self.bottleneck_bn = nn.BatchNorm2d(widths[0])
        self.bottleneck_conv = nn.Sequential(nn.Conv2d(widths[0], widths[0], 3, 1, 1, bias=False),
                                             nn.BatchNorm2d(widths[0]), nn.ReLU(inplace=True))
        skips = encoder_channels[-2::-1] + [3]  # stage 3, 2, 1, stem, then the image itself
        ups, previous = [], widths[0]
        for skip, cout in zip(skips, [*widths[1:], widths[-1]]):
            ups.append(UpBlock(previous, skip, cout, cond_dim if every_scale else 0))
            previous = cout
        self.ups = nn.ModuleList(ups)
        self.out = nn.Conv2d(previous, 1, 1)

    def forward(self, pyramid: list[torch.Tensor], cond: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """pyramid: [image, stem, stage1..stage4] per image (B, ...); cond: (M, C) per part; index: (M,) the
        image of each part. Returns (M, H, W) logits."""
        x = self.bottleneck_image(pyramid[-1])[index] + self.bottleneck_part(cond)[:, :, None, None]
        x = self.bottleneck_conv(F.relu(self.bottleneck_bn(x), inplace=True))
        for up, skip in zip(self.ups, pyramid[-2::-1]):
            x = up(x, skip, index, cond)
        return self.out(x).squeeze(1)


class SegmentationNet(nn.Module):
    """``forward(batch)`` -> ``{"mask_logits": (B, P, S, S) (-inf in padded slots), "masks": (B, P, S, S)
    softmax probabilities, "background": (B, S, S)}`` with S = ``model.image_size``."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.size = config.image_size
        self.encoder = ResNetEncoder(3, config.resnet_width, config.resnet_blocks)
        self.parts = PartEncoder(config)
        self.decoder = ConditionalDecoder(self.encoder.channels, self.parts.out_dim, config.decoder_width,
                                          config.condition_every_scale)

    def forward(self, batch: dict) -> dict:
        valid = batch["valid"]
        image = prepare_image(batch["image"], self.size)
        pyramid = [image, *self.encoder(image)]
        _, f_3d = self.parts(batch["points"], batch["instance_onehot"], valid)
        logits = self.decoder(pyramid, pack(f_3d, valid), owner(valid))
        logits = unpack(logits, valid, fill=float("-inf"))  # (B, P, S, S)
        background = logits.new_zeros(logits.shape[0], 1, *logits.shape[2:])
        probs = torch.softmax(torch.cat([logits, background], dim=1), dim=1)
        return {"mask_logits": logits, "masks": probs[:, :-1], "background": probs[:, -1]}
