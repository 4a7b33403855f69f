"""DeepToF-style baseline (Marco et al. 2017, as re-implemented by later iToF papers): an encoder-decoder
CNN (U-Net trunk) whose 3x3 head outputs the depth directly (no residual connection)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from .common import check_input, crop_to, pad_to_multiple
from .registry import register_backbone

__all__ = ["UNetTrunk", "DeepToF", "PAPER_CHANNELS", "REDUCED_CHANNELS"]

#: Channels of the public re-implementations (~2.7 M parameters with this trunk).
PAPER_CHANNELS = (64, 64, 128, 128, 128, 128, 256, 256)
#: CPU-friendly default (about a quarter of the parameters).
REDUCED_CHANNELS = (32, 32, 64, 64, 64, 64, 128, 128)


def _conv(a: int, b: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(a, b, 3, padding=1), nn.ReLU(inplace=True))


class UNetTrunk(nn.Module):
    """U-Net trunk with channel list ``channels`` = (c0, c1, ..., c_{2n-1}): level i has two 3x3 convs
    (c_{2i}, c_{2i+1}), 2x2 max-pooling between levels, mirrored decoder with transposed-conv upsampling
    and skip concatenation. Output: c0 channels at full resolution. Needs sizes divisible by 2**(n-1)."""

    def __init__(self, in_channels: int, channels: Sequence[int]) -> None:
        super().__init__()
        channels = [int(c) for c in channels]
        if len(channels) < 2 or len(channels) % 2 or min(channels) < 1:
            raise ValueError(f"UNetTrunk: channels must be an even-length list of positive ints, got {channels}")
        levels = len(channels) // 2
        self.multiple = 2 ** (levels - 1)
        self.out_channels = channels[0]
        self.enc = nn.ModuleList()
        prev = in_channels
        for i in range(levels):
            self.enc.append(nn.Sequential(_conv(prev, channels[2 * i]), _conv(channels[2 * i], channels[2 * i + 1])))
            prev = channels[2 * i + 1]
        self.pool = nn.MaxPool2d(2)
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for i in reversed(range(levels - 1)):
            skip = channels[2 * i + 1]
            self.up.append(nn.ConvTranspose2d(prev, skip, 2, stride=2))
            self.dec.append(nn.Sequential(_conv(2 * skip, channels[2 * i]), _conv(channels[2 * i], channels[2 * i])))
            prev = channels[2 * i]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        h = x
        for i, enc in enumerate(self.enc):
            if i:
                h = self.pool(h)
            h = enc(h)
            skips.append(h)
        skips.pop()
        for up, dec in zip(self.up, self.dec):
            h = dec(torch.cat([up(h), skips.pop()], dim=1))
        return h


@register_backbone("deeptof")
class DeepToF(nn.Module):
    """Encoder-decoder CNN predicting depth directly. ``channels``: trunk channel list (default reduced;
    ``PAPER_CHANNELS`` = [64, 64, 128, 128, 128, 128, 256, 256] is the re-implementation size)."""

    def __init__(self, in_channels: int = 1, channels: Sequence[int] = REDUCED_CHANNELS) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.trunk = UNetTrunk(in_channels, channels)
        self.multiple = self.trunk.multiple
        self.head = nn.Conv2d(self.trunk.out_channels, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(x, self.in_channels, "DeepToF")
        xp, size = pad_to_multiple(x, self.multiple)
        return crop_to(self.head(self.trunk(xp)), size)
