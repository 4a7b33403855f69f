"""Logs a fixed panel of validation samples every validation epoch (wandb, TensorBoard and PNG files).

``ImagePanelLogger(indices=4, dirpath=None, max_tile=256, min_tile=160, every_n_epochs=1, key="val/panels")``

- ``indices``: the dataset indices (``batch["index"]``) shown every epoch, or an int N: N indices spread
  evenly over the validation set (``linspace(0, len - 1, N)``; the first N when the length is unknown).
  The same samples every epoch (the validation noise is fixed per index), so panels are comparable.
- Nothing is re-run: ``on_validation_batch_end`` copies the chosen samples from the batch (``noisy``,
  ``clean``, ``sigma``, ``mask``, ``index``, optional ``name``) and from ``outputs["pred_mm"]`` (the dict
  that ``DepthRestorer.validation_step`` returns; (B, 1, H, W) restored depth in mm). Only the first
  validation loader is used; the sanity-check pass is skipped.
- At the end of the epoch the samples are gathered from all DDP processes, and rank 0 builds one image
  (``tofdenoise.visualize.sample_panel`` per sample, stacked) and
  * writes ``<dirpath>/epoch_XXX.png`` atomically (``dirpath`` default: ``<trainer.default_root_dir>/panels``),
  * logs it with ``WandbLogger.log_image(key, [image], step=global_step)`` for each attached WandbLogger,
  * and ``experiment.add_image(key, image, global_step, dataformats="HWC")`` for each TensorBoardLogger.

Hydra entry (``configs/callbacks/default.yaml``)::

    image_panels:
      _target_: tofdenoise.callbacks.image_panels.ImagePanelLogger
      indices: 4            # or a list of validation dataset indices
      dirpath: ${paths.run_dir}/panels
      max_tile: 256         # longest tile side in px (larger maps are shrunk)
      min_tile: 160         # small maps are enlarged (integer factor, nearest) so titles fit
      every_n_epochs: 1
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger

from tofdenoise import visualize
from tofdenoise.atomic import atomic_write_png

__all__ = ["ImagePanelLogger", "write_png_rgb_atomic"]

_REQUIRED_KEYS = ("noisy", "clean", "index")


def write_png_rgb_atomic(path: str | Path, image_rgb: np.ndarray) -> Path:
    """Encode a uint8 RGB image as PNG and write it atomically."""
    return atomic_write_png(path, cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2BGR))


class ImagePanelLogger(Callback):
    """Every validation epoch: noisy | restored | clean, sigma_D and |error| maps of fixed samples."""

    def __init__(
        self,
        indices: int | Sequence[int] = 4,
        dirpath: str | Path | None = None,
        max_tile: int = 256,
        every_n_epochs: int = 1,
        key: str = "val/panels",
        min_tile: int | None = 160,
    ) -> None:
        super().__init__()
        if isinstance(indices, int):
            if indices < 1:
                raise ValueError(f"ImagePanelLogger: indices must be >= 1 or a list of indices, got {indices}")
            self._count: int | None = indices
            self._wanted: list[int] | None = None
        else:
            wanted = [int(i) for i in indices]
            if not wanted or any(i < 0 for i in wanted):
                raise ValueError(f"ImagePanelLogger: indices must be non-negative and non-empty, got {wanted}")
            self._count, self._wanted = None, sorted(set(wanted))
        if every_n_epochs < 1:
            raise ValueError(f"ImagePanelLogger: every_n_epochs must be >= 1, got {every_n_epochs}")
        self.dirpath = None if dirpath is None else Path(dirpath)
        self.max_tile = max_tile
        self.min_tile = min_tile
        self.every_n_epochs = every_n_epochs
        self.key = key
        self._samples: dict[int, dict[str, Any]] = {}
        self.last_panel_path: Path | None = None

    # ---------------------------------------------------------------- selection
    @property
    def indices(self) -> list[int] | None:
        """The fixed dataset indices (None until resolved from the validation set length)."""
        return None if self._wanted is None else list(self._wanted)

    def _resolve(self, trainer: pl.Trainer) -> None:
        if self._wanted is not None:
            return
        length = None
        loaders = trainer.val_dataloaders
        loader = loaders[0] if isinstance(loaders, (list, tuple)) and loaders else loaders
        try:
            length = len(loader.dataset)  # type: ignore[union-attr]
        except (AttributeError, TypeError):
            length = None
        n = int(self._count or 1)
        if length:
            self._wanted = sorted({int(round(v)) for v in np.linspace(0, length - 1, min(n, length))})
        else:
            self._wanted = list(range(n))

    def _active(self, trainer: pl.Trainer) -> bool:
        return not trainer.sanity_checking and (trainer.current_epoch + 1) % self.every_n_epochs == 0

    # ---------------------------------------------------------------- hooks
    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._samples = {}
        if self._active(trainer):
            self._resolve(trainer)

    def on_validation_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        if dataloader_idx != 0 or not self._active(trainer) or self._wanted is None:
            return
        if not isinstance(outputs, dict) or "pred_mm" not in outputs:
            raise KeyError(
                "ImagePanelLogger needs validation_step to return a dict with 'pred_mm' "
                "(B, 1, H, W) restored depth in mm"
            )
        if not isinstance(batch, dict) or any(k not in batch for k in _REQUIRED_KEYS):
            raise KeyError(
                f"ImagePanelLogger needs batch dicts with keys {list(_REQUIRED_KEYS)} (+ 'sigma', 'mask' optional)"
            )
        index = torch.as_tensor(batch["index"]).reshape(-1).tolist()
        wanted = set(self._wanted)
        for i, idx in enumerate(index):
            idx = int(idx)
            if idx not in wanted or idx in self._samples:
                continue
            names = batch.get("name")
            self._samples[idx] = {
                "noisy": visualize.batch_plane(batch["noisy"], i),
                "restored": visualize.batch_plane(outputs["pred_mm"], i),
                "clean": visualize.batch_plane(batch["clean"], i),
                "sigma": visualize.batch_plane(batch["sigma"], i) if "sigma" in batch else None,
                "mask": visualize.batch_plane(batch["mask"], i) if "mask" in batch else None,
                "name": str(names[i]) if names is not None and i < len(names) else "",
            }

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self._active(trainer) or self._wanted is None:
            return
        samples = self._gather(self._samples)
        self._samples = {}
        if trainer.global_rank != 0 or not samples:
            return
        epoch = trainer.current_epoch
        panels = [
            visualize.sample_panel(
                s["noisy"],
                s["restored"],
                s["clean"],
                s["sigma"],
                s["mask"],
                title=f"epoch {epoch} | index {idx}" + (f" | {s['name']}" if s["name"] else ""),
                max_tile=self.max_tile,
                min_tile=self.min_tile,
            )
            for idx, s in sorted(samples.items())
        ]
        image = visualize.stack_panels(panels)
        root = self.dirpath if self.dirpath is not None else Path(trainer.default_root_dir) / "panels"
        self.last_panel_path = write_png_rgb_atomic(root / f"epoch_{epoch:03d}.png", image)
        caption = f"epoch {epoch}: indices {sorted(samples)}"
        for logger in trainer.loggers:
            if isinstance(logger, WandbLogger):
                logger.log_image(key=self.key, images=[image], step=trainer.global_step, caption=[caption])
            elif isinstance(logger, TensorBoardLogger):
                logger.experiment.add_image(self.key, image, trainer.global_step, dataformats="HWC")

    @staticmethod
    def _gather(samples: dict[int, dict[str, Any]]) -> dict[int, dict[str, Any]]:
        """Merge the samples seen by every DDP process (object all-gather; they are a few small arrays)."""
        dist = torch.distributed
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() < 2:
            return samples
        gathered: list[Any] = [None] * dist.get_world_size()
        dist.all_gather_object(gathered, samples)
        merged: dict[int, dict[str, Any]] = {}
        for part in gathered:
            for idx, s in (part or {}).items():
                merged.setdefault(idx, s)
        return merged
