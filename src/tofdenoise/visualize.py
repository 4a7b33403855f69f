"""Colourised depth, uncertainty and error maps and sample panels (OpenCV colour maps, uint8 images).

Public API:

- ``to_numpy_2d(x) -> float64 (H, W)``: a tensor/array of shape (H, W), (1, H, W) or (1, 1, H, W).
- ``robust_range(values, mask=None, percentiles=(1, 99)) -> (lo, hi)``: colour-scale limits from the valid,
  finite values.
- ``colorize(values, vmin, vmax, colormap=cv2.COLORMAP_TURBO, mask=None) -> uint8 RGB (H, W, 3)``; invalid
  or non-finite pixels are drawn in ``INVALID_RGB`` (mid grey). ``colorize_depth`` (TURBO) and
  ``colorize_error`` (INFERNO) are the two uses.
- ``colorbar(height, vmin, vmax, colormap, unit="mm") -> uint8 RGB``: a vertical colour bar with labels.
- ``add_title(image, title) -> uint8 RGB``: a title strip above an image (``cv2.putText``).
- ``compose_panel(depth_maps, sigma_mm=None, mask=None, reference_key="clean", max_tile=320, title=None,
  min_tile=None) -> uint8 RGB``: row 1 the depth maps (shared depth scale, colour bar), row 2 sigma_D and the absolute
  error of every map against the reference (shared error scale in mm, colour bar).
- ``sample_panel(noisy_mm, restored_mm, clean_mm, sigma_mm, mask, title=None, max_tile=320, min_tile=None)
  -> uint8 RGB``:
  the validation panel of one sample (noisy | restored | clean ; sigma_D | |noisy - clean| |
  |restored - clean|).
- ``stack_panels(panels, gap=6) -> uint8 RGB``: panels of possibly different widths stacked vertically.
- ``prediction_preview(maps, sigma_mm=None, mask=None) -> uint8 BGR``: ``compose_panel`` converted to BGR
  for ``cv2.imwrite`` (used by the prediction writer).

Colour scales: the depth scale is shared by all depth maps of a panel and spans the 1st..99th percentile of
the reference's valid pixels (of all maps when there is no reference), so noisy outliers saturate instead of
compressing the scale. sigma_D and the absolute errors are all millimetres of deviation and share one scale
from 0 to the 99th percentile of the largest of them (the raw error, usually), so "error ~ sigma" reads
directly. A pixel is drawn invalid where ``mask`` is 0 or the value is not finite.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np

__all__ = [
    "INVALID_RGB",
    "DEPTH_COLORMAP",
    "ERROR_COLORMAP",
    "to_numpy_2d",
    "robust_range",
    "colorize",
    "colorize_depth",
    "colorize_error",
    "colorbar",
    "add_title",
    "compose_panel",
    "sample_panel",
    "stack_panels",
    "prediction_preview",
]

INVALID_RGB = (110, 110, 110)
DEPTH_COLORMAP = cv2.COLORMAP_TURBO
ERROR_COLORMAP = cv2.COLORMAP_INFERNO
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_TEXT_RGB = (235, 235, 235)
_BG_RGB = (24, 24, 24)


def to_numpy_2d(x: Any, name: str = "map") -> np.ndarray:
    """float64 (H, W) numpy array from a tensor/array of shape (H, W), (1, H, W) or (1, 1, H, W)."""
    if hasattr(x, "detach"):
        x = x.detach().to("cpu").double().numpy()
    a = np.asarray(x, dtype=np.float64)
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 2:
        raise ValueError(f"{name}: expected a single 2-D map, got shape {np.shape(x)}")
    return a


def batch_plane(batch_maps: Any, i: int, name: str = "map") -> np.ndarray:
    """float32 (H, W) numpy map of image ``i`` of a (B, 1, H, W) or (B, H, W) tensor/array."""
    return to_numpy_2d(batch_maps[i], name).astype(np.float32)


def _valid(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    ok = np.isfinite(values)
    if mask is not None:
        ok &= mask
    return ok


def robust_range(
    values: np.ndarray | Sequence[np.ndarray],
    mask: np.ndarray | None = None,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> tuple[float, float]:
    """(lo, hi) percentiles of the finite values under ``mask``; a flat or empty set gives a unit-wide range."""
    arrays = [values] if isinstance(values, np.ndarray) else list(values)
    pool = [a[_valid(a, mask)] for a in arrays]
    flat = np.concatenate(pool) if pool else np.empty(0)
    if flat.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(flat, percentiles))
    if not hi > lo:
        hi = lo + 1.0
    return lo, hi


def colorize(
    values: Any, vmin: float, vmax: float, colormap: int = DEPTH_COLORMAP, mask: np.ndarray | None = None
) -> np.ndarray:
    """Map ``values`` linearly from [vmin, vmax] (clipped) through an OpenCV colour map; uint8 RGB (H, W, 3)."""
    v = to_numpy_2d(values)
    if not vmax > vmin:
        raise ValueError(f"colour scale needs vmax > vmin, got [{vmin}, {vmax}]")
    ok = _valid(v, None if mask is None else np.asarray(mask, dtype=bool))
    scaled = np.zeros(v.shape, dtype=np.uint8)
    scaled[ok] = np.rint(np.clip((v[ok] - vmin) / (vmax - vmin), 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(scaled, colormap), cv2.COLOR_BGR2RGB)
    rgb[~ok] = INVALID_RGB
    return rgb


def colorize_depth(depth_mm: Any, vmin_mm: float, vmax_mm: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Depth in mm through the TURBO colour map (near = blue, far = red)."""
    return colorize(depth_mm, vmin_mm, vmax_mm, DEPTH_COLORMAP, mask)


