"""U-Net baseline (the paper's cross-backbone setting: four stages, initial width 32)."""

from __future__ import annotations

import torch
from torch import nn

from .common import check_input, crop_to, pad_to_multiple
from .registry import register_backbone

__all__ = ["UNet", "ConvBlock"]


class ConvBlock(nn.Sequential):
    """Two 3x3 convolutions, each followed by an activation (optionally with BatchNorm)."""

    def __init__(self, in_ch: int, out_ch: int, norm: bool = False, act: str = "relu") -> None:
        layers: list[nn.Module] = []
        for a, b in ((in_ch, out_ch), (out_ch, out_ch)):
            layers.append(nn.Conv2d(a, b, 3, padding=1, bias=not norm))
            if norm:
                layers.append(nn.BatchNorm2d(b))
            layers.append(nn.LeakyReLU(0.2, inplace=True) if act == "lrelu" else nn.ReLU(inplace=True))
        super().__init__(*layers)


@register_backbone("unet")
class UNet(nn.Module):
    """Classic U-Net: ``stages`` encoder stages of two 3x3 convs (widths width * 2**i), each followed by
    2x2 max-pooling, a bottleneck at width * 2**stages, and a mirrored decoder (2x2 transposed-conv
    upsampling, skip concatenation, two 3x3 convs). A zero-initialised 1x1 head predicts the residual
    added to the noisy depth (channel 0), so the network is the identity at initialisation.

    Inputs of any size are padded (reflect) to a multiple of 2**stages and cropped back.
    """

    def __init__(
        self,
        in_channels: int = 1,
        width: int = 32,
        stages: int = 4,
        norm: bool = False,
        residual: bool = True,
    ) -> None:
        super().__init__()
        if in_channels < 1:
            raise ValueError(f"UNet: in_channels must be >= 1, got {in_channels}")
        if stages < 1 or width < 1:
            raise ValueError(f"UNet: stages and width must be >= 1, got stages={stages}, width={width}")
        self.in_channels = in_channels
        self.residual = residual
        self.multiple = 2**stages
        widths = [width * 2**i for i in range(stages + 1)]
        self.enc = nn.ModuleList()
        prev = in_channels
        for w in widths[:-1]:
            self.enc.append(ConvBlock(prev, w, norm))
            prev = w
        self.pool = nn.MaxPool2d(2)
        self.bottleneck = ConvBlock(widths[-2], widths[-1], norm)
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for i in reversed(range(stages)):
            self.up.append(nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2))
            self.dec.append(ConvBlock(2 * widths[i], widths[i], norm))
        self.head = nn.Conv2d(widths[0], 1, 1)
        if residual:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(x, self.in_channels, "UNet")
        xp, size = pad_to_multiple(x, self.multiple)
        skips = []
        h = xp
        for block in self.enc:
            h = block(h)
            skips.append(h)
            h = self.pool(h)
        h = self.bottleneck(h)
        for up, dec, skip in zip(self.up, self.dec, reversed(skips)):
            h = dec(torch.cat([up(h), skip], dim=1))
        out = self.head(h)
        if self.residual:
            out = out + xp[:, :1]
        return crop_to(out, size)
