"""A finished run's own test sets scored again: rebuilt from the run's ``config.yaml``, restored with its best
checkpoint (``tofdenoise evaluate --run RUN_DIR``).

A run's ``metrics.json`` holds one number per metric and set. To ask another question of the same test images (where
the error sits: at depth edges or on surfaces, ``--edge-jump-mm``), the sets are rebuilt exactly as the run built
them (its data settings, calibration and seeds: the same images, noise and holes; the data cache is reused) and
scored with ``evaluation.MapScorer``, so the whole-image means equal the run's recorded test numbers. Sets:

- ``synthetic``: the paper-protocol split (inputs noised as ``data.eval_noise`` says);
- ``simulated``: the simulator-noised split, when the run has one (``data.simulated_test``);
- ``real``: the run's capture set (``data.real_dir``) against its references, only when asked for (rebuilding 200
  scenes' references takes minutes) and when the folder is still there.

Which sets the run had is read from its ``metrics.json``. Returns ``{"run", "checkpoint", "sets": {name:
{"restored": R, "input": R, "inputs_as_recorded": bool}}}`` with each ``R`` as ``evaluation.MapScorer.result``
(``input``: the noisy input scored the same way). ``inputs_as_recorded`` says whether the rebuilt inputs score as
the run's recorded ``raw`` numbers (MAE to 1e-6 mm): a run made by older data code may be rebuilt into other test
images, and then its numbers here are not its record's. Errors (``EvalInputError``) name the run folder and the
missing file or the set that cannot be rebuilt.

The network runs on ``device`` at the precision the run was tested at, its ``trainer.precision`` (Lightning's
precision plugin of that name: its module and input conversion and the autocast of its test step; e.g.
``bf16-mixed`` = bf16 autocast, on the CPU too), unless ``precision`` names another. Until 2026-11-29 it ran in
float32 whatever the run had, so a ``bf16-mixed`` run's numbers were not its record's (``unet-range-l1-s1`` of
``docs/results/gpu-short``: simulated MAE 3.02225 mm here against 3.01173 mm recorded) and the ``regions.json``
written from it came from another precision than the MAE beside them. The numbers equal the record's on the
device type the run was tested on; a GPU run's ``bf16-mixed`` re-run on the CPU uses the CPU's bf16 kernels.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tofdenoise.evaluation import EvalInputError, MapScorer
from tofdenoise.inference.denoise import load_restorer
from tofdenoise.records import BEST_CHECKPOINT, METRICS_NAME, metric_sets, read_metrics_json
from tofdenoise.training.metrics import D_MAX_MM

__all__ = ["PRECISIONS", "RUN_SETS", "evaluate_run", "precision_plugin", "run_precision"]

#: the trainer precisions ``evaluate_run`` reproduces (Lightning's names)
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true")
#: Lightning's short spellings of them, as ``Trainer(precision=...)`` reads them
_PRECISION_ALIASES = {"32": "32-true", "16": "16-mixed", "bf16": "bf16-mixed", "64": "64-true"}

#: the test sets a run can be scored on again, in the order a run tests them
RUN_SETS = ("synthetic", "simulated", "real")
#: the resolved config a training run saves in its folder (``experiments.train_job.CONFIG_NAME``)
CONFIG_NAME = "config.yaml"
#: how far the rebuilt inputs' MAE may be from the record's raw MAE and still be the recorded test images (mm)
INPUT_TOLERANCE_MM = 1e-6


def _wanted_sets(run_dir: Path, data: Any, recorded: Sequence[str], sets: Sequence[str] | None) -> list[str]:
    """The sets to score: ``sets`` checked against those the run was tested on (``recorded``), or (None) its
    synthetic and simulated ones."""
    unknown = [s for s in sets or () if s not in RUN_SETS]
    if unknown:
        raise EvalInputError(f"unknown test set(s) {', '.join(unknown)}; expected some of {', '.join(RUN_SETS)}")
    real_dir = data.get("real_dir")
    wanted = list(sets) if sets else [s for s in ("synthetic", "simulated") if s in recorded]
    missing = [s for s in wanted if s not in recorded]
    if missing:
        raise EvalInputError(
            f"run {run_dir}: its {METRICS_NAME} has no {', '.join(missing)} set: it was tested on "
            f"{', '.join(recorded) or 'nothing'}"
        )
    if "real" in wanted:
        if not real_dir:
            raise EvalInputError(f"run {run_dir}: its config has no data.real_dir: it had no real set")
        if not Path(str(real_dir)).is_dir():
            raise EvalInputError(f"run {run_dir}: its real set {real_dir} (data.real_dir) is not there any more")
    return [s for s in RUN_SETS if s in wanted]


def _unified_precision(value: Any, where: str) -> str:
    text = str(value).strip()
    text = _PRECISION_ALIASES.get(text, text)
    if text not in PRECISIONS:
        raise EvalInputError(f"{where}: precision {value!r} is not one of {', '.join(PRECISIONS)}")
    return text


def run_precision(cfg: Any, config_path: Path) -> str:
    """The precision a run was tested at: its config's ``trainer.precision`` (Lightning's default, ``32-true``, when
    the config has none), in Lightning's unified spelling."""
    trainer = cfg.get("trainer") if hasattr(cfg, "get") else None
    value = trainer.get("precision") if trainer is not None and hasattr(trainer, "get") else None
    return "32-true" if value is None else _unified_precision(value, f"{config_path} (trainer.precision)")


