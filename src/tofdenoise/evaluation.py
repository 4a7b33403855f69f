"""The unified depth metrics of folders of depth maps produced by any method (what ``tofdenoise evaluate`` writes).

Files are matched by their path below the folder less the suffix (``scene_001.png`` <-> ``scene_001.npy`` is fine;
sub-folders are searched, as ``tofdenoise denoise`` mirrors them: ``day1/scene_001`` pairs with ``day1/scene_001``).
Depth files: single-channel 16-bit PNG/TIFF holding millimetres (0 = invalid), or ``.npy``/``.npz`` (single
array)/``.exr`` float maps in millimetres. An 8-bit PNG cannot hold depth in mm and is an error. Mask files: any
single-channel image or array, nonzero = evaluate. A pixel counts where the reference is valid (finite and > 0),
the mask (if given) is nonzero and the prediction holds a depth; metrics are per image, then averaged over images
(``tofdenoise.training.metrics``; PSNR with D_max = 1000 mm, no clamping). An image without a valid pixel is listed
with null values and left out of the mean.

A prediction pixel without a depth is a failure, never a reward, and never a depth of 0 mm: NaN, +-inf, or 0 and
below in a prediction file (0 is a depth file's invalid marker: a 16-bit PNG has no NaN, and ``tofdenoise
denoise`` writes its holes as 0). A pixel the method should have predicted (reference valid, mask nonzero) but left
without a depth is left out of that image's metrics and *counted* as ``nan_px`` (per image and in total); an image
without a predicted depth at any such pixel is a failure row (null metrics, listed in ``failed``, left out of the
mean). A result with ``nan_px > 0`` is therefore not comparable with one without: its mean covers fewer pixels.
(:class:`MapScorer` takes in-memory predictions as they are: a network's output of 0 is a prediction, and scored.)

:func:`evaluate_dirs` returns (``tofdenoise evaluate`` writes it as strict JSON)::

    {"mean": {"psnr_db", "mae_mm", "mse_mm2", "ssim"},
     "images": {"<name>": {"psnr_db", "mae_mm", "mse_mm2", "ssim", "valid_px", "nan_px"}},
     "mae_mm_pooled": float, "num_images": int, "skipped": [names without a valid reference pixel],
     "nan_px": int, "failed": [names without a predicted depth wherever they are evaluated],
     "d_max_mm": float}

With ``edge_jump_mm`` (``tofdenoise evaluate --edge-jump-mm``) the result also holds ``"regions": {"edge_jump_mm",
"edge": R, "off_edge": R, "edge_px_share"}``: the same metrics over the pixels at a depth step of the reference
(``training.metrics.depth_edge_mask``: flying pixels, where a camera mixes two surfaces) and over the rest, each
``R`` a result of the layout above (an image without a pixel of that region is listed in its ``skipped``), and
the share of the scored pixels that are edge pixels.

Bad input raises :class:`EvalInputError` naming the file: missing counterpart, shape mismatch, wrong dtype,
unreadable file, empty or missing folder, two files with the same name less the suffix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tofdenoise.records import json_number
from tofdenoise.training.metrics import D_MAX_MM, METRIC_KEYS, DepthMetrics, depth_edge_mask

__all__ = ["DEPTH_SUFFIXES", "EvalInputError", "MapScorer", "list_maps", "evaluate_dirs"]

DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".npz", ".exr")


class EvalInputError(ValueError):
    """Bad evaluation input; the message names the file or folder."""


def list_maps(folder: str | Path, what: str) -> dict[str, Path]:
    """name -> file for the depth/mask files in ``folder`` and its sub-folders, the name being the file's path below
    ``folder`` less its suffix (``day1/scene_001``); hidden files and folders are left out. Errors for an empty
    folder or two files of one name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EvalInputError(f"{what} folder not found: {folder}")
    found: dict[str, Path] = {}
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder)
        if any(part.startswith(".") for part in rel.parts) or path.suffix.lower() not in DEPTH_SUFFIXES:
            continue
        if not path.is_file():
            continue
        name = rel.with_suffix("").as_posix()
        if name in found:
            raise EvalInputError(f"{what} folder {folder} has two files for '{name}': {found[name]} and {path}")
        found[name] = path
    if not found:
        raise EvalInputError(f"{what} folder {folder} holds no depth file ({', '.join(DEPTH_SUFFIXES)})")
    return found


