"""DVSS: the paper's U-shaped Depth Visual State Space network and its block ablations (Sec. III-D, Table 2).

DVSS block:  Y = X + Conv1x1([VSSB(LN(X)), SCR(DWConv(LN(X)))])
Variants:    dvss_no_local  Y = X + Conv1x1(VSSB(LN(X)))                  (no DWConv, no SCR)
             dvss_no_dwconv Y = X + Conv1x1([VSSB(LN(X)), SCR(LN(X))])
             dvss_se        Y = X + Conv1x1([VSSB(LN(X)), SE(DWConv(LN(X)))])
Network: Patch Embedding (3x3 conv) -> encoder levels (DVSS blocks, then downsampling) -> bottleneck ->
decoder (upsampling, skip concatenation + 1x1 fusion, DVSS blocks) -> Depth Head (3x3 conv, zero-initialised)
whose output is a residual added to the noisy depth (channel 0): the network is the identity at init.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence

import torch
import torch.utils.checkpoint
from torch import nn

from .common import (
    Downsample,
    LayerNorm2d,
    Upsample,
    check_input,
    crop_to,
    eager_inference,
    pad_to_multiple,
    pointwise,
)
from .registry import register_backbone
from .scr import SCR, SqueezeExcitation, factorable
from .ss2d import SS2D

__all__ = ["DVSSBlock", "DVSSNet"]

LOCAL_CHOICES = ("scr", "se", "none")
#: the devices on which DVSS runs its blocks on channels-last memory when no gradient is recorded: the CPU (a
#: 480 x 640 frame 1.11x faster, the same numbers to rounding; docs/benchmarks.md). ``benchmarks/bench_gpu.py`` times
#: CUDA both ways; it is left out until measured
CHANNELS_LAST_INFERENCE_DEVICES = ("cpu",)


def folds_for_inference(x: torch.Tensor) -> bool:
    """True where DVSS evaluates its 1x1 fusions of concatenations as products on channels-last memory (an eager
    forward without a gradient (:func:`~tofdenoise.models.common.eager_inference`), no autocast, x (B, C, H, W) on
    channels-last memory)."""
    return eager_inference() and not torch.is_autocast_enabled(x.device.type) and x.permute(0, 2, 3, 1).is_contiguous()


def _rows(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> (B H W, C): a view on channels-last memory."""
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1])