def precision_plugin(precision: str, device: torch.device) -> Any:
    """Lightning's precision plugin for ``precision`` on ``device``, as the run's Trainer built it for its test."""
    from lightning.pytorch.plugins.precision import DoublePrecision, HalfPrecision, MixedPrecision, Precision

    precision = _unified_precision(precision, "precision")
    if precision == "32-true":
        return Precision()
    if precision == "64-true":
        return DoublePrecision()
    if precision.endswith("-mixed"):
        return MixedPrecision(precision, "cuda" if device.type == "cuda" else "cpu")
    return HalfPrecision(precision)


def evaluate_run(
    run_dir: str | Path,
    sets: Sequence[str] | None = None,
    device: str = "auto",
    d_max_mm: float = D_MAX_MM,
    edge_jump_mm: float | None = None,
    log: Callable[[str], None] | None = None,
    precision: str | None = None,
) -> dict[str, Any]:
    """Score the test sets ``sets`` (default: synthetic and, if the run had it, simulated) of the finished run in
    ``run_dir`` again with its best checkpoint (module docstring), at ``precision`` (None: the run's
    ``trainer.precision``). The result's ``precision``: ``{"value", "from"}``."""
    run_dir = Path(run_dir)
    config, ckpt = run_dir / CONFIG_NAME, run_dir / BEST_CHECKPOINT
    metrics_path = run_dir / METRICS_NAME
    for path, what in (
        (config, "the run's resolved config"),
        (ckpt, "its best checkpoint"),
        (metrics_path, "its test metrics"),
    ):
        if not path.is_file():
            raise EvalInputError(f"run {run_dir}: no {path.relative_to(run_dir)} ({what}); expected a finished run")
    recorded = read_metrics_json(metrics_path)
    cfg = OmegaConf.load(config)
    data = cfg.get("data")
    if data is None or "_target_" not in data:
        raise EvalInputError(f"{config}: no 'data' node with a _target_ (the run's data module)")
    if precision is None:
        used = {"value": run_precision(cfg, config), "from": f"{config} (trainer.precision)"}
    else:
        used = {"value": _unified_precision(precision, "--precision"), "from": "--precision"}
    wanted = _wanted_sets(run_dir, data, metric_sets(recorded), sets)
    data.simulated_test = "simulated" in wanted
    if "real" not in wanted:
        data.real_dir = None
    datamodule = instantiate(data)
    datamodule.setup("test")
    model = load_restorer(ckpt, device)
    plugin = precision_plugin(used["value"], model.device)
    model = plugin.convert_module(model)
    results: dict[str, Any] = {}
    with torch.no_grad():
        for name, loader in zip(datamodule.test_set_names, datamodule.test_dataloader()):
            if name not in wanted:
                continue
            restored, noisy = MapScorer(d_max_mm, edge_jump_mm), MapScorer(d_max_mm, edge_jump_mm)
            for b, batch in enumerate(loader):
                batch = plugin.convert_input(batch)  # as the Trainer's test loop: converted, then moved
                batch = {k: v.to(model.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
                with plugin.test_step_context():
                    pred = model.restore_mm(batch, tile=model.tiling.eval_tile_px)
                pred = pred.double().cpu()  # exact for every precision's output (numpy has no bf16)
                clean, inputs = batch["clean"].double().cpu(), batch["noisy"].double().cpu()
                mask = batch["mask"].cpu() != 0
                index = batch.get("index")
                for i in range(pred.shape[0]):
                    stem = str(batch["name"][i]) if "name" in batch else str(int(index[i]) if index is not None else i)
                    restored.add(stem, pred[i, 0].numpy(), clean[i, 0].numpy(), mask[i, 0].numpy())
                    noisy.add(stem, inputs[i, 0].numpy(), clean[i, 0].numpy(), mask[i, 0].numpy())
                if log is not None:
                    log(f"[{name}] batch {b + 1}/{len(loader)}")
            scored = {"restored": restored.result(), "input": noisy.result()}
            raw_mae = ((recorded.get(name) or {}).get("raw") or {}).get("mae_mm")
            got = scored["input"]["mean"]["mae_mm"]
            scored["inputs_as_recorded"] = bool(
                isinstance(raw_mae, (int, float)) and got is not None and abs(got - raw_mae) <= INPUT_TOLERANCE_MM
            )
            results[name] = scored
    return {"run": str(run_dir), "checkpoint": str(ckpt), "precision": used, "sets": results}