def _read_depth(path: Path, what: str) -> np.ndarray:
    from tofdenoise.data_modules.io import MIN_MEDIAN_DEPTH_MM, read_depth_mm

    try:
        depth = read_depth_mm(path, what=what).astype(np.float64)
    except (OSError, ValueError) as exc:
        raise EvalInputError(str(exc)) from exc
    with np.errstate(invalid="ignore"):
        valid = depth[np.isfinite(depth) & (depth > 0)]
    # a map in metres (a float .npy of depth / 1000) scored as millimetres gave MAE values 1000x too small, exit 0
    if valid.size and float(np.median(valid)) < MIN_MEDIAN_DEPTH_MM:
        raise EvalInputError(
            f"{what} file {path}: median valid depth {float(np.median(valid)):.4g} is implausible in millimetres "
            f"(below {MIN_MEDIAN_DEPTH_MM:g}); tofdenoise evaluate reads depth in mm "
            "(a map in metres: multiply by 1000)"
        )
    return depth


def _read_prediction(path: Path) -> np.ndarray:
    """A prediction file's depth in mm with its pixels without a depth as NaN: 0 and below (a depth file's invalid
    marker: ``tofdenoise denoise`` writes its holes as 0, and a 16-bit PNG has no NaN) and -inf; NaN and +inf stay.
    Scored as they were, a method's holes counted as a depth of 0 mm (an MAE of the depth itself)."""
    depth = _read_depth(path, "predicted depth")
    with np.errstate(invalid="ignore"):
        return np.where(depth > 0, depth, np.nan)


def _read_mask(path: Path) -> np.ndarray:
    from tofdenoise.data_modules.io import read_array

    try:
        return read_array(path, what="mask", image_dtypes=(np.uint8, np.uint16)) != 0
    except (OSError, ValueError) as exc:
        raise EvalInputError(str(exc)) from exc


def _match(ref: dict[str, Path], other: dict[str, Path], what: str, folder: Path) -> None:
    for stem, path in ref.items():
        if stem not in other:
            raise EvalInputError(
                f"no {what} for reference file {path}: expected {folder}/{stem}.<"
                f"{'|'.join(s.lstrip('.') for s in DEPTH_SUFFIXES)}>"
            )
    extra = sorted(set(other) - set(ref))
    if extra:
        raise EvalInputError(
            f"{what} file {other[extra[0]]} has no reference counterpart ({len(extra)} unmatched file(s) in {folder})"
        )