def conv1x1_of_cat(conv: nn.Conv2d, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """``conv(torch.cat([first, second], dim=1))`` for a 1x1 convolution, as two products on channels-last memory
    (no concatenated copy); channels-last output, equal to rounding."""
    c1 = first.shape[1]
    weight = conv.weight.view(conv.out_channels, -1)
    first = first.contiguous(memory_format=torch.channels_last)  # no copy where it is already
    out = pointwise(first, weight[:, :c1], conv.bias)  # channels-last (models.common.pointwise)
    out.permute(0, 2, 3, 1).view(-1, out.shape[1]).addmm_(_rows(second), weight[:, c1:].t())  # in place: a view
    return out


class DVSSBlock(nn.Module):
    """One DVSS block on (B, C, H, W); ``local`` in {"scr", "se", "none"}, ``dwconv`` toggles the DWConv."""

    def __init__(
        self,
        dim: int,
        d_state: int = 16,
        expand: float = 2.0,
        local: str = "scr",
        dwconv: bool = True,
        scan_backend: str = "auto",
    ) -> None:
        super().__init__()
        if local not in LOCAL_CHOICES:
            raise ValueError(f"DVSSBlock: local must be one of {LOCAL_CHOICES}, got {local!r}")
        self.norm = LayerNorm2d(dim)
        self.vssb = SS2D(dim, d_state=d_state, expand=expand, scan_backend=scan_backend)
        self.local = local
        branches = 1
        if local != "none":
            self.dwconv = nn.Conv2d(dim, dim, 3, padding=1, groups=dim) if dwconv else nn.Identity()
            self.refine = SCR(dim) if local == "scr" else SqueezeExcitation(dim)
            branches = 2
        self.fuse = nn.Conv2d(branches * dim, dim, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xn = self.norm(x)
        if folds_for_inference(x):
            return self._forward_folded(x, xn)
        xg = self.vssb(xn.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
        if self.local == "none":
            return x + self.fuse(xg)
        xl = self.refine(self.dwconv(xn))
        return x + self.fuse(torch.cat([xg, xl], dim=1))

    def _forward_folded(self, x: torch.Tensor, xn: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` for inference on channels-last memory, equal to rounding: the SS2D's out_proj folded into
        the fusion's weights (fuse_g @ out_proj, a (C, d_inner) matrix), the concatenation replaced by a second
        product (for one image with SCR's or SE's channel gate folded into its weights), the residual added in
        place."""
        c = x.shape[1]
        y = self.vssb.gated(xn.permute(0, 2, 3, 1))
        weight = self.fuse.weight.view(c, -1)
        folded = weight[:, :c] @ self.vssb.out_proj.weight
        out = pointwise(y.permute(0, 3, 1, 2), folded, self.fuse.bias)  # channels-last (models.common.pointwise)
        rows = out.permute(0, 2, 3, 1).view(-1, c)  # a view (raises otherwise): the in-place sums write into out
        if self.local != "none":
            local = self.dwconv(xn)
            if factorable(local):  # SCR(.) = T * g: g folded into the fusion's columns (no T * g pass)
                t, g = self.refine.factored(local)
                rows.addmm_(_rows(t), (weight[:, c:] * g.view(1, -1)).t())
            else:
                rows.addmm_(_rows(self.refine(local)), weight[:, c:].t())
        rows += _rows(x)
        return out


class _Stage(nn.Sequential):
    """A sequence of DVSS blocks, optionally with activation checkpointing while training."""

    def __init__(self, n: int, dim: int, checkpoint: bool, **kw) -> None:
        super().__init__(*[DVSSBlock(dim, **kw) for _ in range(n)])
        self.checkpoint = checkpoint

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self:
            if self.checkpoint and self.training and torch.is_grad_enabled():
                x = torch.utils.checkpoint.checkpoint(block, x, use_reentrant=False)
            else:
                x = block(x)
        return x


def _blocks(n: int, dim: int, checkpoint: bool = False, **kw) -> _Stage:
    return _Stage(n, dim, checkpoint, **kw)


class DVSSNet(nn.Module):
    """U-shaped DVSS network. Level i has width ``width * 2**i``; ``len(enc_blocks)`` downsamplings, so
    inputs are padded (reflect) to a multiple of ``2**len(enc_blocks)`` and cropped back.
    ``checkpoint=True`` recomputes each block's activations in the backward pass (less memory, one extra
    forward pass per block)."""

    def __init__(
        self,
        in_channels: int = 1,
        width: int = 32,
        enc_blocks: Sequence[int] = (1, 1, 2),
        bottleneck_blocks: int = 2,
        dec_blocks: Sequence[int] | None = None,
        d_state: int = 16,
        expand: float = 2.0,
        local: str = "scr",
        dwconv: bool = True,
        residual: bool = True,
        scan_backend: str = "auto",
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        enc_blocks = [int(v) for v in enc_blocks]
        dec_blocks = [int(v) for v in dec_blocks] if dec_blocks is not None else list(enc_blocks)
        if in_channels < 1:
            raise ValueError(f"DVSSNet: in_channels must be >= 1, got {in_channels}")
        if width < 2 or width % 2:
            raise ValueError(f"DVSSNet: width must be an even number >= 2, got {width}")
        if (
            not enc_blocks
            or len(dec_blocks) != len(enc_blocks)
            or min(enc_blocks + dec_blocks + [bottleneck_blocks]) < 0
        ):
            raise ValueError(
                f"DVSSNet: enc_blocks and dec_blocks must be equally long lists of counts >= 0, "
                f"got enc_blocks={enc_blocks}, dec_blocks={dec_blocks}"
            )
        self.in_channels = in_channels
        self.residual = residual
        levels = len(enc_blocks)
        self.multiple = 2**levels
        kw = dict(
            d_state=d_state, expand=expand, local=local, dwconv=dwconv, scan_backend=scan_backend, checkpoint=checkpoint
        )
        widths = [width * 2**i for i in range(levels + 1)]
        self.patch_embed = nn.Conv2d(in_channels, width, 3, padding=1)
        self.encoder = nn.ModuleList([_blocks(n, widths[i], **kw) for i, n in enumerate(enc_blocks)])
        self.down = nn.ModuleList([Downsample(widths[i]) for i in range(levels)])
        self.bottleneck = _blocks(bottleneck_blocks, widths[-1], **kw)
        self.up = nn.ModuleList([Upsample(widths[i + 1]) for i in reversed(range(levels))])
        self.skip_fuse = nn.ModuleList([nn.Conv2d(2 * widths[i], widths[i], 1) for i in reversed(range(levels))])
        self.decoder = nn.ModuleList([_blocks(dec_blocks[i], widths[i], **kw) for i in reversed(range(levels))])
        self.head = nn.Conv2d(width, 1, 3, padding=1)
        if residual:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_input(x, self.in_channels, type(self).__name__)
        xp, size = pad_to_multiple(x, self.multiple)
        if not torch.is_grad_enabled() and xp.device.type in CHANNELS_LAST_INFERENCE_DEVICES:
            # inference: channels-last memory from the stem on, so that LayerNorm2d's and SS2D's (B, H, W, C) views
            # are free and the convolutions take their NHWC kernels, with no layout copies between the blocks.
            # Training steps keep the default layout: there it gains nothing, and their numbers stay those of the
            # recorded runs (validation, without a gradient, takes it and agrees with them to rounding). The stem
            # reads a channels-last copy of its few input channels and so writes channels-last features itself, in
            # an eager forward: no copy of the (B, width, H, W) features (13 ms of a 480 x 640 frame). A traced or
            # exported graph copies the features after the stem (the copy above is not an ONNX operator)
            if eager_inference():
                h = self.patch_embed(torch.empty_like(xp, memory_format=torch.channels_last).copy_(xp))
            else:
                h = self.patch_embed(xp).contiguous(memory_format=torch.channels_last)
        else:
            h = self.patch_embed(xp)
        skips = []
        for blocks, down in zip(self.encoder, self.down):
            h = blocks(h)
            skips.append(h)
            h = down(h)
        h = self.bottleneck(h)
        for up, fuse, blocks, skip in zip(self.up, self.skip_fuse, self.decoder, reversed(skips)):
            if folds_for_inference(skip):
                h = blocks(conv1x1_of_cat(fuse, up(h), skip))
            else:
                h = blocks(fuse(torch.cat([up(h), skip], dim=1)))
        out = self.head(h)
        if self.residual:
            out = out + xp[:, :1]
        return crop_to(out, size)


def _variant(name: str, local: str, dwconv: bool):
    """Register a DVSSNet factory with fixed ``local``/``dwconv`` (signature without those two)."""

    def factory(**kwargs) -> DVSSNet:
        return DVSSNet(local=local, dwconv=dwconv, **kwargs)

    params = [
        p for p in inspect.signature(DVSSNet.__init__).parameters.values() if p.name not in ("self", "local", "dwconv")
    ]
    factory.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    factory.__name__ = factory.__qualname__ = f"build_{name}"
    factory.__doc__ = f"DVSS variant {name!r}: DVSSNet(local={local!r}, dwconv={dwconv})."
    register_backbone(name)(factory)
    return factory


build_dvss = _variant("dvss", "scr", True)
build_dvss_no_local = _variant("dvss_no_local", "none", False)
build_dvss_no_dwconv = _variant("dvss_no_dwconv", "scr", False)
build_dvss_se = _variant("dvss_se", "se", True)
