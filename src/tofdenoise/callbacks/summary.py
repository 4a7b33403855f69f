"""A readable one-line summary at the end of every fit / test run (stdout, and the Python logger)."""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback

from tofdenoise.records import TEST_SET_LABELS, learned_status

__all__ = ["RunSummary", "format_fit_summary", "format_test_summary", "format_learned_warning"]

log = logging.getLogger(__name__)


def _fmt(value: Any, digits: int = 3) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "n/a"
    if math.isnan(v):
        return "nan"
    return f"{v:.{digits}f}"


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s"


def format_fit_summary(
    name: str,
    epochs: int,
    steps: int,
    seconds: float,
    best_score: Any,
    best_path: str,
    monitor: str,
    raw_mae_mm: Any = None,
) -> str:
    """``[name] fit: 10 epochs, 400 steps in 3m12s | best val/mae_mm 4.21 (raw 9.87) -> .../best.ckpt``."""
    raw = f" (raw {_fmt(raw_mae_mm)})" if raw_mae_mm is not None else ""
    best = f"best {monitor} {_fmt(best_score)}{raw}" if best_score is not None else f"no {monitor} yet"
    where = f" -> {best_path}" if best_path else " (no checkpoint written)"
    return f"[{name}] fit: {epochs} epochs, {steps} steps in {_duration(seconds)} | {best}{where}"


def format_test_summary(name: str, results: dict[str, dict[str, Any]], seconds: float) -> str:
    """``[name] test synthetic [paper protocol (hetero-noised)]: MAE 4.1 mm (raw 9.9), PSNR 45.2 dB (raw 38.1),
    SSIM 0.991 | simulated [simulator-noised]: ...`` (labels: ``records.TEST_SET_LABELS``)."""
    parts = []
    for set_name, res in results.items():
        raw = res.get("raw", {})
        label = f" [{TEST_SET_LABELS[set_name]}]" if set_name in TEST_SET_LABELS else ""
        parts.append(
            f"{set_name}{label}: MAE {_fmt(res.get('mae_mm'), 2)} mm (raw {_fmt(raw.get('mae_mm'), 2)}), "
            f"PSNR {_fmt(res.get('psnr_db'), 2)} dB (raw {_fmt(raw.get('psnr_db'), 2)}), "
            f"SSIM {_fmt(res.get('ssim'), 4)} (raw {_fmt(raw.get('ssim'), 4)})"
        )
    body = " | ".join(parts) if parts else "no test set"
    return f"[{name}] test in {_duration(seconds)} | {body}"


def format_learned_warning(record: dict[str, Any] | None) -> str | None:
    """The learned guard in plain words (``None`` when the run learned): ``WARNING: the network did not learn:
    best val MAE 7.68 mm vs raw 7.79 mm (needs <= 7.40 mm, 5% below raw); treat this run as failed``."""
    if not record:
        return None
    status = learned_status(record)
    reason = str(record.get("learned_reason", ""))
    if status == "did not learn":
        return f"WARNING: the network {reason}; treat this run as failed"
    if status == "not trained":
        return f"WARNING: the network was {reason}"
    if status == "not verified":
        return f"WARNING: learning {reason}; treat this run as unverified"
    return None


class RunSummary(Callback):
    """Prints one line after ``fit`` (epochs, optimiser steps, time, best val MAE and checkpoint) and one
    after ``test`` (per test set: restored vs raw MAE / PSNR / SSIM). Only on global rank 0.

    When the network did not learn (``DepthRestorer.learned_record()``: not trained, best validation MAE not
    ``learned_margin`` below the raw MAE, or no validation to tell), a ``WARNING: ...`` line follows both.

    Args:
        name: run name shown in brackets (the Hydra config passes ``run_name``).
    """

    def __init__(self, name: str = "tofdenoise") -> None:
        self.name = name
        self.lines: list[str] = []
        self._t0 = time.perf_counter()

    def _emit(self, trainer: pl.Trainer, line: str) -> None:
        self.lines.append(line)
        if trainer.is_global_zero:
            print(line, flush=True)
            log.debug(line)  # the Hydra log file keeps it; the console shows the plain line once

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._t0 = time.perf_counter()

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        ckpt = trainer.checkpoint_callback
        best_score = getattr(ckpt, "best_model_score", None) if ckpt is not None else None
        best_path = getattr(ckpt, "best_model_path", "") if ckpt is not None else ""
        monitor = getattr(ckpt, "monitor", None) or "val/mae_mm"
        raw = trainer.callback_metrics.get("val/raw/mae_mm")
        if best_score is None:
            best_score = trainer.callback_metrics.get(monitor)
        self._emit(
            trainer,
            format_fit_summary(
                self.name,
                trainer.current_epoch,
                trainer.global_step,
                time.perf_counter() - self._t0,
                best_score,
                best_path,
                monitor,
                raw,
            ),
        )
        self._warn_if_not_learned(trainer, pl_module)

    def _warn_if_not_learned(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        record_fn = getattr(pl_module, "learned_record", None)
        warning = format_learned_warning(record_fn()) if callable(record_fn) else None
        if warning:
            self._emit(trainer, warning)

    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._t0 = time.perf_counter()

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        results = getattr(pl_module, "test_results", None) or {}
        self._emit(trainer, format_test_summary(self.name, results, time.perf_counter() - self._t0))
        self._warn_if_not_learned(trainer, pl_module)
