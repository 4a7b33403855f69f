"""Training augmentation: one random crop and random flips applied to all maps of a sample together."""

from __future__ import annotations

import numpy as np
import torch


def crop_window(height: int, width: int, crop_h: int, crop_w: int, generator: torch.Generator) -> tuple[int, int]:
    """Top-left corner of a uniformly random crop_h x crop_w window."""
    if crop_h > height or crop_w > width:
        raise ValueError(f"crop {crop_h}x{crop_w} does not fit a {height}x{width} sample (lower data.crop_size)")
    top = int(torch.randint(0, height - crop_h + 1, (1,), generator=generator))
    left = int(torch.randint(0, width - crop_w + 1, (1,), generator=generator))
    return top, left


def crop_coverage(height: int, width: int, crop: tuple[int, int] | None) -> np.ndarray:
    """The probability that a uniformly random crop window (:func:`crop_window`) covers each pixel of a
    height x width sample, as a (height, width) float64 array (all ones without a crop). Separable: a row i is
    covered by the min(i, height - crop_h) - max(0, i - crop_h + 1) + 1 of the height - crop_h + 1 window tops that
    reach it, a column likewise. A 64 x 64 crop of a 128 x 160 map covers a corner pixel once in 65 x 97 draws and the
    centre in 64 x 64 of them."""
    if crop is None:
        return np.ones((height, width))
    crop_h, crop_w = crop
    if crop_h > height or crop_w > width:
        raise ValueError(f"crop {crop_h}x{crop_w} does not fit a {height}x{width} sample (lower data.crop_size)")

    def axis(n: int, c: int) -> np.ndarray:
        i = np.arange(n)
        return (np.minimum(i, n - c) - np.maximum(0, i - c + 1) + 1) / (n - c + 1)

    return np.outer(axis(height, crop_h), axis(width, crop_w))


def random_crop_flip(
    maps: dict[str, torch.Tensor],
    crop: tuple[int, int] | None,
    generator: torch.Generator,
    hflip: bool = True,
    vflip: bool = True,
) -> dict[str, torch.Tensor]:
    """Crop and flip every (..., H, W) tensor in ``maps`` with the same window and flips (maps stay aligned)."""
    first = next(iter(maps.values()))
    height, width = first.shape[-2:]
    for name, tensor in maps.items():
        if tensor.shape[-2:] != (height, width):
            raise ValueError(f"map {name!r} has size {tuple(tensor.shape[-2:])}, expected {(height, width)}")
    if crop is not None:
        top, left = crop_window(height, width, crop[0], crop[1], generator)
        maps = {k: v[..., top : top + crop[0], left : left + crop[1]] for k, v in maps.items()}
    flips = torch.rand(2, generator=generator)
    dims = []
    if hflip and flips[0] < 0.5:
        dims.append(-1)
    if vflip and flips[1] < 0.5:
        dims.append(-2)
    if dims:
        maps = {k: torch.flip(v, dims) for k, v in maps.items()}
    return {k: v.contiguous() for k, v in maps.items()}
