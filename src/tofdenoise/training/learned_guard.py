"""The learned guard's inputs during a run: which steps, validation MAE and raw MAE a verdict is judged on.

The rule itself (when a run counts as learned) lives in :func:`tofdenoise.records.learned_verdict`;
this module only keeps its inputs for ``DepthRestorer``:

- the lowest validation MAE and the raw validation MAE seen by a fit (sanity checks excluded), float64;
- where the verdict's inputs come from, in this order: the fit of this process (live while it runs, frozen at
  its end), else the record saved in the checkpoint last loaded (a test of a saved checkpoint: the steps
  behind those weights), else nothing (0 steps: an untrained network);
- the record saved in and restored from a checkpoint (plain values: checkpoints load with weights_only=True).

A classical filter (no trainable parameters) gets :func:`~tofdenoise.records.classical_verdict` with
the validation MAEs of its parameter search (:meth:`LearnedGuard.record_tuning`).
"""

from __future__ import annotations

import math
from typing import Any

from tofdenoise.records import classical_verdict, learned_verdict

__all__ = ["LEARNED_RECORD_KEY", "LearnedGuard", "MissingGuardRecordError"]

#: key of the learned guard's record inside a checkpoint
LEARNED_RECORD_KEY = "tofdenoise_learned_record"


class MissingGuardRecordError(ValueError):
    """A checkpoint without the learned guard's record: not written by ``DepthRestorer``'s ``on_save_checkpoint``."""


def _record(trained_steps: Any, best_val_mae_mm: Any, raw_val_mae_mm: Any) -> dict[str, Any]:
    return {
        "trained_steps": int(trained_steps or 0),
        "best_val_mae_mm": None if best_val_mae_mm is None else float(best_val_mae_mm),
        "raw_val_mae_mm": None if raw_val_mae_mm is None else float(raw_val_mae_mm),
    }


class LearnedGuard:
    """The inputs of one model's learned-guard verdict (see the module docstring for where they come from)."""

    def __init__(self) -> None:
        self.raw_val_mae_mm: float | None = None
        self.best_val_mae_mm: float | None = None
        self._fitting = False  # a fit ran (or runs) in this process
        self._frozen: dict[str, Any] | None = None  # the record at the end of that fit
        self._loaded: dict[str, Any] | None = None  # the record of the checkpoint last loaded

    def observe_validation(self, val_mae_mm: float, raw_val_mae_mm: float) -> None:
        """One validation epoch of a fit: keep the raw MAE and the lowest restored MAE (non-finite values ignored)."""
        if math.isfinite(raw_val_mae_mm):
            self.raw_val_mae_mm = raw_val_mae_mm
        if math.isfinite(val_mae_mm) and (self.best_val_mae_mm is None or val_mae_mm < self.best_val_mae_mm):
            self.best_val_mae_mm = val_mae_mm

    def record_tuning(self, best_val_mae_mm: float, raw_val_mae_mm: float) -> None:
        """A classical filter's parameter search: the validation MAE of the chosen parameters and the raw one."""
        self.best_val_mae_mm = float(best_val_mae_mm)
        self.raw_val_mae_mm = float(raw_val_mae_mm)

    def start_fit(self) -> None:
        self._fitting, self._frozen = True, None

    def end_fit(self, trainer: Any) -> None:
        self._frozen = self.live(trainer)

    def live(self, trainer: Any) -> dict[str, Any]:
        """Optimiser steps so far, lowest validation MAE (this guard's float64 value, else the checkpoint
        callback's ``best_model_score`` of ``val/mae_mm``) and raw validation MAE."""
        best = self.best_val_mae_mm
        if best is None:
            cb = trainer.checkpoint_callback
            score = getattr(cb, "best_model_score", None)
            if score is not None and getattr(cb, "monitor", None) == "val/mae_mm":
                best = float(score)
        return _record(trainer.global_step, best, self.raw_val_mae_mm)

    def inputs(self, trainer: Any | None) -> dict[str, Any]:
        """The verdict's inputs: this process's fit (frozen, or live while it runs), else the loaded checkpoint's
        record, else 0 steps."""
        if self._frozen is not None:
            return self._frozen
        if self._fitting and trainer is not None:
            return self.live(trainer)
        if self._loaded is not None:
            return self._loaded
        return _record(0, None, None)

    def verdict(self, trainable: bool, margin: float, trainer: Any | None) -> dict[str, Any]:
        """The run-level fields of ``metrics.json`` (``learned_verdict`` or, for a classical filter,
        ``classical_verdict``)."""
        if not trainable:
            return classical_verdict(self.best_val_mae_mm, self.raw_val_mae_mm, margin=margin)
        rec = self.inputs(trainer)
        return learned_verdict(rec["trained_steps"], rec["best_val_mae_mm"], rec["raw_val_mae_mm"], margin=margin)

    def save(self, checkpoint: dict[str, Any], trainer: Any) -> None:
        checkpoint[LEARNED_RECORD_KEY] = self.live(trainer)

    def load(self, checkpoint: dict[str, Any]) -> None:
        """Restore the record of a checkpoint (validation MAEs continue across a resume); a checkpoint without
        one was not written by ``DepthRestorer`` and is refused."""
        saved = checkpoint.get(LEARNED_RECORD_KEY)
        if not isinstance(saved, dict):
            raise MissingGuardRecordError(
                f"checkpoint has no '{LEARNED_RECORD_KEY}' record: it was not written by DepthRestorer "
                "(to start a network from foreign weights use model.init_weights, which reads weights only)"
            )
        self._loaded = _record(saved.get("trained_steps"), saved.get("best_val_mae_mm"), saved.get("raw_val_mae_mm"))
        if self.raw_val_mae_mm is None:
            self.raw_val_mae_mm = self._loaded["raw_val_mae_mm"]
        if self.best_val_mae_mm is None:
            self.best_val_mae_mm = self._loaded["best_val_mae_mm"]
