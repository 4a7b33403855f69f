"""The classical row's job (``tofdenoise classic``): tune a joint bilateral filter on validation, test it.

Flow: compose ``configs/classical.yaml`` (it includes ``train.yaml``: the same data, noise, sensor, experiment
and paths overrides as ``tofdenoise train``, hence the same validation and test images) -> build the
datamodule -> **tune**: every point of ``classical.grid`` (the product of its lists) restores every validation
image through ``DepthRestorer.restore_mm`` with backbone ``bilateral`` and is scored by ``DepthMetrics``
(the validation metrics of the networks); the lowest validation MAE wins (ties: the first point in grid order)
-> ``tuning.json`` (every point's validation metrics, the raw input's, the choice) -> **test**: a
``DepthRestorer`` with the chosen parameters goes through ``trainer.test`` exactly like a trained network, and
``tofdenoise.callbacks.run_outputs.write_test_outputs`` writes ``metrics.json`` (run-level fields from
``training.results.classical_verdict``: ``method_kind`` "classical", 0 steps, the tuned validation MAE) and
``per_image/<set>.csv`` -> ``run_info.json`` and ``config.yaml``. Every file is written atomically.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from lightning.pytorch import seed_everything
from omegaconf import DictConfig, OmegaConf, open_dict

from tofdenoise.atomic import atomic_write_text
from tofdenoise.callbacks.run_outputs import write_test_outputs
from tofdenoise.config import instantiate_node
from tofdenoise.experiments.train_job import record_calibration, validate_config
from tofdenoise.models import available_backbones, is_trainable
from tofdenoise.records import TRUTH_NAME, code_commit, code_digest, json_number, write_run_info, write_scene_record
from tofdenoise.run_lock import RunLock
from tofdenoise.training.metrics import DepthMetrics
from tofdenoise.training.module import DepthRestorer

__all__ = ["run", "grid_points", "tune", "select_best", "TUNING_NAME", "GRID_KEYS", "DEFAULT_BACKBONE"]

log = logging.getLogger("tofdenoise.classic")

TUNING_NAME = "tuning.json"
DEFAULT_BACKBONE = "bilateral"
#: the parameters a grid may search (``JointBilateral`` arguments)
GRID_KEYS = ("sigma_spatial_px", "sigma_depth_mm", "amplitude_power", "radius_px")
#: DepthRestorer settings taken from the composed ``model`` config when present (the evaluation protocol)
#: the DepthRestorer settings of the composed ``model`` config a classical filter keeps (it has no optimiser)
_MODEL_KEYS = ("conditioning", "tiling", "d_max_mm", "learned_margin")


def grid_points(grid: Mapping[str, Any], fixed: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
    """The product of the grid's lists in order (last key fastest), each point completed by ``fixed``.

    Raises ValueError naming the key for an unknown parameter, an empty list or a key both searched and fixed.
    """
    fixed = {k: v for k, v in dict(fixed or {}).items() if v is not None}
    unknown = sorted(set(grid) - set(GRID_KEYS)) + sorted(set(fixed) - set(GRID_KEYS))
    if unknown:
        raise ValueError(f"classical.grid: unknown parameter(s) {unknown}; valid: {list(GRID_KEYS)}")
    if not grid:
        raise ValueError("classical.grid: no parameter to search")
    keys = list(grid)
    values = []
    for key in keys:
        v = grid[key]
        v = list(v) if isinstance(v, (list, tuple)) else [v]
        if not v:
            raise ValueError(f"classical.grid.{key}: empty list")
        bad = [x for x in v if isinstance(x, bool) or not isinstance(x, (int, float))]
        if bad:
            raise ValueError(f"classical.grid.{key}: expected numbers (inf is written inf), got {bad[0]!r}")
        if key in fixed:
            raise ValueError(f"classical.grid.{key} is searched and also fixed (classical.{key}); keep one")
        values.append(v)
    return [{**dict(zip(keys, combo)), **fixed} for combo in itertools.product(*values)]


def select_best(scores: Sequence[Mapping[str, Any]], key: str = "val_mae_mm") -> int:
    """Index of the lowest finite ``key`` (the first of equal ones); ValueError when none is finite."""
    best, best_value = None, math.inf
    for i, s in enumerate(scores):
        v = s.get(key)
        if v is not None and math.isfinite(float(v)) and float(v) < best_value:
            best, best_value = i, float(v)
    if best is None:
        raise ValueError(f"no grid point has a finite {key}: the validation split has no valid pixel")
    return best


def _to_device(batch: Mapping[str, Any], device: torch.device) -> dict[str, Any]:
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def tune(
    models: Sequence[Any],
    loader: Iterable[Mapping[str, Any]],
    device: torch.device | str = "cpu",
    d_max_mm: float = 1000.0,
) -> tuple[list[dict[str, float]], dict[str, float], int]:
    """Validation metrics of each model (``DepthRestorer``s) in one pass over ``loader``, plus the raw input's.

    Returns (per model ``{"val_psnr_db", "val_mae_mm", "val_mse_mm2", "val_ssim", "val_mae_mm_pooled"}``,
    the raw input's in the same layout, number of images): the validation metrics of the networks
    (``DepthMetrics`` per image then averaged, each image once).
    """

    device = torch.device(device)
    metrics = [DepthMetrics(d_max_mm=d_max_mm).to(device) for _ in models]
    raw = DepthMetrics(d_max_mm=d_max_mm).to(device)
    for model in models:
        model.to(device).eval()
    with torch.no_grad():
        for batch in loader:
            batch = _to_device(batch, device)
            index = batch.get("index")
            for model, metric in zip(models, metrics):
                pred = model.restore_mm(batch, tile=model.tiling.eval_tile_px)
                metric.update(pred, batch["clean"], batch["mask"], index=index)
            raw.update(batch["noisy"], batch["clean"], batch["mask"], index=index)

    def values(m: Any) -> dict[str, float]:
        return {f"val_{k}": float(v) for k, v in m.compute().items()}

    return [values(m) for m in metrics], values(raw), raw.counts()["images"]


def _device(choice: str, cfg: DictConfig) -> torch.device:
    choice = str(choice or "auto")
    if choice == "auto":
        accel = str(cfg.trainer.get("accelerator", "cpu"))
        return torch.device("cuda" if accel in ("gpu", "cuda", "auto") and torch.cuda.is_available() else "cpu")
    if choice not in ("cpu", "cuda"):
        raise ValueError(f"classical.device must be auto, cpu or cuda, got {choice!r}")
    if choice == "cuda" and not torch.cuda.is_available():
        raise ValueError("classical.device=cuda but no CUDA device is available")
    return torch.device(choice)


def _model_kwargs(cfg: DictConfig, backbone: str) -> dict[str, Any]:
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True) if cfg.get("model") is not None else {}
    kwargs = {k: model_cfg[k] for k in _MODEL_KEYS if k in model_cfg}
    # the filter reads depth and amplitude, centred as classical.input_centering says
    conditioning = dict(kwargs.get("conditioning") or {})
    conditioning.update(use_signal_channel=True, centering=str(cfg.classical.input_centering))
    kwargs.update(backbone=backbone, conditioning=conditioning)
    return kwargs


def run(cfg: DictConfig) -> dict[str, Any]:
    """Tune on validation, test the chosen parameters; returns ``{"run_dir", "best", "metrics", "tuning"}``."""

    validate_config(cfg)
    if cfg.get("classical") is None:
        raise ValueError("config: the 'classical' node is missing (compose configs/classical.yaml)")
    ccfg = cfg.classical
    backbone = str(ccfg.get("backbone", DEFAULT_BACKBONE))
    if backbone not in available_backbones() or is_trainable(backbone):
        raise ValueError(
            f"config classical.backbone: {backbone!r} is not a registered classical filter; valid: "
            f"{', '.join(b for b in available_backbones() if not is_trainable(b))}"
        )
    grid = OmegaConf.to_container(ccfg.grid, resolve=True) if ccfg.get("grid") is not None else {}
    points = grid_points(grid, {k: ccfg.get(k) for k in GRID_KEYS if k in ccfg})
    run_dir = Path(str(cfg.paths.run_dir)).expanduser().resolve()
    with RunLock(run_dir):  # one writer per run folder (tofdenoise.run_lock)
        return _tune_and_test(cfg, run_dir, backbone, grid, points)


def _tune_and_test(
    cfg: DictConfig, run_dir: Path, backbone: str, grid: dict[str, Any], points: list[dict[str, Any]]
) -> dict[str, Any]:

    ccfg = cfg.classical
    run_dir.mkdir(parents=True, exist_ok=True)
    with open_dict(cfg):
        cfg.paths.run_dir = str(run_dir)
    device = _device(ccfg.get("device", "auto"), cfg)
    seed_everything(int(cfg.seed), workers=True)
    started = time.strftime("%Y-%m-%dT%H:%M:%S%z")

    base = _model_kwargs(cfg, backbone)
    models = [DepthRestorer(**base, backbone_kwargs=dict(p)) for p in points]  # bad parameters fail here
    datamodule = instantiate_node(cfg.data, "data")  # a bad data setting: one line naming the key
    record_calibration(cfg, datamodule.calib)
    atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    datamodule.prepare_data()
    datamodule.setup("validate")
    t0 = time.perf_counter()
    scores, raw, n_images = tune(models, datamodule.val_dataloader(), device, float(models[0].hparams.d_max_mm))
    tune_s = time.perf_counter() - t0
    best_i = select_best(scores)
    best_params = dict(points[best_i])
    rows = [
        {
            **{k: (json_number(float(v)) if isinstance(v, float) else v) for k, v in p.items()},
            "radius_px_used": int(m.backbone.radius_px),
            **{k: json_number(v) for k, v in s.items()},
        }
        for p, m, s in zip(points, models, scores)
    ]
    tuning = {
        "method": backbone,
        "selection": "lowest validation MAE (val_mae_mm: per image, then averaged)",
        "grid": grid,
        "fixed": {k: ccfg.get(k) for k in GRID_KEYS if ccfg.get(k) is not None},
        "input_centering": base["conditioning"]["centering"],
        "val_images": n_images,
        "device": str(device),
        "seconds": round(tune_s, 3),
        "points": rows,
        "best_index": best_i,
        "best": rows[best_i],
        "raw": {k: json_number(v) for k, v in raw.items()},
    }
    atomic_write_text(run_dir / TUNING_NAME, json.dumps(tuning, indent=2, allow_nan=False) + "\n")
    log.info(
        "%s: best of %d grid points %s (val MAE %.3f mm, raw %.3f mm) in %.1f s",
        backbone,
        len(points),
        best_params,
        scores[best_i]["val_mae_mm"],
        raw["val_mae_mm"],
        tune_s,
    )

    model = models[best_i].cpu()
    model.record_tuning(scores[best_i]["val_mae_mm"], raw["val_mae_mm"])
    del models
    callbacks = []
    summary = (cfg.get("callbacks") or {}).get("summary")
    if summary is not None:
        callbacks.append(instantiate(summary, _convert_="all"))
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=False, enable_checkpointing=False, _convert_="all")
    datamodule.setup("test")
    trainer.test(model, datamodule=datamodule, verbose=False)
    metrics = write_test_outputs(model, run_dir) if trainer.is_global_zero else None
    run_info = {
        "backbone": backbone,
        "method": f"{backbone} (classical)",
        "noise": cfg.noise.name,
        "loss": "none",
        "run_name": str(cfg.run_name),
        "data": str(cfg.data.get("source", "procedural")),
        "seed": int(cfg.seed),
        "started": started,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "global_step": 0,
        "best_ckpt": None,
        "params": rows[best_i],
        "tuning": TUNING_NAME,
        **code_commit(),
        "code_digest": code_digest(),
    }
    if trainer.is_global_zero:
        write_truth(model, datamodule, run_dir)
        write_run_info(run_dir, run_info)
    return {"run_dir": str(run_dir), "best": best_params, "metrics": metrics, "tuning": tuning}


def write_truth(model: Any, datamodule: Any, run_dir: Path) -> bool:
    """``<run_dir>/real_vs_truth.json``: the tuned filter's capture-set predictions against the rendered truth of a
    simulated capture set (``inference.capture_eval.evaluate_on_captures``, what ``tofdenoise reproduce`` writes for
    a learned run from its checkpoint; a filter has no checkpoint, so its job scores itself). Nothing without a
    capture set or without truth (a real camera's); True when written."""
    real_dir = getattr(datamodule, "real_dir", None)
    if not real_dir:
        return False
    from tofdenoise.inference.capture_eval import evaluate_on_captures, has_truth  # heavy: only with a capture set

    if not has_truth(real_dir):
        return False
    hp = datamodule.hparams
    result = evaluate_on_captures(
        model, real_dir, datamodule.calib, float(model.hparams.d_max_mm), hp.real_min_count, precision="fp32"
    )
    body = {"checkpoint": None, "method": "classical", "captures": str(real_dir), **result}
    write_scene_record(run_dir / TRUTH_NAME, body)
    return True
