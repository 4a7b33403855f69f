"""The one checkpoint callback of a run: ``best.ckpt`` (lowest validation MAE) and ``last.ckpt``.

Lightning allows a single stateful ``ModelCheckpoint`` per trainer (two raise "Found more than one stateful
callback"), so both files come from this one instance. The metric name contains ``/`` (``val/mae_mm``), which
would create sub-folders inside a filename template: the filename is fixed to ``best`` and
``auto_insert_metric_name`` is off.

``best.ckpt`` is chosen at validation ends only, so its weights are the ones that scored its metric. Lightning's
own step and time triggers (``every_n_train_steps``, ``train_time_interval``) exclude the per-validation one, and at
a step mark they compare the *last* validation's metric with the weights of *that* step: a run with
``every_n_train_steps=500`` kept the weights of step 500, 1000, ... under the score of an earlier validation, and a
run shorter than 500 steps wrote no ``best.ckpt`` at all (it then tested its final weights). Here those two
options refresh ``last.ckpt`` only; Lightning's trigger stays per validation (``every_n_epochs``, default 1).

Lightning 2.6 refreshes ``last.ckpt`` only when a top-k checkpoint was written at the same step. A run must be
resumable from its newest state, so this class also writes ``last.ckpt`` after every validation/epoch end and, with
``every_n_train_steps`` / ``train_time_interval``, every N optimiser steps / that much time, from the first epoch on.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import Any
from weakref import proxy

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.trainer.states import TrainerFn

__all__ = ["BestAndLastCheckpoint", "BEST_NAME", "CheckpointWriteError", "LAST_NAME", "MONITOR"]

BEST_NAME = "best"
LAST_NAME = "last"
MONITOR = "val/mae_mm"


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (e.g. the disk is full): names the file; the previous one is intact."""


class BestAndLastCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` writing ``<dirpath>/best.ckpt`` (best ``monitor``) and ``<dirpath>/last.ckpt``.

    Args:
        dirpath: folder of the two files (the Hydra config uses ``<run_dir>/checkpoints``).
        monitor: logged metric that selects the best checkpoint (default ``val/mae_mm``, lower is better).
        mode: ``"min"`` or ``"max"``.
        every_n_train_steps: also refresh ``last.ckpt`` every N optimiser steps, so a run killed mid-epoch loses
            at most N steps; ``None``/0 = only at validation/epoch end. ``best.ckpt`` is not touched there.
        train_time_interval: the same by wall-clock time.
        every_n_epochs: check ``best`` at every N-th validation's end (default 1).
        verbose: log each save (Lightning's ``ModelCheckpoint`` option).
    """

    def __init__(
        self,
        dirpath: str | Path | None = None,
        monitor: str = MONITOR,
        mode: str = "min",
        every_n_train_steps: int | None = None,
        train_time_interval: timedelta | None = None,
        every_n_epochs: int | None = None,
        verbose: bool = False,
    ) -> None:
        if mode not in ("min", "max"):
            raise ValueError(f"BestAndLastCheckpoint.mode must be 'min' or 'max', got {mode!r}")
        if every_n_train_steps is not None and every_n_train_steps < 0:
            raise ValueError(f"BestAndLastCheckpoint.every_n_train_steps must be >= 0, got {every_n_train_steps}")
        super().__init__(
            dirpath=dirpath,
            filename=BEST_NAME,
            monitor=monitor,
            mode=mode,
            save_top_k=1,
            save_last=True,
            auto_insert_metric_name=False,
            every_n_epochs=every_n_epochs,
            verbose=verbose,
            enable_version_counter=False,
        )
        self.CHECKPOINT_NAME_LAST = LAST_NAME
        #: the refresh triggers of last.ckpt (Lightning's own step/time triggers stay off: module docstring)
        self.last_every_n_train_steps = every_n_train_steps or 0
        self.last_train_time_interval = train_time_interval
        self._last_refresh_time = time.monotonic()

    # ------------------------------------------------------------------ one run's files per folder
    def _own_file(self, name: str) -> Path | None:
        return Path(self.dirpath) / f"{name}{self.FILE_EXTENSION}" if self.dirpath else None

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """A fit that starts afresh (no checkpoint restored) removes ``best.ckpt`` and ``last.ckpt`` of an earlier
        run from the folder: left there, an interrupted new run would resume the earlier one's ``last.ckpt``
        (``ckpt_path=last``), and its records would name the earlier ``best.ckpt`` until its first validation."""
        super().on_train_start(trainer, pl_module)
        if trainer.ckpt_path is not None or not trainer.is_global_zero:
            return
        removed = []
        for name in (BEST_NAME, self.CHECKPOINT_NAME_LAST):
            path = self._own_file(name)
            if path is not None and path.is_file():
                path.unlink()
                removed.append(path.name)
        if removed:
            print(
                f"{self.dirpath}: a fresh start: removed the earlier run's {' and '.join(removed)}",
                file=sys.stderr,
                flush=True,
            )

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Lightning's restore, with the best checkpoint re-based on this folder when the run folder was copied or
        moved: Lightning keeps the other folder's ``best_model_path`` (and its score not), so a copied run tested,
        and recorded, the original folder's ``best.ckpt``, and its first validation replaced the copy's best
        whether or not it was better. Here a ``best.ckpt`` in this folder takes its recorded score; without one
        no best is known yet."""
        super().load_state_dict(state_dict)
        theirs = state_dict.get("dirpath")
        if theirs is None or self.dirpath is None or os.path.realpath(str(theirs)) == os.path.realpath(self.dirpath):
            return
        here, score = self._own_file(BEST_NAME), state_dict.get("best_model_score")
        if here is not None and here.is_file() and score is not None and state_dict.get("best_model_path"):
            self.best_model_path = self.kth_best_model_path = str(here)
            self.best_model_score = self.kth_value = score
            self.best_k_models = {str(here): score}
        else:
            self.best_model_path = ""

    # ------------------------------------------------------------------ atomic writes
    def _save_checkpoint(self, trainer: pl.Trainer, filepath: str) -> None:
        """Write ``filepath`` as a whole or not at all. Lightning streams a checkpoint through an fsspec transaction
        that moves a temporary file from the system's temp folder, a copy across file systems that a full disk
        cuts short (a truncated ``best.ckpt``). Here the checkpoint goes to a temporary name next to
        ``filepath`` and is renamed over it; on failure the temporary file is removed, the previous checkpoint
        stays as it was and the error names the file."""
        folder, name = os.path.split(filepath)
        tmp = os.path.join(folder, f".{name}.tmp-{os.getpid()}")
        try:
            trainer.save_checkpoint(tmp, self.save_weights_only)
            if trainer.is_global_zero:
                os.replace(tmp, filepath)
        except OSError as exc:
            if trainer.is_global_zero:
                with contextlib.suppress(OSError):
                    os.remove(tmp)
            reason = exc.strerror or str(exc)
            raise CheckpointWriteError(
                exc.errno, f"could not write checkpoint {filepath}: {reason}; the previous checkpoint is unchanged"
            ) from None
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.after_save_checkpoint(proxy(self))

    # ------------------------------------------------------------------ last.ckpt always up to date
    _phase: str = "train"
    _last_saved_marker: tuple[str, int] | None = None

    def _save_last_checkpoint(self, trainer: pl.Trainer, monitor_candidates: dict[str, Any]) -> None:
        super()._save_last_checkpoint(trainer, monitor_candidates)
        self._last_saved_marker = (self._phase, trainer.global_step)

    @staticmethod
    def _may_save(trainer: pl.Trainer) -> bool:
        return not (bool(trainer.fast_dev_run) or trainer.state.fn != TrainerFn.FITTING or trainer.sanity_checking)

    def _ensure_last(self, trainer: pl.Trainer) -> None:
        if self.save_last and self._may_save(trainer) and self._last_saved_marker != (self._phase, trainer.global_step):
            # Lightning skips every save at a step that has one already (``_last_global_step_saved``): a refresh of
            # last.ckpt at an epoch's last step would then stop that epoch's validation from choosing best.ckpt
            saved_step = self._last_global_step_saved
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
            self._last_global_step_saved = saved_step
            self._last_refresh_time = time.monotonic()

    def _refresh_due(self, trainer: pl.Trainer) -> bool:
        """Whether ``last.ckpt`` is due after this optimiser step (step mark or time interval; the time decision is
        rank 0's, broadcast, so that every rank saves or none does)."""
        n = self.last_every_n_train_steps
        if n >= 1 and trainer.global_step % n == 0:
            return True
        if self.last_train_time_interval is None:
            return False
        elapsed = time.monotonic() - self._last_refresh_time
        due = elapsed >= self.last_train_time_interval.total_seconds()
        return bool(trainer.strategy.broadcast(due))

    def on_train_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        self._phase = "train"
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if self._refresh_due(trainer):
            self._ensure_last(trainer)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._phase = "epoch"
        super().on_train_epoch_end(trainer, pl_module)
        if self._should_save_on_train_epoch_end(trainer):
            self._ensure_last(trainer)
        self._phase = "train"

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._phase = "val"
        super().on_validation_end(trainer, pl_module)
        if not self._should_save_on_train_epoch_end(trainer):
            self._ensure_last(trainer)
        self._phase = "train"