def colorize_error(error_mm: Any, vmax_mm: float, mask: np.ndarray | None = None) -> np.ndarray:
    """A non-negative deviation in mm (|error| or sigma_D) through INFERNO, from 0 to ``vmax_mm``."""
    return colorize(error_mm, 0.0, vmax_mm, ERROR_COLORMAP, mask)


def _tick_decimals(span: float) -> int:
    """Decimals for colour-bar labels: one scale for all ticks (0 for spans >= 100, 1 for >= 10, else 2)."""
    return 0 if span >= 100 else (1 if span >= 10 else 2)


def colorbar(
    height: int,
    vmin: float,
    vmax: float,
    colormap: int = DEPTH_COLORMAP,
    unit: str = "mm",
    bar_width: int = 16,
    label_width: int = 62,
) -> np.ndarray:
    """Vertical colour bar (vmax at the top) with five labelled ticks and the unit; uint8 RGB."""
    height = max(int(height), 40)
    top, bottom = 14, 8
    h_bar = height - top - bottom
    ramp = np.linspace(255, 0, h_bar).round().astype(np.uint8)[:, None].repeat(bar_width, axis=1)
    bar_rgb = cv2.cvtColor(cv2.applyColorMap(ramp, colormap), cv2.COLOR_BGR2RGB)
    out = np.full((height, bar_width + label_width + 4, 3), _BG_RGB, dtype=np.uint8)
    out[top : top + h_bar, 2 : 2 + bar_width] = bar_rgb
    cv2.putText(out, unit, (2, 10), _FONT, 0.35, _TEXT_RGB, 1, cv2.LINE_AA)
    decimals = _tick_decimals(abs(vmax - vmin))
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = top + int(round(frac * (h_bar - 1)))
        value = vmax - frac * (vmax - vmin)
        cv2.line(out, (2 + bar_width, y), (5 + bar_width, y), _TEXT_RGB, 1)
        cv2.putText(
            out,
            f"{value:.{decimals}f}",
            (8 + bar_width, min(max(y + 4, 10), height - 2)),
            _FONT,
            0.35,
            _TEXT_RGB,
            1,
            cv2.LINE_AA,
        )
    return out


def add_title(image: np.ndarray, title: str, line_height: int = 16) -> np.ndarray:
    """Return ``image`` with a dark strip above it holding ``title`` (one line per ``\\n``, clipped to the width).

    The strip is ``4 + 16 * lines`` px high (20 px for one line).
    """
    h, w = image.shape[:2]
    lines = title.split("\n")
    strip = 4 + line_height * len(lines)
    out = np.full((h + strip, w, 3), _BG_RGB, dtype=np.uint8)
    out[strip:] = image
    scale = 0.42
    for i, text in enumerate(lines):
        while text and cv2.getTextSize(text, _FONT, scale, 1)[0][0] > w - 4:
            text = text[:-1]
        cv2.putText(out, text, (3, line_height * (i + 1) - 2), _FONT, scale, _TEXT_RGB, 1, cv2.LINE_AA)
    return out


