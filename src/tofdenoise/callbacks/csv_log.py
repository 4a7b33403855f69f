"""A CSV log that survives resuming: ``metrics.csv`` keeps the rows of the interrupted run.

Lightning's ``CSVLogger`` deletes an existing ``metrics.csv`` when its writer starts, so a run resumed with
``ckpt_path=last`` (or tested again with ``train=false``) loses every learning-curve row written before. Here:

- :class:`ResumableCSVLogger` is ``CSVLogger`` with a writer that keeps the file and its header (new columns
  still extend the header, as in Lightning).
- :class:`CSVLogResume` (a callback) makes the kept log consistent when training starts: rows with
  ``step >= trainer.global_step`` are dropped, because the run is about to log those steps again. Lightning
  logs optimiser step k (0-based) and the validation/epoch-end rows after it with ``step = k``, and a
  checkpoint taken after k + 1 steps restores ``global_step = k + 1``; rows logged after that checkpoint
  and before a kill are therefore exactly the rows with ``step >= global_step``. A fresh run in the same folder
  starts at ``global_step = 0`` and so replaces the old log, like Lightning does; a test-only run (no
  training) appends its test rows.

The rewrite is atomic (``tofdenoise.atomic``). Only the global-zero process writes, as for every CSV log.
"""

from __future__ import annotations

import csv
import io
import math
import os

import lightning.pytorch as pl
from lightning.fabric.loggers.logger import rank_zero_experiment
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from tofdenoise.atomic import atomic_write_text

__all__ = ["CSVLogResume", "KeepingExperimentWriter", "ResumableCSVLogger", "drop_rows_from_step"]


def _step_of(row: dict[str, str]) -> float:
    try:
        return float(row.get("step") or "nan")
    except ValueError:
        return math.nan


def drop_rows_from_step(path: str | os.PathLike[str], step: int) -> tuple[list[str], int]:
    """Rewrite the CSV log ``path`` without the rows whose ``step`` is >= ``step`` (rows without a numeric
    step are kept). Returns (header, number of rows dropped); a missing file gives ([], 0)."""
    if not os.path.isfile(path):
        return [], 0
    header, rows = _read_rows(path)
    kept = [r for r in rows if not _step_of(r) >= step]
    dropped = len(rows) - len(kept)
    if dropped:
        _write_rows(path, header, kept)
    return header, dropped


def _read_rows(path: str | os.PathLike[str]) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def _write_rows(path: str | os.PathLike[str], header: list[str], rows: list[dict[str, str]]) -> None:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=header, lineterminator="\r\n")  # Lightning's csv line ends
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, out.getvalue())


class KeepingExperimentWriter(ExperimentWriter):
    """Lightning's CSV experiment writer, except that an existing ``metrics.csv`` is kept and appended to."""

    def __init__(self, log_dir: str) -> None:
        super().__init__(log_dir=log_dir)
        self._load_header()

    def _check_log_dir_exists(self) -> None:  # Lightning deletes metrics.csv here
        pass

    def _load_header(self) -> None:
        if os.path.isfile(self.metrics_file_path):
            with open(self.metrics_file_path, newline="") as fh:
                header = list(next(csv.reader(fh), []))
            # Lightning appends rows in sorted column order: a file with another order is rewritten sorted first
            if header != sorted(header):
                _, rows = _read_rows(self.metrics_file_path)
                _write_rows(self.metrics_file_path, sorted(header), rows)
            self.metrics_keys = sorted(header)

    def drop_from_step(self, step: int) -> int:
        """Flush pending rows, then drop every row with ``step >= step`` (see the module docstring)."""
        self.save()
        _, dropped = drop_rows_from_step(self.metrics_file_path, step)
        self._load_header()
        return dropped


class ResumableCSVLogger(CSVLogger):
    """``lightning.pytorch.loggers.CSVLogger`` (same arguments) whose ``metrics.csv`` survives a resume; pair it
    with the :class:`CSVLogResume` callback, which drops the rows the resumed run logs again.

    ``flush_logs_every_n_steps`` defaults to 1 (Lightning: 100): every row is on disk as soon as it is logged,
    so a killed run loses no row that its checkpoint covers (the cost of a flush per step: docs/benchmarks.md,
    "Training step on the CPU")."""

    def __init__(
        self,
        save_dir: str | os.PathLike[str],
        name: str | None = "lightning_logs",
        version: int | str | None = None,
        prefix: str = "",
        flush_logs_every_n_steps: int = 1,
    ) -> None:
        super().__init__(
            save_dir, name=name, version=version, prefix=prefix, flush_logs_every_n_steps=flush_logs_every_n_steps
        )

    @property
    @rank_zero_experiment
    def experiment(self) -> KeepingExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = KeepingExperimentWriter(log_dir=self.log_dir)
        return self._experiment


class CSVLogResume(pl.Callback):
    """When training starts, drop the rows of every :class:`ResumableCSVLogger` that the run will log again
    (``step >= trainer.global_step``, i.e. everything after the checkpoint it resumed from)."""

    def __init__(self) -> None:
        self.dropped_rows = 0

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        for logger in trainer.loggers:
            if isinstance(logger, ResumableCSVLogger):
                self.dropped_rows += logger.experiment.drop_from_step(int(trainer.global_step))
