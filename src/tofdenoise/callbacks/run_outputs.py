"""The records of a run folder, the same for both front ends (``tofdenoise train`` and ``tofdenoise fit|test``).

:class:`RunOutputs` writes into ``dirpath`` (default: ``trainer.default_root_dir``), every file atomically, on
the global-zero process only (file names in :mod:`tofdenoise.records`):

- ``run_info.json``: ``{"backbone", "noise", "loss", "run_name", "data", "seed", "started"}`` once Lightning has
  restored the checkpoint it was given (train start of ``fit``, test start of ``test``), so an attempt that fails
  to load its checkpoint (a broken file, a checkpoint of another architecture) leaves the records of the earlier
  attempt untouched. A resumed fit keeps the first attempt's ``started`` and adds ``resumed``. After fit it adds
  ``global_step``, ``best_ckpt`` (the best checkpoint, ``null`` when none was written) and, when the run has a
  :class:`~tofdenoise.callbacks.training_cost.TrainingCost` callback, its ``train_seconds``, ``train_images``,
  ``train_images_per_second``, ``peak_gpu_memory_gib`` and ``peak_rss_gib``; after test
  ``finished``, ``global_step`` and ``best_ckpt`` (the checkpoint tested, ``null`` for the weights in memory).
  A fit with nothing left to train (resumed at its last epoch) writes the records at fit end.
- a test of a fitted run's own best checkpoint in its folder (``records.training_state`` FITTED; the front ends refuse
  any other test there) keeps the fit's ``run_info.json`` and ``config.yaml`` and adds ``tested`` and ``finished``.
- an attempt that does not resume (a fresh fit, a test) first removes an earlier attempt's results from the folder
  (``records.RESULT_RECORDS``: ``metrics.json``, ``per_image/`` and the per-scene records), so that no record of
  another run stays beside its ``run_info.json`` (the checkpoint callback removes the earlier checkpoints).
- ``config.yaml``: ``config_text`` when a front end sets it, with ``run_info.json`` (the Hydra entry point
  stores its resolved config; LightningCLI saves its own through ``SaveConfigCallback``).
- at test end: ``metrics.json`` (``write_test_outputs``: the final test metrics per set, restored and raw, the
  samples the datamodule left out counted in ``skipped_images``, and the learned guard's run-level fields) and
  ``per_image/<set>.csv``.

The run-level fields come from the run itself: ``backbone`` / ``loss`` from the LightningModule's
hyper-parameters, ``noise`` / ``data`` (the source) from the datamodule's, ``seed`` from Lightning's
``seed_everything`` (``PL_GLOBAL_SEED``), ``run_name`` from ``name`` (default ``<backbone>-<noise>-<loss>``),
``commit`` / ``commit_dirty`` / ``commit_describe`` from the checkout the package runs from
(:func:`tofdenoise.records.code_commit`), ``machine`` from the process (:func:`run_machine`: CPU model and count,
torch's version and thread count, the accelerator and, on CUDA, the GPU's name).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.trainer.states import TrainerFn

from tofdenoise.atomic import atomic_write_text
from tofdenoise.callbacks.training_cost import TrainingCost
from tofdenoise.records import (
    FITTED,
    METRICS_NAME,
    PER_IMAGE_DIR,
    RUN_INFO_NAME,
    code_commit,
    code_digest,
    host_machine,
    read_record,
    remove_results,
    training_state,
    write_metrics_json,
    write_per_image_csv,
    write_run_info,
)

__all__ = ["RunOutputs", "run_machine", "write_test_outputs"]

#: test set name -> the datamodule's ``skipped_samples`` key of the samples it left out before testing
_SKIP_KEYS = {"synthetic": "test", "simulated": "test", "real": "real"}
CONFIG_NAME = "config.yaml"


def run_machine(trainer: pl.Trainer | None = None) -> dict[str, Any]:
    """What a run trains on: :func:`~tofdenoise.records.host_machine` (CPU model, logical CPUs, architecture, OS)
    with ``torch`` (version), ``torch_threads`` (intra-op threads), ``accelerator`` (the trainer's: ``cpu``,
    ``cuda``, ...; None without a trainer) and ``gpu`` (the CUDA device's name, None elsewhere)."""
    accelerator = type(trainer.accelerator).__name__ if trainer is not None else None
    device = trainer.strategy.root_device if trainer is not None else torch.device("cpu")
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else None
    name = accelerator.removesuffix("Accelerator").lower() if accelerator else None
    return {
        **host_machine(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "accelerator": name,
        "gpu": gpu,
    }


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def write_test_outputs(model: Any, run_dir: Path) -> dict[str, Any]:
    """``<run_dir>/metrics.json`` (final test metrics per set, restored + raw, and the learned guard's run-level
    fields ``trained_steps``, ``best_val_mae_mm``, ``raw_val_mae_mm``, ``learned_margin``, ``learned``,
    ``learned_reason`` from ``model.learned_record()``) and ``<run_dir>/per_image/<set>.csv`` from a
    ``DepthRestorer`` after ``trainer.test``; returns what ``metrics.json`` holds."""
    run_dir = Path(run_dir)
    results = dict(getattr(model, "test_results", {}) or {})
    if not results:
        raise RuntimeError("no test results to write: trainer.test produced no test set")
    results = _with_dataset_skips(results, model)
    for set_name, per in (getattr(model, "test_per_image", {}) or {}).items():
        write_per_image_csv(
            run_dir / PER_IMAGE_DIR / f"{set_name}.csv", per["rows"], per["raw_rows"], names=per["names"]
        )
    write_metrics_json(run_dir / METRICS_NAME, results, run=model.learned_record())
    return json.loads((run_dir / METRICS_NAME).read_text())


def _with_dataset_skips(results: dict[str, Any], model: Any) -> dict[str, Any]:
    """Add the samples the datamodule left out of a test set (no valid pixel, a capture scene without an input
    frame) to that set's ``skipped_images``: they never reached the metric, which counts only its own."""
    trainer = getattr(model, "_trainer", None)
    skipped = getattr(getattr(trainer, "datamodule", None), "skipped_samples", None) or {}
    out = {}
    for set_name, entry in results.items():
        n = len(skipped.get(_SKIP_KEYS.get(set_name, set_name), []))
        if n and isinstance(entry, dict):
            entry = {**entry, "skipped_images": int(entry.get("skipped_images") or 0) + n}
        out[set_name] = entry
    return out


def _hparam(obj: Any, key: str, default: Any = None) -> Any:
    hparams = getattr(obj, "hparams", None) or {}
    value = hparams.get(key, default) if hasattr(hparams, "get") else default
    return None if value is None else str(value)


class RunOutputs(Callback):
    """``run_info.json`` (+ ``config.yaml``) after the checkpoint is restored, ``metrics.json`` and the per-image
    CSVs at test end (see the module docstring).

    Args:
        dirpath: folder of the records; ``None``: ``trainer.default_root_dir``.
        name: the run's name in ``run_info.json`` (``run_name``); ``None``: ``<backbone>-<noise>-<loss>``.

    Attributes:
        config_text: the resolved config written as ``config.yaml`` with the records (``None``: not written).
        metrics: what the last ``metrics.json`` holds (``None`` before a test).
        started: when this callback was built (the attempt's ``started`` unless it resumes an earlier one).
    """

    def __init__(self, dirpath: str | None = None, name: str | None = None) -> None:
        self.dirpath, self.name = dirpath, name
        self.config_text: str | None = None
        self.metrics: dict[str, Any] | None = None
        self.run_info: dict[str, Any] = {}
        self.pending = True
        self.kept_fit = False  # a test of a fitted run keeps the fit's record (_write_records)
        self.started = _now()  # the attempt starts when its callbacks are built

    def run_dir(self, trainer: pl.Trainer) -> Path:
        return Path(self.dirpath if self.dirpath is not None else trainer.default_root_dir).expanduser().resolve()

    def _describe(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        backbone, loss = _hparam(pl_module, "backbone"), _hparam(pl_module, "loss")
        datamodule = getattr(trainer, "datamodule", None)
        noise, source = _hparam(datamodule, "noise"), _hparam(datamodule, "source", "procedural")
        seed = os.environ.get("PL_GLOBAL_SEED")
        summary = getattr(datamodule, "summary", None)  # ToFDataModule: split sizes, skipped samples, noise, cache
        return {
            "backbone": backbone,
            "noise": noise,
            "loss": loss,
            "run_name": str(self.name) if self.name is not None else f"{backbone}-{noise}-{loss}",
            "data": source,
            "seed": int(seed) if seed not in (None, "") else None,
            "started": self.started,
            "prepared_data": summary() if callable(summary) else None,
            # fine-tuning: the weights this run started from (model.init_weights), path and sha256
            "init_weights": getattr(pl_module, "init_record", None),
            # the code that trained it: commit, whether tracked files differed from it, git describe; and its digest
            **code_commit(),
            "code_digest": code_digest(),
            # what trained it: CPU training is bit-identical only on the same machine kind and thread count
            "machine": run_machine(trainer),
        }

    def _write_records(self, trainer: pl.Trainer, pl_module: pl.LightningModule, resumed: bool) -> None:
        """The attempt's ``run_info.json`` and ``config.yaml`` (once per attempt, global zero only)."""
        if not self.pending or not trainer.is_global_zero:
            return
        run_dir = self.run_dir(trainer)
        path = run_dir / RUN_INFO_NAME
        if trainer.state.fn == TrainerFn.TESTING and training_state(run_dir) == FITTED:
            # a test of the fitted run's own best checkpoint (both front ends refuse any other test there): the fit's
            # record stays (steps, training cost, start, code, config), the test adds when it ran
            self.run_info = {**(read_record(path) or {}), "tested": _now()}
            self.kept_fit = True
            write_run_info(run_dir, self.run_info)
            self.pending = False
            return
        self.run_info = self._describe(trainer, pl_module)
        if not resumed:  # a fresh start: no result of an earlier attempt stays beside this one's run_info.json
            removed = remove_results(run_dir)
            if removed:
                print(f"{run_dir}: a fresh start: removed the earlier run's {', '.join(removed)}", file=sys.stderr)
        if resumed and path.is_file():
            try:
                started = json.loads(path.read_text(encoding="utf-8")).get("started")
            except (OSError, ValueError, AttributeError):
                started = None
            if started:
                self.run_info["resumed"] = _now()
                self.run_info["started"] = started
        write_run_info(run_dir, self.run_info)
        if self.config_text is not None:
            atomic_write_text(run_dir / CONFIG_NAME, self.config_text)
        self.pending = False

    def _update(self, trainer: pl.Trainer, **fields: Any) -> None:
        if trainer.is_global_zero:
            self.run_info.update(fields)
            write_run_info(self.run_dir(trainer), self.run_info)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._write_records(trainer, pl_module, resumed=trainer.ckpt_path is not None)

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # a resumed fit with nothing left to train never reaches on_train_start
        self._write_records(trainer, pl_module, resumed=trainer.ckpt_path is not None)
        cb = trainer.checkpoint_callback
        best = getattr(cb, "best_model_path", "") if cb is not None else ""
        cost = next((c.summary() for c in trainer.callbacks if isinstance(c, TrainingCost)), {})
        self._update(trainer, global_step=int(trainer.global_step), best_ckpt=best or None, **cost)

    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._write_records(trainer, pl_module, resumed=False)

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        self.metrics = write_test_outputs(pl_module, self.run_dir(trainer))
        ckpt = trainer.ckpt_path
        if self.kept_fit:  # the fit's steps stay; its best checkpoint is the one tested, named where it lies now
            self._update(trainer, finished=_now(), **({} if ckpt is None else {"best_ckpt": str(ckpt)}))
            return
        self._update(
            trainer,
            finished=_now(),
            global_step=int(trainer.global_step),
            best_ckpt=None if ckpt is None else str(ckpt),
        )
