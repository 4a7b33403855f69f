"""Shared building blocks for the backbones: size padding, channels-first LayerNorm, pixel-(un)shuffle
down/up-sampling, float32 sums over pixels, parameter count."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "Downsample",
    "Upsample",
    "LayerNorm2d",
    "count_parameters",
    "draw_zero_parameters",
    "execution_distances",
    "pad_to_multiple",
    "crop_to",
    "check_input",
    "mean_hw",
    "normalize_fp32",
    "pointwise",
]


def mean_hw(x: torch.Tensor, keepdim: bool = True) -> torch.Tensor:
    """Mean of a (B, C, H, W) tensor over its pixels, summed in float32 and returned in ``x``'s dtype.

    A whole frame's sum leaves float16's range (65504) at 480 x 640 (307,200 pixels): onnxruntime's CUDA provider
    sums a float16 ``ReduceMean`` in float16, and DVSS's channel attention gave NaN there (CHANGELOG.md,
    2026-11-26). Exact for float32 inputs."""
    return x.float().mean(dim=(2, 3), keepdim=keepdim).to(x.dtype)


def eager_inference() -> bool:
    """True for a plain eager forward without a gradient: not traced (``torch.jit`` / ONNX export), not compiled,
    not exported by ``torch.export`` -- where the inference-only shortcuts of a backbone (weights folded per call,
    in-place activations, native fused kernels) may run. A traced or exported graph keeps the training forward's
    operators."""
    return not (
        torch.is_grad_enabled()
        or torch.jit.is_tracing()
        or torch.compiler.is_compiling()
        or torch.compiler.is_exporting()
        or torch.onnx.is_in_onnx_export()
    )


#: :func:`pointwise` on oneDNN's 1x1 convolution (True) or on MKL's matrix product (False; its output is
#: channels-last whatever the input's layout). Measured on an AMD EPYC only (docs/benchmarks.md); the benchmark prints
#: both on the machine it runs on
POINTWISE_ONEDNN = True


def pointwise(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """A per-pixel linear map, ``x`` (B, C, H, W) -> (B, out, H, W) with ``weight`` (out, C) and an optional bias
    (out,): ``x[b, :, i, j] @ weight.T + bias`` at every pixel, as a 1x1 convolution (oneDNN's kernels on the CPU).
    On channels-last memory it reads the (B H W, C) rows in place and writes channels-last output: the same product
    as ``rows @ weight.T``, which torch hands to MKL's sgemm. On an AMD EPYC (Zen 4) MKL's sgemm ran SS2D's
    per-pixel products 1.2-1.9x slower than oneDNN's 1x1 convolution, with equal results for up to 128 input
    channels (docs/benchmarks.md, "MKL's products on an AMD CPU"); the inference paths of DVSS use this.
    :data:`POINTWISE_ONEDNN` False takes MKL's product instead (``benchmarks/bench_scan_cpu.py`` times both)."""
    if not POINTWISE_ONEDNN:
        b, c, h, w = x.shape
        rows = x.permute(0, 2, 3, 1).reshape(-1, c)
        out = torch.addmm(bias, rows, weight.t()) if bias is not None else rows @ weight.t()
        return out.view(b, h, w, -1).permute(0, 3, 1, 2)  # channels-last
    return F.conv2d(x, weight.reshape(weight.shape[0], -1, 1, 1), bias)


def normalize_fp32(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """``F.normalize(x, dim)`` with the sum of squares in float32 (see :func:`mean_hw`: a sum over a frame's
    pixels overflows float16); returned in ``x``'s dtype."""
    return F.normalize(x.float(), dim=dim).to(x.dtype)


def count_parameters(module: nn.Module, trainable_only: bool = True) -> int:
    """Number of scalar parameters of ``module``.

    Args:
        module: any ``nn.Module``.
        trainable_only: count only the parameters with ``requires_grad``.
    """
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def draw_zero_parameters(module: nn.Module, std: float = 0.05, seed: int = 0) -> nn.Module:
    """``module`` with every all-zero parameter drawn from N(0, std²) (a fixed-seed generator), in place.

    For comparing two executions of one network (compiled against eager, one device against another): every
    backbone here starts from a zero-initialised residual head (the identity at initialisation), which passes no
    gradient to the layers before it, so a comparison at initialisation would check the head alone.
    """
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            if not p.any():
                p.copy_(std * torch.randn(p.shape, generator=g).to(p.dtype))
    return module


def execution_distances(
    reference: tuple[torch.Tensor, dict[str, torch.Tensor]], run: tuple[torch.Tensor, dict[str, torch.Tensor]]
) -> dict[str, float]:
    """How far one execution of a network is from another: ``reference`` and ``run`` are (output, {parameter name:
    gradient}). ``"output"``: the largest absolute difference over the reference output's largest magnitude; each
    parameter: the largest absolute difference of its gradient over the larger of the reference gradient's largest
    magnitude and 1e-3 of the network's largest gradient (a gradient that cancels to about 0, such as a bias under a
    weight that sums to 0, is compared at the network's scale, not at its rounding noise: on CUDA one came out
    1.4e-6 eager and 0 compiled). For compiled against eager, one device against another (with
    :func:`draw_zero_parameters`, so that the gradients reach the network)."""
    (y0, g0), (y1, g1) = reference, run
    if g0.keys() != g1.keys():
        raise ValueError("execution_distances: the two runs have gradients of different parameters")
    floor = 1e-3 * max((float(g.abs().max()) for g in g0.values()), default=0.0)
    errors = {"output": float((y1 - y0).abs().max()) / max(float(y0.abs().max()), 1e-30)}
    for name in g0:
        errors[name] = float((g1[name] - g0[name]).abs().max()) / max(float(g0[name].abs().max()), floor, 1e-30)
    return errors


def pad_to_multiple(x: torch.Tensor, multiple: int, mode: str = "reflect") -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad the bottom/right of a (B, C, H, W) tensor so that H and W are multiples of ``multiple``.

    ``mode`` is ``"reflect"`` (falls back to ``"replicate"`` when the image is too small to reflect)
    or ``"replicate"``. Returns the padded tensor and the original (H, W) for :func:`crop_to`.
    """
    if x.dim() != 4:
        raise ValueError(f"pad_to_multiple: expected a (B, C, H, W) tensor, got shape {tuple(x.shape)}")
    if multiple < 1:
        raise ValueError(f"pad_to_multiple: multiple must be >= 1, got {multiple}")
    if mode not in ("reflect", "replicate"):
        raise ValueError(f"pad_to_multiple: mode must be 'reflect' or 'replicate', got {mode!r}")
    h, w = x.shape[-2:]
    pad_h = (-h) % multiple
    pad_w = (-w) % multiple
    if pad_h == 0 and pad_w == 0:
        return x, (h, w)
    use = mode
    if mode == "reflect" and (pad_h >= h or pad_w >= w):
        use = "replicate"
    return F.pad(x, (0, pad_w, 0, pad_h), mode=use), (h, w)


def crop_to(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Crop a (B, C, H', W') tensor back to the top-left (H, W) given by ``size``."""
    h, w = size
    return x[..., :h, :w]


def check_input(x: torch.Tensor, in_channels: int, name: str) -> None:
    """Raise a clear error when ``x`` is not a (B, in_channels, H, W) floating tensor."""
    if x.dim() != 4 or x.shape[1] != in_channels:
        raise ValueError(
            f"{name}: expected input of shape (B, {in_channels}, H, W), got {tuple(x.shape)} "
            f"(in_channels={in_channels}: channel 0 = normalised noisy depth, channel 1 = normalised signal)"
        )
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point input, got dtype {x.dtype}")


class LayerNorm2d(nn.Module):
    """LayerNorm over the channel dimension of a (B, C, H, W) tensor (per pixel), with affine parameters."""

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.permute(0, 2, 3, 1)
        # the normalised shape from the parameter (a constant), not from x: ONNX export traces x's shape
        x = F.layer_norm(x, self.weight.shape, self.weight, self.bias, self.eps)
        return x.permute(0, 3, 1, 2)


class Downsample(nn.Sequential):
    """3x3 conv C -> C/2 then pixel-unshuffle: (C, H, W) -> (2C, H/2, W/2)."""

    def __init__(self, dim: int) -> None:
        super().__init__(nn.Conv2d(dim, dim // 2, 3, padding=1, bias=False), nn.PixelUnshuffle(2))


class Upsample(nn.Sequential):
    """3x3 conv C -> 2C then pixel-shuffle: (C, H, W) -> (C/2, 2H, 2W)."""

    def __init__(self, dim: int) -> None:
        super().__init__(nn.Conv2d(dim, dim * 2, 3, padding=1, bias=False), nn.PixelShuffle(2))
