"""Overlapping tiled inference with smooth blending windows, for frames too large to process at once.

The frame is first padded at its bottom/right to the model's ``multiple`` exactly as the backbones pad a whole
frame (``models/common.py:pad_to_multiple``, reflect), and tiles are cut from that padded frame: the tile side is
``tile`` rounded down to the multiple, every tile starts on a multiple (stride ``tile - overlap`` rounded down to
the multiple; the last tile of a row or column ends at the padded border), and the blend is cropped back to the
frame. Every tile thus sees the pixels, the padding and the down-sampling grid of the whole-frame forward pass;
a border tile cut from the unpadded frame at ``size - tile`` would not (before 2026-11-29, 45.8 mm max difference
for DVSS at 481 x 639 in 128 px tiles). Each tile's output is weighted by a separable window that is 1 in
the tile's interior and along image borders, and that falls from 1 to 0 with a raised-cosine ramp towards
edges shared with a neighbouring tile. The ramp leaves a margin of ``margin`` pixels (default overlap // 4)
next to the tile edge at weight exactly 0, where a network's output is affected by the tile boundary.
Outputs are accumulated as sum(w * y) / sum(w).

Exactness: for a network whose receptive-field radius r satisfies r <= margin (and 2 * margin < overlap),
every pixel with non-zero weight in a tile is computed exactly as in the whole image, so the blend equals
the whole-image output up to float rounding. For larger receptive fields (U-Nets, state-space and
attention backbones) the blend is seam-free (the weights are smooth and sum to one) but only approximately
equal to whole-image inference.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from .common import crop_to, pad_to_multiple

__all__ = ["tiled_forward", "tile_starts", "model_multiple", "min_tile_px", "blend_window_1d", "TilingSettings"]


@dataclass(frozen=True)
class TilingSettings:
    """When a restorer runs a frame tile by tile (``model.tiling`` in the configs).

    Args:
        predict_tile_px: the tile side of ``predict`` and ``tofdenoise denoise`` for a frame whose activations do
            not fit the memory budget (halved down to 64 px while they do not); ``None`` = never tile.
        eval_tile_px: the same for validation and test (``None`` = whole frames, the paper's protocol).
        overlap_px: overlap of neighbouring tiles in pixels.
    """

    predict_tile_px: int | None = 512
    eval_tile_px: int | None = None
    overlap_px: int = 32

    def __post_init__(self) -> None:
        for name in ("predict_tile_px", "eval_tile_px"):
            value = getattr(self, name)
            if value is not None:
                if int(value) <= int(self.overlap_px):
                    raise ValueError(f"tiling.{name} must exceed tiling.overlap_px ({self.overlap_px}), got {value}")
                object.__setattr__(self, name, int(value))
        if int(self.overlap_px) < 0:
            raise ValueError(f"tiling.overlap_px must be >= 0, got {self.overlap_px}")
        object.__setattr__(self, "overlap_px", int(self.overlap_px))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def tile_starts(size: int, tile: int, overlap: int, multiple: int = 1) -> list[int]:
    """Start offsets of tiles of length ``tile`` covering ``[0, size)`` with at least ``overlap`` overlap.

    With ``multiple`` > 1 every start is a multiple of it (``size`` and ``tile`` must be multiples of it): the
    stride ``tile - overlap`` is rounded down to the multiple, so neighbours overlap by at least ``overlap``.

    Raises:
        ValueError: ``size`` or ``tile`` is not a multiple of ``multiple``, or no stride of at least one
            multiple is left after the overlap.
    """
    if multiple < 1 or size % multiple or tile % multiple:
        raise ValueError(f"tile_starts: size {size} and tile {tile} must be multiples of multiple={multiple}")
    if size <= tile:
        return [0]
    stride = (tile - overlap) // multiple * multiple
    if stride < 1:
        raise ValueError(
            f"tile_starts: a tile of {tile} px with an overlap of {overlap} px leaves no stride that is a multiple "
            f"of {multiple} px; the tile must be at least {overlap + multiple} px"
        )
    n = math.ceil((size - tile) / stride) + 1
    starts = [min(i * stride, size - tile) for i in range(n)]
    return sorted(set(starts))


def model_multiple(model: Any) -> int:
    """The side a model pads its input to a multiple of (a backbone's ``multiple``; 1 when it has none)."""
    return max(int(getattr(model, "multiple", 1) or 1), 1)


def min_tile_px(overlap: int, multiple: int = 1) -> int:
    """The smallest tile side ``tiled_forward`` takes for ``overlap`` and a model's ``multiple``: a multiple of it
    that leaves a stride of at least one multiple after the overlap."""
    m = max(int(multiple), 1)
    return -(-(int(overlap) + m) // m) * m


def blend_window_1d(
    length: int, overlap: int, margin: int, ramp_start: bool, ramp_end: bool, dtype=torch.float32, device=None
) -> torch.Tensor:
    """1-D weight: 1 inside, 0 for ``margin`` pixels at a ramped end, then a raised-cosine ramp to 1 over
    ``overlap - 2 * margin`` pixels. Ends not shared with another tile (image borders) stay at 1."""
    w = torch.ones(length, dtype=torch.float64, device=device)
    ramp_len = overlap - 2 * margin
    pos = torch.arange(ramp_len, dtype=torch.float64, device=device)
    ramp = torch.sin(0.5 * math.pi * (pos + 0.5) / ramp_len) ** 2  # complementary: ramp + flip(ramp) = 1
    if ramp_start:
        w[:margin] = 0.0
        w[margin : margin + ramp_len] = ramp
    if ramp_end:
        if margin:
            w[length - margin :] = 0.0
        w[length - margin - ramp_len : length - margin] = torch.minimum(
            w[length - margin - ramp_len : length - margin], ramp.flip(0)
        )
    return w.to(dtype)


@torch.no_grad()
def tiled_forward(
    model: nn.Module,
    x: torch.Tensor,
    tile: int = 256,
    overlap: int = 32,
    margin: int | None = None,
    tile_batch: int = 1,
    multiple: int | None = None,
) -> torch.Tensor:
    """Run ``model`` on overlapping tiles of ``x`` and blend them, for frames too large for memory.

    Neighbouring tiles are blended with smooth weights that fall to 0 towards a shared edge and sum to one (the
    module's docstring says when the blend equals whole-image inference). Images no larger than one tile are
    processed whole. Runs under ``torch.no_grad()``.

    Args:
        model: any callable (B, C, h, w) -> (B, C_out, h, w), e.g. a backbone.
        x: the input, (B, C, H, W).
        tile: tile side [pixels].
        overlap: overlap between neighbouring tiles [pixels], less than ``tile``.
        margin: pixels at a shared tile edge given weight 0 (default ``overlap // 4``; less than half the
            overlap).
        tile_batch: tiles per model call.
        multiple: the model pads its input to a multiple of this (reflect, bottom/right; default:
            ``model.multiple`` when the model has one, else 1). The frame is padded the same way before it is
            tiled, the tile side is rounded down to it and every tile starts on it, so that each tile sees what
            the whole-frame forward pass sees; the output is cropped back to (H, W).

    Returns:
        The blended output, (B, C_out, H, W).

    Raises:
        ValueError: ``x`` is not 4-D, or the tile, overlap, margin, tile_batch or multiple do not fit together
            (a tile must be at least ``overlap`` + ``multiple`` px after rounding down to the multiple).
    """
    if x.dim() != 4:
        raise ValueError(f"tiled_forward: expected x of shape (B, C, H, W), got {tuple(x.shape)}")
    if margin is None:
        margin = overlap // 4
    bad_margin = margin < 0 or (overlap > 0 and 2 * margin >= overlap)
    if tile < 1 or overlap < 0 or overlap >= tile or bad_margin:
        raise ValueError(
            f"tiled_forward: need tile >= 1, 0 <= overlap < tile and 0 <= 2 * margin < overlap; "
            f"got tile={tile}, overlap={overlap}, margin={margin}"
        )
    if tile_batch < 1:
        raise ValueError(f"tiled_forward: tile_batch must be >= 1, got {tile_batch}")
    m = model_multiple(model) if multiple is None else int(multiple)
    if m < 1:
        raise ValueError(f"tiled_forward: multiple must be >= 1, got {multiple}")
    b, _, h, w = x.shape
    if h <= tile and w <= tile:
        return model(x)
    side = tile // m * m
    if side - overlap < m:
        raise ValueError(
            f"tiled_forward: a tile of {tile} px with an overlap of {overlap} px leaves no tile start on the "
            f"model's multiple of {m} px; use a tile of at least {min_tile_px(overlap, m)} px "
            "(--tile / tiling.predict_tile_px / tiling.eval_tile_px) or a smaller tiling.overlap_px"
        )
    xp, size = pad_to_multiple(x, m)
    hp, wp = xp.shape[-2:]
    th, tw = min(side, hp), min(side, wp)
    # The stride is rounded down to the multiple: neighbours overlap by ``ramp_overlap`` >= overlap, and their
    # ramps span that overlap (so that they still sum to one).
    ramp_overlap = side - (side - overlap) // m * m
    ys, xs = tile_starts(hp, th, ramp_overlap, m), tile_starts(wp, tw, ramp_overlap, m)
    boxes = [(y0, x0) for y0 in ys for x0 in xs]
    out = None
    weight = x.new_zeros(1, 1, hp, wp)
    for i in range(0, len(boxes), tile_batch):
        chunk = boxes[i : i + tile_batch]
        inp = torch.cat([xp[:, :, y0 : y0 + th, x0 : x0 + tw] for y0, x0 in chunk], dim=0)
        pred = model(inp)
        if out is None:
            out = x.new_zeros(b, pred.shape[1], hp, wp)
        for j, (y0, x0) in enumerate(chunk):
            wy = blend_window_1d(th, ramp_overlap, margin, y0 > 0, y0 + th < hp, x.dtype, x.device)
            wx = blend_window_1d(tw, ramp_overlap, margin, x0 > 0, x0 + tw < wp, x.dtype, x.device)
            win = (wy[:, None] * wx[None, :])[None, None]
            out[:, :, y0 : y0 + th, x0 : x0 + tw] += pred[j * b : (j + 1) * b] * win
            weight[:, :, y0 : y0 + th, x0 : x0 + tw] += win
    return crop_to(out / weight, size)
