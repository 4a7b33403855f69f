"""ToF-KPN-style baseline (Qiu et al., ICCV 2019; depth(+amplitude) variant): a U-Net trunk predicts, per
pixel, a 3x3 kernel w and a bias b; w is L1-normalised (w / (sum |w| + 1e-6)) and the output is
sum over the 3x3 window of (depth + b) * w, gathered with ``F.unfold`` (replicate-padded borders)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .common import check_input, crop_to, pad_to_multiple
from .deeptof import REDUCED_CHANNELS, UNetTrunk
from .registry import register_backbone

__all__ = ["ToFKPN", "apply_kernels"]

KERNEL = 3
EPS = 1e-6


def apply_kernels(depth: torch.Tensor, weights: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Per-pixel 3x3 filtering: depth (B,1,H,W), raw weights (B,9,H,W), bias (B,1,H,W) -> (B,1,H,W).

    Weights are L1-normalised, w / (sum_j |w_j| + 1e-6); out = sum_j (depth + bias)_j * w_j over the window
    (window order of ``F.unfold``: row-major, centre = index 4). The bias is per pixel, added before
    gathering, so the window reads the biased depth of its neighbours.
    """
    b, _, h, w = depth.shape
    weights = weights / (weights.abs().sum(dim=1, keepdim=True) + EPS)
    src = F.pad(depth + bias, (1, 1, 1, 1), mode="replicate")
    patches = F.unfold(src, KERNEL).view(b, KERNEL * KERNEL, h, w)
    return (patches * weights).sum(dim=1, keepdim=True)


@register_backbone("tofkpn")
class ToFKPN(nn.Module):
    """Kernel-prediction network. The head is initialised to the identity kernel (centre weight 1, bias 0),
    so the network starts as (almost exactly: factor 1/(1+1e-6)) the identity on the depth channel."""

    def __init__(self, in_channels: int = 1, channels: Sequence[int] = REDUCED_CHANNELS) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.trunk = UNetTrunk(in_channels, channels)
        self.multiple = self.trunk.multiple
        self.head = nn.Conv2d(self.trunk.out_channels, KERNEL * KERNEL + 1, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        with torch.no_grad():
            self.head.bias.zero_()
            self.head.bias[KERNEL * KERNEL // 2] = 1.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(x, self.in_channels, "ToFKPN")
        xp, size = pad_to_multiple(x, self.multiple)
        out = self.head(self.trunk(xp))
        pred = apply_kernels(xp[:, :1], out[:, : KERNEL * KERNEL], out[:, KERNEL * KERNEL :])
        return crop_to(pred, size)
