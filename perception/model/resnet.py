"""ResNet-18-style image encoder written in torch (no torchvision), with a channel-width multiplier.

Layout as ResNet-18: a 7x7 stride-2 stem, a 3x3 stride-2 max-pool, four stages of basic blocks (2, 2, 2, 2 by
default) with 64, 128, 256, 512 channels times ``width``; the last three stages halve the resolution. A
224x224 input gives a 512x7x7 bottleneck at width 1.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def prepare_image(image: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 (B, 3, H, W) (or float in [0, 1]) -> float (B, 3, size, size), resized (antialiased) and
    standardised with the ImageNet statistics."""
    x = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    if x.shape[-1] != size or x.shape[-2] != size:
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    mean = x.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = x.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x - mean) / std


def resize_masks(masks: torch.Tensor, size: int) -> torch.Tensor:
    """Resize (B, C, H, W) soft masks by area averaging (down) or bilinear interpolation (up)."""
    if masks.shape[-1] == size and masks.shape[-2] == size:
        return masks
    mode = "area" if masks.shape[-1] > size else "bilinear"
    return F.interpolate(masks, size=(size, size), mode=mode, **({} if mode == "area" else {"align_corners": False}))


def channels(width: float, base: int) -> int:
    return max(4, int(round(base * width)))


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = nn.Identity()
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        return F.relu(self.bn2(self.conv2(y)) + self.shortcut(x), inplace=True)


class ResNetEncoder(nn.Module):
    """``forward(x)`` returns the feature maps of every scale, finest first:
    [stem (H/2), stage 1 (H/4), stage 2 (H/8), stage 3 (H/16), stage 4 (H/32)]; ``channels`` lists their depths.

    ``extra_channels`` > 0 makes the input ``[image (3 channels); extra]``; the stem convolution is then held as
    two convolutions, one per channel group, whose sum is the convolution of the concatenation. That lets
    :meth:`forward_split` encode many (image, extra) pairs that share images while convolving each image once.
    """

    def __init__(self, in_channels: int = 3, width: float = 1.0, blocks: tuple[int, ...] = (2, 2, 2, 2),
                 extra_channels: int = 0):
        super().__init__()
        widths = [channels(width, base) for base in (64, 128, 256, 512)]
        self.in_channels = in_channels
        self.stem_conv = nn.Conv2d(in_channels, widths[0], 7, 2, 3, bias=False)
        self.stem_extra = nn.Conv2d(extra_channels, widths[0], 7, 2, 3, bias=False) if extra_channels else None
        self.stem_bn = nn.BatchNorm2d(widths[0])
        stages = []
        previous = widths[0]
        for index, (count, cout) in enumerate(zip(blocks, widths)):
            layers = [BasicBlock(previous, cout, 1 if index == 0 else 2)]
            layers += [BasicBlock(cout, cout, 1) for _ in range(count - 1)]
            stages.append(nn.Sequential(*layers))
            previous = cout
        self.stages = nn.ModuleList(stages)
        self.channels = [widths[0], *widths]
        self.out_channels = widths[-1]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        if self.stem_extra is None:
            return self.from_stem(self.stem_conv(x))
        k = self.in_channels
        return self.from_stem(self.stem_conv(x[:, :k]) + self.stem_extra(x[:, k:]))

    def forward_split(self, shared: torch.Tensor, index: torch.Tensor, own: torch.Tensor) -> list[torch.Tensor]:
        """The encoding of ``[shared[index]; own]`` (M inputs; ``shared``: B images, ``index``: (M,) which image
        each input uses, ``own``: (M, extra, H, W)), with each shared image convolved once: the same as
        ``forward(torch.cat([shared[index], own], 1))``."""
        return self.from_stem(self.stem_conv(shared)[index] + self.stem_extra(own))

    def from_stem(self, stem: torch.Tensor) -> list[torch.Tensor]:
        x = F.relu(self.stem_bn(stem), inplace=True)
        features = [x]
        x = F.max_pool2d(x, 3, 2, 1)
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        return features


class GlobalImageEncoder(nn.Module):
    """ResNet encoder, global average pool and a linear layer with batch norm and ReLU: (B, C, H, W) -> (B, F)."""

    def __init__(self, in_channels: int, width: float, blocks: tuple[int, ...], out_dim: int,
                 extra_channels: int = 0):
        super().__init__()
        self.resnet = ResNetEncoder(in_channels, width, blocks, extra_channels)
        self.head = nn.Sequential(nn.Linear(self.resnet.out_channels, out_dim, bias=False), nn.BatchNorm1d(out_dim),
                                  nn.ReLU(inplace=True))
        self.out_dim = out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.resnet(x)[-1].mean(dim=(2, 3)))

    def forward_split(self, shared: torch.Tensor, index: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        return self.head(self.resnet.forward_split(shared, index, own)[-1].mean(dim=(2, 3)))