class MapScorer:
    """Per-image metrics of (prediction, reference, mask) maps, one image at a time, and the result object of the
    module docstring (``evaluate_dirs``, ``inference.capture_eval`` and ``inference.run_eval`` build it this way);
    ``edge_jump_mm``: also score the edge and off-edge pixels apart (the module docstring's ``regions``)."""

    def __init__(self, d_max_mm: float = D_MAX_MM, edge_jump_mm: float | None = None) -> None:
        if edge_jump_mm is not None and not edge_jump_mm > 0:
            raise EvalInputError(f"--edge-jump-mm must be > 0, got {edge_jump_mm}")
        self.d_max_mm = float(d_max_mm)
        self.edge_jump_mm = None if edge_jump_mm is None else float(edge_jump_mm)
        self._metric = DepthMetrics(d_max_mm=d_max_mm)
        self._stems: list[str] = []
        self._nan_px: dict[str, int] = {}
        self._regions = (
            {"edge": MapScorer(d_max_mm), "off_edge": MapScorer(d_max_mm)} if edge_jump_mm is not None else {}
        )

    def add(self, stem: str, pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Score one image: pixels where ``ref`` is finite and > 0, ``mask`` (bool) is true and ``pred`` finite."""
        self._nan_px[stem] = _nonfinite_px(pred, ref, mask)
        index = torch.tensor([len(self._stems)])
        self._stems.append(stem)
        self._metric.update(
            torch.from_numpy(pred), torch.from_numpy(ref), None if mask is None else torch.from_numpy(mask), index=index
        )
        if self._regions:
            edge = depth_edge_mask(torch.from_numpy(ref), self.edge_jump_mm).numpy().reshape(ref.shape)
            scored = np.ones(ref.shape, bool) if mask is None else mask.astype(bool)
            self._regions["edge"].add(stem, pred, ref, scored & edge)
            self._regions["off_edge"].add(stem, pred, ref, scored & ~edge)

    def result(self) -> dict:
        mean = self._metric.compute()
        images: dict[str, dict] = {}
        skipped: list[str] = []
        failed: list[str] = []
        for row in self._metric.per_image_rows():
            stem = self._stems[int(row["index"])]
            images[stem] = {k: json_number(row[k]) for k in METRIC_KEYS}
            images[stem]["valid_px"] = row["valid_px"]
            images[stem]["nan_px"] = self._nan_px[stem]
            if row["valid_px"] == 0:
                (failed if self._nan_px[stem] > 0 else skipped).append(stem)
        out = {
            "mean": {k: json_number(mean[k]) for k in METRIC_KEYS},
            "images": images,
            "mae_mm_pooled": json_number(mean["mae_mm_pooled"]),
            "num_images": self._metric.counts()["images"],
            "skipped": skipped,
            "nan_px": int(sum(self._nan_px.values())),
            "failed": failed,
            "d_max_mm": self.d_max_mm,
        }
        if self._regions:
            edge, off_edge = self._regions["edge"].result(), self._regions["off_edge"].result()
            edge_px = sum(row["valid_px"] for row in edge["images"].values())
            all_px = edge_px + sum(row["valid_px"] for row in off_edge["images"].values())
            out["regions"] = {
                "edge_jump_mm": self.edge_jump_mm,
                "edge": edge,
                "off_edge": off_edge,
                "edge_px_share": json_number(edge_px / all_px if all_px else float("nan")),
            }
        return out


def evaluate_dirs(
    pred_dir: str | Path,
    ref_dir: str | Path,
    mask_dir: str | Path | None = None,
    d_max_mm: float = D_MAX_MM,
    edge_jump_mm: float | None = None,
) -> dict:
    """Compute the result object written by ``tofdenoise evaluate`` (see the module docstring)."""
    pred_dir, ref_dir = Path(pred_dir), Path(ref_dir)
    refs = list_maps(ref_dir, "reference")
    preds = list_maps(pred_dir, "prediction")
    _match(refs, preds, "prediction", pred_dir)
    masks: dict[str, Path] = {}
    if mask_dir is not None:
        masks = list_maps(mask_dir, "mask")
        _match(refs, masks, "mask", Path(mask_dir))
    scorer = MapScorer(d_max_mm, edge_jump_mm)
    for stem in sorted(refs):
        ref = _read_depth(refs[stem], "reference depth")
        pred = _read_prediction(preds[stem])
        if pred.shape != ref.shape:
            raise EvalInputError(
                f"predicted depth file {preds[stem]} has shape {pred.shape}; expected {ref.shape} like {refs[stem]}"
            )
        mask = None
        if masks:
            mask = _read_mask(masks[stem])
            if mask.shape != ref.shape:
                raise EvalInputError(
                    f"mask file {masks[stem]} has shape {mask.shape}; expected {ref.shape} like {refs[stem]}"
                )
        scorer.add(stem, pred, ref, mask)
    return scorer.result()


def _nonfinite_px(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None) -> int:
    """Pixels to be evaluated (reference finite and > 0, mask nonzero) where the prediction is NaN or inf (a prediction
    file's pixels without a depth are NaN by then: :func:`_read_prediction`)."""
    with np.errstate(invalid="ignore"):
        wanted = np.isfinite(ref) & (ref > 0)
    if mask is not None:
        wanted &= mask
    return int((wanted & ~np.isfinite(pred)).sum())
