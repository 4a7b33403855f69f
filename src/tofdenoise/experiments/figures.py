"""The paper's qualitative figures from the runs of its tables: Fig. 7 (synthetic test set) and Fig. 8 (real set).

A figure is a few scenes of one test set, each shown as the network input, one column per method (a row of the
paper's tables, i.e. a run, for one seed) and the reference; under every depth map, its absolute error against
the reference on one shared millimetre scale, with the scene's MAE in the title (``visualize.compose_panel``).

Nothing is chosen by result. The scenes are evenly spaced through the test set (:func:`pick_indices`). Every
prediction is the one the run's test scored: the run's best checkpoint restores the test loader's input
through ``DepthRestorer.restore_mm`` with the evaluation tile size, as ``DepthRestorer.test_step`` does.
:func:`check_against_records` proves it: each column's per-scene MAE must equal the run's
``per_image/<set>.csv``, and the input's MAE must equal the raw MAE recorded there. A checkpoint, a calibration
or an input that differs from what the tables scored is an error, not a picture.

Paper (``../shared/seeds``, Sec. V): Fig. 7 shows rendered RGB, DVSS-Range, DeepToF, ToF-KPN, RCF, the proposed
method and the ground truth. The built-in scenes have no RGB image, so our Fig. 7 shows the noisy input in its
place. Fig. 8 shows five real scenes: raw, DeepToF, ToF-KPN, RCF, the proposed method and the multi-frame
reference. "Proposed" is DVSS trained on the hetero synthesis with L_full (the paper's configuration).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from tofdenoise.config import compose_config
from tofdenoise.records import BEST_CHECKPOINT, written_provenance

from .runner import RunSpec
from .tables import Row, row_spec, table_rows

__all__ = [
    "FigureSpec",
    "FIGURES",
    "FigureMismatch",
    "figure_rows",
    "figure_specs",
    "pick_indices",
    "render_figure",
    "build_figure",
    "check_against_records",
    "stale_columns",
    "encode_png_palette",
    "FIGURE_PNG",
    "FIGURE_JSON",
]

FIGURE_PNG = "figure.png"
FIGURE_JSON = "figure.json"


class FigureMismatch(ValueError):
    """A figure's prediction or input is not the one the run's test scored."""


@dataclass(frozen=True)
class FigureSpec:
    """A qualitative figure: which test set, which table rows as columns (label, table, row key), how many scenes."""

    key: str
    title: str
    test_set: str  # "synthetic" (the test split) or "real" (the capture set)
    columns: tuple[tuple[str, str, str], ...]
    scenes: int
    input_label: str
    reference_label: str
    #: what differs from the paper's figure (the results page prints it)
    note: str = ""


#: "Ours": the paper's proposed configuration, DVSS trained on the hetero synthesis with L_full
_PROPOSED = ("Ours", "1", "dvss_full")
_BASELINES = (("DeepToF", "1", "deeptof"), ("ToF-KPN", "1", "tofkpn"), ("RCF", "1", "rcf"))

FIGURES: dict[str, FigureSpec] = {
    "fig7": FigureSpec(
        "fig7",
        "Fig. 7: qualitative comparison on the synthetic test set",
        "synthetic",
        (("DVSS-Range", "3", "dvss_range"), *_BASELINES, _PROPOSED),
        scenes=3,
        input_label="Input",
        reference_label="GT",
        note="The paper's first column is the rendered RGB image; the built-in scenes have none, so the noisy "
        "input is shown in its place.",
    ),
    "fig8": FigureSpec(
        "fig8",
        "Fig. 8: results on the real set (the second camera's captures)",
        "real",
        (*_BASELINES, _PROPOSED),
        scenes=5,
        input_label="Raw",
        reference_label="Reference",
        note="The real set is the second simulated camera's capture set (docs/camera-tutorial.md); the reference "
        "is the mean of its valid high-exposure frames.",
    ),
}


def figure_rows(spec: FigureSpec) -> list[tuple[str, Row]]:
    """``(label, Row)`` of every column, in order."""
    out = []
    for label, table, key in spec.columns:
        rows = {r.key: r for r in table_rows(table)}
        if key not in rows:
            raise ValueError(f"{spec.key}: table {table} has no row {key!r}")
        if key == "raw" or rows[key].kind != "train":
            raise ValueError(f"{spec.key}: column {label!r} must be a trained row (the input is shown anyway)")
        out.append((label, rows[key]))
    return out


def figure_specs(spec: FigureSpec, seed: int, common: Sequence[str] = ()) -> list[RunSpec]:
    """The runs the figure's columns need for ``seed`` (the same folders as the tables' runs)."""
    tables = [table for _, table, _ in spec.columns]
    return [row_spec(row, seed, common, table=table) for table, (_, row) in zip(tables, figure_rows(spec))]


def pick_indices(n: int, k: int) -> list[int]:
    """``k`` indices evenly spaced over ``0..n-1`` (first and last included; all of them when ``k >= n``)."""
    if n < 1:
        raise ValueError("pick_indices: the test set is empty")
    if k >= n:
        return list(range(n))
    if k == 1:
        return [0]
    return sorted({round(i * (n - 1) / (k - 1)) for i in range(k)})


def render_figure(
    spec: FigureSpec,
    models: Mapping[str, Any],
    dataset: Any,
    indices: Sequence[int],
    max_tile: int = 320,
    min_tile: int | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The figure (uint8 RGB) and its record: per scene, the MAE of the input and of every column.

    ``models``: label -> ``DepthRestorer`` in eval mode (the columns, in order); ``dataset``: the test set's
    dataset (items with ``noisy``, ``clean``, ``mask``, ``amplitude``, ``name``). Predictions run on each model's
    device through ``restore_mm`` with its ``tiling.eval_tile_px``; MAE is ``depth_metrics_per_image`` over the scoring
    mask (the test metrics' function).
    """
    import torch
    from torch.utils.data import default_collate

    from tofdenoise.training.metrics import depth_metrics_per_image
    from tofdenoise.visualize import compose_panel, stack_panels

    if not models:
        raise ValueError(f"{spec.key}: no column to show")
    d_max = float(next(iter(models.values())).hparams.d_max_mm)
    panels, scenes = [], []
    for index in indices:
        item = dataset[index]
        batch = default_collate([item])  # a batch of one, as the test loader (eval_batch_size 1) gives it
        clean, mask = batch["clean"], batch["mask"]
        maps: dict[str, np.ndarray] = {spec.input_label: batch["noisy"][0, 0].numpy()}
        mae = {spec.input_label: float(depth_metrics_per_image(batch["noisy"], clean, mask, d_max)["mae_mm"][0])}
        for label, model in models.items():
            on_device = {k: v.to(model.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
            with torch.no_grad():
                pred = model.restore_mm(on_device, tile=model.tiling.eval_tile_px).float().cpu()
            mae[label] = float(depth_metrics_per_image(pred, clean, mask, d_max)["mae_mm"][0])
            maps[label] = pred[0, 0].numpy()
        maps[spec.reference_label] = clean[0, 0].numpy()
        name = str(item["name"])
        panels.append(
            compose_panel(
                maps,
                mask=mask[0, 0].numpy(),
                reference_key=spec.reference_label,
                max_tile=max_tile,
                min_tile=min_tile,
                title=f"{spec.test_set} scene {name} (index {index})",
            )
        )
        scenes.append({"index": int(index), "name": name, "mae_mm": mae})
    record = {
        "figure": spec.key,
        "title": spec.title,
        "test_set": spec.test_set,
        "input": spec.input_label,
        "reference": spec.reference_label,
        "columns": list(models),
        "note": spec.note,
        "scenes": scenes,
    }
    return stack_panels(panels, gap=10), record


def encode_png_palette(image_rgb: np.ndarray, colors: int = 256) -> bytes:
    """A uint8 RGB image as an 8-bit palette PNG (median-cut palette, no dithering): about a third of the RGB
    file for colour-mapped panels, whose colours come from two 256-entry colour maps, greys and text."""

    if image_rgb.dtype != np.uint8 or image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ValueError(f"encode_png_palette: expected uint8 (H, W, 3), got {image_rgb.dtype} {image_rgb.shape}")
    image = Image.fromarray(np.ascontiguousarray(image_rgb), "RGB")
    paletted = image.quantize(colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    buf = io.BytesIO()
    paletted.save(buf, "PNG", optimize=True)
    return buf.getvalue()


def _per_image_rows(path: Path) -> dict[str, dict[str, str]]:
    if not path.is_file():
        raise FigureMismatch(f"{path}: missing; the run has no per-image test record of this set")
    with path.open(newline="") as f:
        return {row["name"]: row for row in csv.DictReader(f)}


def stale_columns(record: Mapping[str, Any], run_dirs: Mapping[str, Path]) -> list[str]:
    """The columns of a figure record whose run was trained again after the figure was drawn: the run's
    ``run_info.json`` ``started`` is later than the figure's ``provenance.written`` (both ISO 8601 UTC). Their
    predictions are of the earlier training, which the run's record no longer holds: the page says so and the
    figure is drawn again (``reproduce --figure``) once the other columns' checkpoints are at hand."""
    written = str((record.get("provenance") or {}).get("written") or "")
    stale = []
    for label, run_dir in run_dirs.items():
        try:
            started = str(json.loads((Path(run_dir) / "run_info.json").read_text()).get("started") or "")
        except (OSError, ValueError):
            continue
        if written and started > written:
            stale.append(label)
    return stale


def check_against_records(
    record: Mapping[str, Any], run_dirs: Mapping[str, Path], tol_mm: float = 1e-3, skip: Sequence[str] = ()
) -> None:
    """Raise :class:`FigureMismatch` unless every scene's input MAE equals each run's recorded raw MAE and each
    column's MAE equals its run's recorded MAE (``per_image/<set>.csv``), within ``tol_mm``; the columns in
    ``skip`` (:func:`stale_columns`) are not compared."""
    test_set = record["test_set"]
    for label, run_dir in run_dirs.items():
        if label in skip:
            continue
        path = Path(run_dir) / "per_image" / f"{test_set}.csv"
        rows = _per_image_rows(path)
        for scene in record["scenes"]:
            row = rows.get(scene["name"])
            if row is None:
                raise FigureMismatch(f"{path}: no row for scene {scene['name']!r}: not the test set the run scored")
            for shown, column in ((scene["mae_mm"][record["input"]], "raw_mae_mm"), (scene["mae_mm"][label], "mae_mm")):
                recorded = float(row[column])
                if not math.isclose(shown, recorded, rel_tol=0.0, abs_tol=tol_mm):
                    what = "input" if column == "raw_mae_mm" else f"{label}'s prediction"
                    raise FigureMismatch(
                        f"{path}: scene {scene['name']!r}: the figure's {what} has MAE {shown:.4f} mm, the run's "
                        f"test recorded {column} = {recorded:.4f} mm; the figure would not show what the table scored"
                    )


def build_figure(
    spec: FigureSpec, seed: int, specs: Sequence[RunSpec], out_dir: Path, device: str = "auto"
) -> tuple[np.ndarray, dict[str, Any]]:
    """Render ``spec`` from the finished runs ``specs`` (:func:`figure_specs`, in column order) under ``out_dir``
    and check it against their records; the figure (uint8 RGB) and its record.

    The test set is built from the proposed column's overrides (every column's run has the same data, sensor
    and evaluation noise; the check against each run's raw MAE confirms it). On CUDA the networks run under bf16
    autocast when the runs' trainer did (``trainer.precision``), as their test did.
    """

    import torch
    from hydra.utils import instantiate

    from tofdenoise.inference.denoise import load_restorer, resolve_device

    labels = [label for label, _ in figure_rows(spec)]
    if len(specs) != len(labels):
        raise ValueError(f"{spec.key}: {len(specs)} runs for {len(labels)} columns")
    run_dirs = {label: Path(out_dir) / s.name for label, s in zip(labels, specs)}
    cfg = compose_config(list(specs[-1].overrides))
    datamodule = instantiate(cfg.data, _convert_="all")
    datamodule.prepare_data()
    datamodule.setup("test")
    key = "test" if spec.test_set == "synthetic" else "real"
    if key not in datamodule.datasets:
        raise ValueError(f"{spec.key}: the runs' data has no {spec.test_set} test set (set data.real_dir)")
    dataset = datamodule.datasets[key]
    dev = resolve_device(device)
    models = {label: load_restorer(d / BEST_CHECKPOINT, dev) for label, d in run_dirs.items()}
    bf16 = dev.type == "cuda" and "bf16" in str(cfg.trainer.get("precision", ""))
    with torch.autocast("cuda", dtype=torch.bfloat16) if bf16 else nullcontext():
        image, record = render_figure(spec, models, dataset, pick_indices(len(dataset), spec.scenes))
    check_against_records(record, run_dirs, tol_mm=1e-3 if dev.type == "cpu" else 1e-2)
    record["seed"] = int(seed)
    record["runs"] = {label: s.name for label, s in zip(labels, specs)}
    record["provenance"] = written_provenance()  # when, with which code and where it was rendered
    return image, record
