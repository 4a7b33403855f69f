"""What a run's training cost: time, throughput and peak memory, summed over the attempts of a resumed run.

:class:`TrainingCost` measures, on every process:

- ``train_seconds``: wall time inside the training epochs (data loading, optimiser steps, logging and
  checkpointing included), not counting the validation loops that run during fit. A resumed run continues from
  the value stored in its checkpoint, so the time between that checkpoint and a kill (work that is redone) is
  not counted and the time the run was stopped is not either. On CUDA the device is synchronised at the edges
  of what is timed.
- ``train_images``: training samples processed (every process's batches; with DDP, all processes together,
  assuming the ``DistributedSampler``'s equal share per process) and ``train_images_per_second``.
- ``peak_gpu_memory_gib``: ``torch.cuda.max_memory_allocated`` of the process (the largest over attempts;
  ``None`` without CUDA) and ``peak_rss_gib``: the peak resident memory of the process (``VmHWM``; data
  loader workers are separate processes and are not included).

:class:`tofdenoise.callbacks.run_outputs.RunOutputs` writes :meth:`TrainingCost.summary` into ``run_info.json``
at fit end; the results page and ``tofdenoise report`` read it from there.
"""

from __future__ import annotations

import time
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import Callback

from ..allocator import peak_rss_bytes

__all__ = ["TrainingCost", "peak_rss_gib"]

_GIB = 1024.0**3


def peak_rss_gib() -> float:
    """Peak resident set size of this process in GiB (:func:`tofdenoise.allocator.peak_rss_bytes`)."""
    return peak_rss_bytes() / _GIB


class TrainingCost(Callback):
    """Training time, images per second and peak memory of a run (see the module docstring)."""

    def __init__(self) -> None:
        self.seconds = 0.0  # finished epochs of all attempts (and the part of an epoch a checkpoint saw)
        self.images = 0  # this process's samples, all attempts
        self.peak_gpu_bytes: int | None = None
        self.peak_rss = 0.0
        self._epoch_start: float | None = None
        self._paused = 0.0  # validation time inside the current epoch
        self._val_start: float | None = None
        self._world_size = 1

    # ------------------------------------------------------------------ clock
    @staticmethod
    def _clock(pl_module: pl.LightningModule | None = None) -> float:
        if pl_module is not None and pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)
        return time.perf_counter()

    def _epoch_elapsed(self, now: float) -> float:
        """Training time of the current epoch so far (a validation in progress is not training time)."""
        if self._epoch_start is None:
            return 0.0
        paused = self._paused + (0.0 if self._val_start is None else now - self._val_start)
        return max(0.0, now - self._epoch_start - paused)

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._world_size = int(trainer.world_size)
        self._epoch_start, self._paused = self._clock(pl_module), 0.0

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.seconds += self._epoch_elapsed(self._clock(pl_module))
        self._epoch_start = None
        self._sample_memory(pl_module)

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._epoch_start is not None:  # validation during a training epoch: not training time
            self._val_start = self._clock(pl_module)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._val_start is not None:
            self._paused += self._clock(pl_module) - self._val_start
            self._val_start = None

    def on_train_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        # counted at the start, so a checkpoint written at this batch's end includes it
        noisy = batch.get("noisy") if isinstance(batch, dict) else None
        self.images += int(noisy.shape[0]) if isinstance(noisy, torch.Tensor) else 0

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._epoch_start is not None:  # stopped inside an epoch (max_steps, a limit): count what ran
            self.seconds += self._epoch_elapsed(self._clock(pl_module))
            self._epoch_start = None
        self._sample_memory(pl_module)

    def _sample_memory(self, pl_module: pl.LightningModule) -> None:
        self.peak_rss = max(self.peak_rss, peak_rss_gib())
        if pl_module.device.type == "cuda":
            peak = int(torch.cuda.max_memory_allocated(pl_module.device))
            self.peak_gpu_bytes = max(peak, self.peak_gpu_bytes or 0)

    # ------------------------------------------------------------------ checkpoint state (resume adds to it)
    def state_dict(self) -> dict[str, Any]:
        seconds = self.seconds + self._epoch_elapsed(time.perf_counter())
        return {
            "seconds": seconds,
            "images": self.images,
            "peak_gpu_bytes": self.peak_gpu_bytes,
            "peak_rss_gib": max(self.peak_rss, peak_rss_gib()),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.seconds = float(state_dict.get("seconds", 0.0))
        self.images = int(state_dict.get("images", 0))
        peak = state_dict.get("peak_gpu_bytes")
        self.peak_gpu_bytes = None if peak is None else int(peak)
        self.peak_rss = float(state_dict.get("peak_rss_gib", 0.0))

    # ------------------------------------------------------------------ record
    def summary(self) -> dict[str, Any]:
        """The ``run_info.json`` fields (all processes' images; this process's time and memory)."""
        images = self.images * self._world_size
        seconds = round(self.seconds, 3)  # the recorded value; the rate is computed from it, so the two agree
        return {
            "train_seconds": seconds,
            "train_images": images,
            "train_images_per_second": round(images / seconds, 3) if seconds > 0 else None,
            "peak_gpu_memory_gib": None if self.peak_gpu_bytes is None else round(self.peak_gpu_bytes / _GIB, 3),
            "peak_rss_gib": round(self.peak_rss, 3),
        }
