"""Spatial-Channel Refinement (SCR) and the squeeze-and-excitation (SE) module used in its ablation.

The paper describes SCR only in words (Sec. III-D, Fig. "SCR module"): "a global branch and a local branch
interact in a coarse-to-fine manner to jointly refine channel and spatial responses; the global branch
provides channel-level context, while the local branch preserves spatially detailed responses".
Our reading, in formulas (X is the DWConv output, (B, C, H, W)):

    g   = sigmoid(W2 GELU(W1 [avgpool(X), maxpool(X)]))            global branch: channel context (B, C, 1, 1)
    Xc  = X * g                                                      coarse: channel-recalibrated features
    s   = sigmoid(PW(GELU(DW3x3(Xc))))                               local branch: per-pixel, per-channel gate
    SCR(X) = Xc * s                                                  fine: spatial refinement of the coarse result

The local branch sees the globally recalibrated features (coarse to fine), and its gate is spatial *and*
per channel, which is what distinguishes it from SE (channel-only recalibration: SE(X) = X * g with the
avg-pool MLP only).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .common import eager_inference, mean_hw

__all__ = ["SCR", "SqueezeExcitation", "factorable"]


def factorable(x: torch.Tensor) -> bool:
    """True where SCR and SE can hand over their output as (T, g) (:meth:`SCR.factored`): one image in an eager
    forward without a gradient or autocast."""
    return x.shape[0] == 1 and eager_inference() and not torch.is_autocast_enabled(x.device.type)


class SqueezeExcitation(nn.Module):
    """SE: X * sigmoid(W2 ReLU(W1 avgpool(X))) (Hu et al.)."""

    def __init__(self, channels: int, reduction: int = 4) -> None:
        super().__init__()
        hidden = max(4, channels // reduction)
        self.fc1 = nn.Conv2d(channels, hidden, 1)
        self.fc2 = nn.Conv2d(hidden, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self._channel_gate(x)

    def _channel_gate(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.fc2(F.relu(self.fc1(mean_hw(x)))))

    def factored(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SE(X) as (X, g), SE(X) = X * g (see :meth:`SCR.factored`): no X * g tensor."""
        return x, self._channel_gate(x)


class SCR(nn.Module):
    """Spatial-Channel Refinement: global channel context, then a local spatial-channel gate (see module doc)."""

    def __init__(self, channels: int, reduction: int = 4, kernel_size: int = 3) -> None:
        super().__init__()
        hidden = max(4, channels // reduction)
        self.fc1 = nn.Conv2d(2 * channels, hidden, 1)
        self.fc2 = nn.Conv2d(hidden, channels, 1)
        self.local_dw = nn.Conv2d(channels, channels, kernel_size, padding=kernel_size // 2, groups=channels)
        self.local_pw = nn.Conv2d(channels, channels, 1)

    def _channel_gate(self, x: torch.Tensor) -> torch.Tensor:
        """The global branch: g (B, C, 1, 1)."""
        pooled = torch.cat([mean_hw(x), x.amax(dim=(2, 3), keepdim=True)], dim=1)
        return torch.sigmoid(self.fc2(F.gelu(self.fc1(pooled))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = self._channel_gate(x)
        if factorable(x):
            return self._refine_one_image(x, g).mul_(g)
        xc = x * g
        s = torch.sigmoid(self.local_pw(F.gelu(self.local_dw(xc))))
        return xc * s

    def factored(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SCR(X) as (T, g) with SCR(X) = T * g, g the channel gate (1, C, 1, 1), for one image where
        :func:`factorable`: a caller that multiplies the result by a matrix folds g into it (one pass fewer)."""
        g = self._channel_gate(x)
        return self._refine_one_image(x, g), g

    def _refine_one_image(self, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """:meth:`forward`'s local branch for one image in an eager forward without a gradient or autocast, before
        its channel gate, equal to rounding with passes fewer: the depthwise convolution of X * g is the
        convolution of X with each channel's kernel scaled by g (no X * g tensor), and the spatial gate is applied
        in place; returns s * X (SCR(X) = s * X * g)."""
        dw = self.local_dw
        kernel = dw.weight * g.view(-1, 1, 1, 1).to(dw.weight.dtype)
        s = F.conv2d(x, kernel, dw.bias, dw.stride, dw.padding, dw.dilation, dw.groups)
        s = torch.sigmoid_(self.local_pw(F.gelu(s)))
        return s.mul_(x)
