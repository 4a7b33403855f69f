"""Per-frame outputs of ``tofdenoise-denoise`` (and of LightningCLI ``predict`` on frames), all written atomically.

For a frame named ``<rel>/<stem>`` (its path relative to the input folder, without suffix) under ``out``::

    out/<rel>/<stem>.png              restored depth, 16-bit PNG in mm (0 = invalid), ``io.write_depth_png16``
    out/<rel>/<stem>.npy              restored depth, float32 mm (0 = invalid)                   [npy]
    out/<rel>/<stem>_sigma_mm.npy     sigma_D of the input [mm], float32, NaN = invalid             [calib + amplitude]
    out/<rel>/<stem>_preview.png      input | restored | |restored - input| (| sigma_D) with colour bars  [previews]
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.atomic import atomic_write_png, save_npy_atomic
from tofdenoise.data_modules.io import write_depth_png16

__all__ = ["OutputOptions", "output_paths", "preview_panel", "write_frame_outputs"]

SIGMA_SUFFIX = "_sigma_mm.npy"
PREVIEW_SUFFIX = "_preview.png"


@dataclass(frozen=True)
class OutputOptions:
    npy: bool = False
    previews: bool = False
    preview_max_tile: int | None = 480


def output_paths(out: Path, name: str) -> dict[str, Path]:
    base = Path(out) / name
    return {
        "png": base.with_name(base.name + ".png"),
        "npy": base.with_name(base.name + ".npy"),
        "sigma": base.with_name(base.name + SIGMA_SUFFIX),
        "preview": base.with_name(base.name + PREVIEW_SUFFIX),
    }


def preview_panel(
    input_mm: np.ndarray,
    valid: np.ndarray,
    restored_mm: np.ndarray,
    sigma_mm: np.ndarray | None = None,
    max_tile: int | None = 480,
    title: str | None = None,
) -> np.ndarray:
    """One-row panel (uint8 RGB): input | restored on a shared depth scale (1st..99th percentile of the valid
    input) with its colour bar, then |restored - input| over valid input pixels (and sigma_D of the input) on a
    shared millimetre scale with its colour bar. Invalid pixels are grey."""
    from tofdenoise import visualize as vis

    valid = np.asarray(valid, dtype=bool)
    out_valid = np.isfinite(restored_mm) & (restored_mm > 0)
    lo, hi = vis.robust_range(np.asarray(input_mm, dtype=np.float64), valid)
    share = 100.0 * (1.0 - valid.mean())

    def tile(rgb: np.ndarray, label: str) -> np.ndarray:
        return vis.add_title(vis._resize(rgb, max_tile), label)

    tiles = [
        tile(vis.colorize_depth(input_mm, lo, hi, valid), f"input ({share:.1f}% invalid)"),
        tile(vis.colorize_depth(restored_mm, lo, hi, out_valid), "restored"),
    ]
    tiles.append(vis.colorbar(tiles[0].shape[0], lo, hi, vis.DEPTH_COLORMAP, "mm"))
    diff = np.abs(np.asarray(restored_mm, dtype=np.float64) - input_mm)
    ok = valid & out_valid
    deviations = [(diff, ok, f"|restored-input| median {np.median(diff[ok]) if ok.any() else float('nan'):.2f} mm")]
    if sigma_mm is not None:
        s_ok = valid & np.isfinite(sigma_mm)
        deviations.append(
            (sigma_mm, s_ok, f"sigma_D input, mean {np.mean(sigma_mm[s_ok]) if s_ok.any() else float('nan'):.2f} mm")
        )
    emax = max(vis.robust_range(d, m, (0.0, 99.0))[1] for d, m, _ in deviations)
    tiles += [tile(vis.colorize_error(d, emax, m), label) for d, m, label in deviations]
    tiles.append(vis.colorbar(tiles[0].shape[0], 0.0, emax, vis.ERROR_COLORMAP, "mm"))
    panel = vis._hstack(tiles)
    if title:
        panel = vis.add_title(panel, title)
    return np.ascontiguousarray(panel)


def write_frame_outputs(
    out: str | Path,
    name: str,
    input_mm: np.ndarray,
    valid: np.ndarray,
    restored_mm: np.ndarray,
    options: OutputOptions = OutputOptions(),
    sigma_mm: np.ndarray | None = None,
) -> list[Path]:
    """Write the outputs of one frame (module docstring); returns the written paths."""
    import cv2

    paths = output_paths(Path(out), name)
    written = [write_depth_png16(paths["png"], restored_mm)]
    if options.npy:
        written.append(save_npy_atomic(paths["npy"], np.asarray(restored_mm, dtype=np.float32)))
    if sigma_mm is not None:
        written.append(save_npy_atomic(paths["sigma"], np.asarray(sigma_mm, dtype=np.float32)))
    if options.previews:
        rgb = preview_panel(input_mm, valid, restored_mm, sigma_mm, options.preview_max_tile, title=name)
        written.append(atomic_write_png(paths["preview"], cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    return written


def frame_sigma(frame: Any, calib: Any) -> np.ndarray | None:
    """sigma_D map of a frame's input when a calibration and the amplitude are there, else None."""
    if calib is None or frame.amplitude is None:
        return None
    from tofdenoise.inference.denoise import sigma_map_mm

    return sigma_map_mm(frame.depth_mm, frame.valid, frame.amplitude, calib)
