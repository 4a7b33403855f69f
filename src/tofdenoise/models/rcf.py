"""RCF-style baseline: our reading of "Recurrent cross-modality fusion for time-of-flight depth denoising"
(Dong et al., IEEE TCI 2024), the strongest baseline of the paper's Table 1.

RCF's network code is not public; its abstract names depth and amplitude inputs, a GRU-based network that
refines a depth correction over several steps, a global restoration module and a local update module fusing
depth and amplitude features, and the prior that the error is an additive combination of geometric
information of neighbouring pixels (``../shared/notes/baselines.md``). Everything below beyond that is our
assumption (docs/models.md#rcf-our-reading), RAFT-style::

    f_d = E_d(depth), f_a = E_a(amplitude)            modality encoders: two 3x3 conv + ReLU each, width C
    f   = ReLU(W [f_d * sigmoid(G f_a), f_a])          local fusion: a per-pixel amplitude gate on depth features
    ctx = GlobalRestoration(f)                         ``global_levels`` stride-2 stages, channel attention from
                                                       global pooling (global fusion), top-down sum back to f
    h_0 = tanh(P_h ctx), inp = ReLU(P_x ctx), r_0 = 0
    for k = 1..K:                                      local update module (weights shared over the steps)
        D_{k-1} = depth + r_{k-1}
        g_k   = neighbour differences D_{k-1}(p + j) - D_{k-1}(p), 3x3 window at dilations 1 and 2 (16 maps)
        m_k   = ReLU(M [g_k, r_{k-1}, amplitude])
        h_k   = ConvGRU(h_{k-1}, [inp, m_k])
        w, b  = Head(h_k)                               last conv zero-initialised
        r_k   = r_{k-1} + sum_j tanh(w_j) / 16 * g_k,j + b     additive combination of neighbour geometry
        D_k   = depth + r_k                            one prediction per step

In training mode the forward returns ``[D_1, ..., D_K]`` (``deep_supervision``; ``DepthRestorer.training_loss``
weights the step losses by ``step_loss_weights`` = gamma^(K-k), normalised); in eval mode only ``D_K``. The
zero-initialised head makes every step exactly the identity at initialisation.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .common import check_input, crop_to, mean_hw, pad_to_multiple
from .registry import register_backbone

__all__ = ["RCF", "ConvGRU", "GlobalRestoration", "neighbour_differences", "NEIGHBOURS", "DILATIONS"]

#: offsets (dy, dx) of the 8 neighbours of a 3x3 window, row-major without the centre
NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
#: dilations of the neighbour windows the update combines
DILATIONS = (1, 2)


def neighbour_differences(depth: torch.Tensor, dilation: int = 1) -> torch.Tensor:
    """(B, 1, H, W) -> (B, 8, H, W): ``depth(p + dilation * j) - depth(p)`` for the 8 neighbours j of
    :data:`NEIGHBOURS` (replicate-padded border, so differences across the border are 0)."""
    if depth.dim() != 4 or depth.shape[1] != 1:
        raise ValueError(f"neighbour_differences: expected a (B, 1, H, W) tensor, got {tuple(depth.shape)}")
    d = int(dilation)
    h, w = depth.shape[-2:]
    padded = F.pad(depth, (d, d, d, d), mode="replicate")
    shifted = [padded[..., d + dy * d : d + dy * d + h, d + dx * d : d + dx * d + w] for dy, dx in NEIGHBOURS]
    return torch.cat(shifted, dim=1) - depth


def _conv_relu(a: int, b: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(a, b, 3, stride=stride, padding=1), nn.ReLU(inplace=True))


class ConvGRU(nn.Module):
    """Convolutional GRU cell (3x3): z, r = sigmoid(W_zr [h, x]); q = tanh(W_q [r * h, x]); h' = (1 - z) h + z q."""

    def __init__(self, hidden: int, input_dim: int) -> None:
        super().__init__()
        self.hidden = hidden
        self.zr = nn.Conv2d(hidden + input_dim, 2 * hidden, 3, padding=1)
        self.q = nn.Conv2d(hidden + input_dim, hidden, 3, padding=1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        z, r = torch.sigmoid(self.zr(torch.cat([h, x], dim=1))).chunk(2, dim=1)
        q = torch.tanh(self.q(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q


class GlobalRestoration(nn.Module):
    """Global context of the fused features (B, C, H, W) -> (B, C, H, W), H and W multiples of 2**levels.

    ``levels`` stages of (stride-2 3x3 conv + ReLU, 3x3 conv + ReLU) at width C; at the coarsest scale the
    global fusion: channel attention ``c * sigmoid(W2 ReLU(W1 [avgpool c, maxpool c]))`` over the whole image;
    then a top-down pass (bilinear upsampling, added to each finer stage and finally to the input) and a
    1x1 projection."""

    def __init__(self, width: int, levels: int) -> None:
        super().__init__()
        if levels < 1:
            raise ValueError(f"GlobalRestoration: levels must be >= 1, got {levels}")
        self.stages = nn.ModuleList(
            [nn.Sequential(_conv_relu(width, width, stride=2), _conv_relu(width, width)) for _ in range(levels)]
        )
        reduced = max(4, width // 4)
        self.attention = nn.Sequential(nn.Linear(2 * width, reduced), nn.ReLU(inplace=True), nn.Linear(reduced, width))
        self.project = nn.Conv2d(width, width, 1)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        feats = []
        c = f
        for stage in self.stages:
            c = stage(c)
            feats.append(c)
        pooled = torch.cat([mean_hw(c, keepdim=False), c.amax(dim=(2, 3))], dim=1)
        u = feats[-1] * torch.sigmoid(self.attention(pooled))[:, :, None, None]
        for finer in reversed([f, *feats[:-1]]):
            u = finer + F.interpolate(u, size=finer.shape[-2:], mode="bilinear", align_corners=False)
        return self.project(u)


@register_backbone("rcf")
class RCF(nn.Module):
    """Recurrent cross-modality fusion network (our reading, see the module docstring).

    Args:
        in_channels: must be 2 (channel 0 the normalised depth, channel 1 the normalised amplitude; in training
            ``model.conditioning.use_signal_channel=true``, which ``configs/backbone/rcf.yaml`` sets).
        width: feature width C of the encoders, the fusion and the global restoration module.
        hidden: hidden-state width of the ConvGRU.
        steps: number of recurrent refinement steps K (one prediction each).
        global_levels: stride-2 stages of the global restoration module (inputs are padded to 2**global_levels).
        step_gamma: the loss on step k is weighted by step_gamma ** (K - k) (normalised to sum 1; 1.0 = mean).
    """

    #: deep supervision protocol (``tofdenoise.training.module``): in training mode the forward returns the list
    #: of the K step predictions, final last; ``step_loss_weights`` weights their losses
    deep_supervision = True

    def __init__(
        self,
        in_channels: int = 2,
        width: int = 32,
        hidden: int = 32,
        steps: int = 4,
        global_levels: int = 3,
        step_gamma: float = 0.8,
    ) -> None:
        super().__init__()
        if in_channels != 2:
            raise ValueError(
                f"RCF: fuses depth and amplitude, so in_channels must be 2 (channel 0 depth, channel 1 amplitude), "
                f"got {in_channels}; train it with model.conditioning.use_signal_channel=true "
                "(configs/backbone/rcf.yaml sets it)"
            )
        if width < 1 or hidden < 1:
            raise ValueError(f"RCF: width and hidden must be >= 1, got width={width}, hidden={hidden}")
        if steps < 1:
            raise ValueError(f"RCF: steps must be >= 1, got {steps}")
        if not 0.0 < step_gamma <= 1.0:
            raise ValueError(f"RCF: step_gamma must be in (0, 1], got {step_gamma}")
        self.in_channels = in_channels
        self.steps = int(steps)
        self.multiple = 2 ** int(global_levels)
        raw = [float(step_gamma) ** (self.steps - k) for k in range(1, self.steps + 1)]
        #: loss weight of each step prediction (sum 1), read by ``DepthRestorer.training_loss``
        self.step_loss_weights = tuple(w / sum(raw) for w in raw)
        n_geo = len(NEIGHBOURS) * len(DILATIONS)
        self.n_geo = n_geo
        self.enc_depth = nn.Sequential(_conv_relu(1, width), _conv_relu(width, width))
        self.enc_amp = nn.Sequential(_conv_relu(1, width), _conv_relu(width, width))
        self.amp_gate = nn.Conv2d(width, width, 3, padding=1)
        self.fuse = nn.Sequential(nn.Conv2d(2 * width, width, 1), nn.ReLU(inplace=True))
        self.global_restoration = GlobalRestoration(width, int(global_levels))
        self.to_hidden = nn.Conv2d(width, hidden, 1)
        self.to_input = nn.Conv2d(width, width, 1)
        self.geometry = _conv_relu(n_geo + 2, width)
        self.gru = ConvGRU(hidden, 2 * width)
        self.head = nn.Sequential(_conv_relu(hidden, width), nn.Conv2d(width, n_geo + 1, 3, padding=1))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor | list[torch.Tensor]:
        check_input(x, self.in_channels, "RCF")
        xp, size = pad_to_multiple(x, self.multiple)
        depth, amp = xp[:, :1], xp[:, 1:2]
        f_d, f_a = self.enc_depth(depth), self.enc_amp(amp)
        f = self.fuse(torch.cat([f_d * torch.sigmoid(self.amp_gate(f_a)), f_a], dim=1))
        ctx = self.global_restoration(f)
        h = torch.tanh(self.to_hidden(ctx))
        inp = F.relu(self.to_input(ctx))
        r = torch.zeros_like(depth)
        preds = []
        for _ in range(self.steps):
            current = depth + r
            geo = torch.cat([neighbour_differences(current, d) for d in DILATIONS], dim=1)
            m = self.geometry(torch.cat([geo, r, amp], dim=1))
            h = self.gru(h, torch.cat([inp, m], dim=1))
            out = self.head(h)
            w, b = out[:, : self.n_geo], out[:, self.n_geo :]
            r = r + (torch.tanh(w) * geo).sum(dim=1, keepdim=True) / self.n_geo + b
            preds.append(depth + r)
        if self.training:
            return [crop_to(p, size) for p in preds]
        return crop_to(preds[-1], size)
