"""Compact Restormer (Zamir et al., CVPR 2022): MDTA (transposed channel attention) + GDFN Transformer
blocks in a 4-level U-shape with refinement blocks; width 32, [2, 2, 4, 4] blocks, heads [1, 2, 4, 8]."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .common import Downsample, LayerNorm2d, Upsample, check_input, crop_to, normalize_fp32, pad_to_multiple
from .registry import register_backbone

__all__ = ["Restormer", "MDTA", "GDFN", "TransformerBlock"]


class MDTA(nn.Module):
    """Multi-Dconv-head Transposed Attention: attention over channels (C/h x C/h per head), so the cost
    is linear in the number of pixels. q, k are L2-normalised along pixels; a learnable temperature per head."""

    def __init__(self, dim: int, heads: int, bias: bool = False) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"MDTA: dim={dim} must be divisible by heads={heads}")
        self.heads = heads
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.qkv = nn.Conv2d(dim, dim * 3, 1, bias=bias)
        self.qkv_dw = nn.Conv2d(dim * 3, dim * 3, 3, padding=1, groups=dim * 3, bias=bias)
        self.project_out = nn.Conv2d(dim, dim, 1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv_dw(self.qkv(x)).chunk(3, dim=1)
        q, k, v = (t.reshape(b, self.heads, c // self.heads, h * w) for t in (q, k, v))
        q, k = normalize_fp32(q), normalize_fp32(k)  # sums over h x w pixels: float32 (mean_hw)
        attn = (q @ k.transpose(-2, -1)) * self.temperature
        out = attn.softmax(dim=-1) @ v
        return self.project_out(out.reshape(b, c, h, w))


class GDFN(nn.Module):
    """Gated-Dconv Feed-forward Network: 1x1 -> depthwise 3x3 -> GELU(x1) * x2 -> 1x1."""

    def __init__(self, dim: int, expansion: float = 2.66, bias: bool = False) -> None:
        super().__init__()
        hidden = int(dim * expansion)
        self.project_in = nn.Conv2d(dim, hidden * 2, 1, bias=bias)
        self.dw = nn.Conv2d(hidden * 2, hidden * 2, 3, padding=1, groups=hidden * 2, bias=bias)
        self.project_out = nn.Conv2d(hidden, dim, 1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x1, x2 = self.dw(self.project_in(x)).chunk(2, dim=1)
        return self.project_out(F.gelu(x1) * x2)


class TransformerBlock(nn.Module):
    """x + MDTA(LN x); x + GDFN(LN x)."""

    def __init__(self, dim: int, heads: int, expansion: float = 2.66, bias: bool = False) -> None:
        super().__init__()
        self.norm1 = LayerNorm2d(dim, eps=1e-5)
        self.attn = MDTA(dim, heads, bias)
        self.norm2 = LayerNorm2d(dim, eps=1e-5)
        self.ffn = GDFN(dim, expansion, bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.ffn(self.norm2(x))


def _stage(n: int, dim: int, heads: int, expansion: float) -> nn.Sequential:
    return nn.Sequential(*[TransformerBlock(dim, heads, expansion) for _ in range(n)])


@register_backbone("restormer")
class Restormer(nn.Module):
    """Compact Restormer. Levels 1-3 encoder + latent level 4 (widths w, 2w, 4w, 8w), decoder levels 3 and 2
    reduce the concatenated skip with a 1x1 conv, level 1 keeps 2w channels, then refinement blocks and a
    3x3 output conv (zero-initialised) whose result is added to the noisy depth. Multiple of 8."""

    def __init__(
        self,
        in_channels: int = 1,
        width: int = 32,
        blocks: Sequence[int] = (2, 2, 4, 4),
        heads: Sequence[int] = (1, 2, 4, 8),
        refinement_blocks: int = 2,
        ffn_expansion: float = 2.66,
        residual: bool = True,
    ) -> None:
        super().__init__()
        blocks = [int(v) for v in blocks]
        heads = [int(v) for v in heads]
        if len(blocks) != 4 or len(heads) != 4:
            raise ValueError(f"Restormer: blocks and heads need 4 entries, got blocks={blocks}, heads={heads}")
        if width < 2 or width % 2:
            raise ValueError(f"Restormer: width must be an even number >= 2, got {width}")
        self.in_channels = in_channels
        self.residual = residual
        self.multiple = 8
        w = [width, width * 2, width * 4, width * 8]
        self.embed = nn.Conv2d(in_channels, width, 3, padding=1, bias=False)
        self.enc = nn.ModuleList([_stage(blocks[i], w[i], heads[i], ffn_expansion) for i in range(3)])
        self.down = nn.ModuleList([Downsample(w[i]) for i in range(3)])
        self.latent = _stage(blocks[3], w[3], heads[3], ffn_expansion)
        self.up = nn.ModuleList([Upsample(w[3]), Upsample(w[2]), Upsample(w[1])])
        self.reduce = nn.ModuleList(
            [nn.Conv2d(w[3], w[2], 1, bias=False), nn.Conv2d(w[2], w[1], 1, bias=False), nn.Identity()]
        )
        self.dec = nn.ModuleList(
            [
                _stage(blocks[2], w[2], heads[2], ffn_expansion),
                _stage(blocks[1], w[1], heads[1], ffn_expansion),
                _stage(blocks[0], w[1], heads[0], ffn_expansion),
            ]
        )
        self.refinement = _stage(refinement_blocks, w[1], heads[0], ffn_expansion)
        self.output = nn.Conv2d(w[1], 1, 3, padding=1, bias=False)
        if residual:
            nn.init.zeros_(self.output.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(x, self.in_channels, "Restormer")
        xp, size = pad_to_multiple(x, self.multiple)
        h = self.embed(xp)
        skips = []
        for enc, down in zip(self.enc, self.down):
            h = enc(h)
            skips.append(h)
            h = down(h)
        h = self.latent(h)
        for up, reduce, dec, skip in zip(self.up, self.reduce, self.dec, reversed(skips)):
            h = dec(reduce(torch.cat([up(h), skip], dim=1)))
        out = self.output(self.refinement(h))
        if self.residual:
            out = out + xp[:, :1]
        return crop_to(out, size)