def _resize(img: np.ndarray, max_tile: int | None, min_tile: int | None = None) -> np.ndarray:
    """Shrink (area) so the longest side is <= max_tile, or enlarge small maps by an integer factor (nearest)
    so the longest side is >= min_tile (titles then fit and pixels stay sharp)."""
    h, w = img.shape[:2]
    if max_tile and max(h, w) > max_tile:
        f = max_tile / max(h, w)
        size = (max(1, int(round(w * f))), max(1, int(round(h * f))))
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    if min_tile and max(h, w) < min_tile:
        k = -(-min_tile // max(h, w))
        return cv2.resize(img, (w * k, h * k), interpolation=cv2.INTER_NEAREST)
    return img


def _hstack(tiles: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    parts = []
    for i, t in enumerate(tiles):
        if t.shape[0] < h:
            pad = np.full((h - t.shape[0], t.shape[1], 3), _BG_RGB, dtype=np.uint8)
            t = np.concatenate([t, pad], axis=0)
        parts.append(t)
        if i < len(tiles) - 1:
            parts.append(np.full((h, gap, 3), _BG_RGB, dtype=np.uint8))
    return np.concatenate(parts, axis=1)


def stack_panels(panels: Sequence[np.ndarray], gap: int = 6) -> np.ndarray:
    """Stack RGB panels vertically, padding narrower ones on the right."""
    if not panels:
        raise ValueError("stack_panels: no panel given")
    w = max(p.shape[1] for p in panels)
    parts = []
    for i, p in enumerate(panels):
        if p.shape[1] < w:
            p = np.concatenate([p, np.full((p.shape[0], w - p.shape[1], 3), _BG_RGB, dtype=np.uint8)], axis=1)
        parts.append(p)
        if i < len(panels) - 1:
            parts.append(np.full((gap, w, 3), _BG_RGB, dtype=np.uint8))
    return np.concatenate(parts, axis=0)


def _mae(err: np.ndarray, ok: np.ndarray) -> str:
    return f"{float(np.mean(err[ok])):.2f}" if ok.any() else "n/a"


def compose_panel(
    depth_maps: Mapping[str, Any],
    sigma_mm: Any | None = None,
    mask: Any | None = None,
    reference_key: str = "clean",
    max_tile: int | None = 320,
    title: str | None = None,
    min_tile: int | None = None,
) -> np.ndarray:
    """Two-row panel (uint8 RGB): depth maps on a shared scale; sigma_D and |map - reference| on a shared mm scale.

    ``depth_maps``: ordered name -> depth in mm (H, W). ``mask``: nonzero = valid (all pixels when None).
    Errors are shown for every map other than ``reference_key`` when the reference is present, with the
    map's MAE over valid pixels in its title. Tiles are shrunk to ``max_tile`` px (longest side) or enlarged
    by an integer factor to at least ``min_tile`` px.
    """
    if not depth_maps:
        raise ValueError("compose_panel: no depth map given")
    maps = {k: to_numpy_2d(v, k) for k, v in depth_maps.items()}
    shape = next(iter(maps.values())).shape
    for k, v in maps.items():
        if v.shape != shape:
            raise ValueError(f"compose_panel: map '{k}' has shape {v.shape}, expected {shape}")
    valid = np.ones(shape, dtype=bool) if mask is None else (to_numpy_2d(mask, "mask") != 0)
    if valid.shape != shape:
        raise ValueError(f"compose_panel: mask has shape {valid.shape}, expected {shape}")
    ref = maps.get(reference_key)
    if ref is not None:
        valid &= np.isfinite(ref) & (ref > 0)
        lo, hi = robust_range(ref, valid)
    else:
        lo, hi = robust_range(list(maps.values()), valid)

    row1 = [add_title(_resize(colorize_depth(v, lo, hi, valid), max_tile, min_tile), k) for k, v in maps.items()]
    row1.append(colorbar(row1[0].shape[0], lo, hi, DEPTH_COLORMAP, "mm"))

    dev_maps: list[tuple[str, np.ndarray, np.ndarray]] = []
    if sigma_mm is not None:
        s = to_numpy_2d(sigma_mm, "sigma_mm")
        if s.shape != shape:
            raise ValueError(f"compose_panel: sigma_mm has shape {s.shape}, expected {shape}")
        ok = valid & np.isfinite(s)
        dev_maps.append((f"sigma_D\nmean {_mae(s, ok)} mm", s, ok))
    if ref is not None:
        for k, v in maps.items():
            if k == reference_key:
                continue
            err = np.abs(v - ref)
            ok = valid & np.isfinite(err)
            dev_maps.append((f"|{k}-{reference_key}|\nMAE {_mae(err, ok)} mm", err, ok))
    panel_rows = [_hstack(row1)]
    if dev_maps:
        emax = max(robust_range(d, ok, (0.0, 99.0))[1] for _, d, ok in dev_maps)
        row2 = [add_title(_resize(colorize_error(d, emax, ok), max_tile, min_tile), name) for name, d, ok in dev_maps]
        row2.append(colorbar(row2[0].shape[0], 0.0, emax, ERROR_COLORMAP, "mm"))
        panel_rows.append(_hstack(row2))
    panel = stack_panels(panel_rows, gap=4)
    if title:
        panel = add_title(panel, title)
    return np.ascontiguousarray(panel)


def sample_panel(
    noisy_mm: Any,
    restored_mm: Any,
    clean_mm: Any,
    sigma_mm: Any | None,
    mask: Any | None,
    title: str | None = None,
    max_tile: int | None = 320,
    min_tile: int | None = None,
) -> np.ndarray:
    """The validation panel of one sample (uint8 RGB): noisy | restored | clean, then sigma_D and errors."""
    return compose_panel(
        {"noisy": noisy_mm, "restored": restored_mm, "clean": clean_mm},
        sigma_mm,
        mask,
        reference_key="clean",
        max_tile=max_tile,
        title=title,
        min_tile=min_tile,
    )


def prediction_preview(
    maps: Mapping[str, Any], sigma_mm: Any | None = None, mask: Any | None = None, max_tile: int | None = None
) -> np.ndarray:
    """``compose_panel`` of ``maps`` (e.g. noisy, restored, clean) as uint8 BGR, ready for ``cv2.imwrite``."""
    rgb = compose_panel(maps, sigma_mm, mask, reference_key="clean", max_tile=max_tile)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
