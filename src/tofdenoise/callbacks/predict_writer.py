"""Writes restored depth maps of ``trainer.predict``: 16-bit PNG in millimetres and float32 ``.npy``.

Layout under ``output_dir`` (one folder per prediction set, named after ``datamodule.test_set_names``)::

    <set>/png/<name>.png            restored depth, uint16 millimetres (0 = invalid / out of range)
    <set>/npy/<name>.npy            restored depth, float32 millimetres (0 = invalid, as in the PNG)
    <set>/sigma_npy/<name>.npy      sigma_D map in mm of the input (write_sigma)
    <set>/preview/<name>.png        colourised noisy | restored | sigma_D | |error| panel (write_previews)
    <set>/reference_png/<name>.png  clean reference, uint16 mm (write_reference; ready for tofdenoise evaluate)
    <set>/noisy_png/<name>.png      the network input, uint16 mm (write_reference)
    <set>/reference_npy/<name>.npy  clean reference, float32 mm, as the test step scores it (write_reference)
    <set>/noisy_npy/<name>.npy      the network input, float32 mm (write_reference)
    <set>/mask/<name>.png           the scoring mask, uint8 (255 = scored; write_reference)

All files are written atomically (``tofdenoise.atomic``). ``tofdenoise evaluate --pred <set>/npy
--ref <set>/reference_npy --mask <set>/mask`` computes the metrics of the float maps: the test step's numbers
(``metrics.json``) to float rounding. ``--pred <set>/png --ref <set>/reference_png`` scores both maps rounded to
whole millimetres, which shifts the numbers (docs/evaluation.md gives the measured offsets).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
from lightning.pytorch.callbacks import BasePredictionWriter

from tofdenoise import visualize
from tofdenoise.atomic import atomic_write_png, save_npy_atomic
from tofdenoise.data_modules.io import write_depth_png16
from tofdenoise.visualize import batch_plane

__all__ = ["DepthPredictionWriter"]


class DepthPredictionWriter(BasePredictionWriter):
    """Saves every predicted depth map as it is produced (``write_interval="batch"``: no memory growth).

    Args:
        output_dir: root folder; ``None`` = ``<trainer.default_root_dir>/predictions``.
        write_sigma: also save the input's sigma_D map (``batch["sigma"]``) as ``.npy``.
        write_previews: also save a colourised panel PNG (noisy, restored, sigma_D, |error| when the batch has
            a reference) with a shared depth colour scale (``tofdenoise.visualize``).
        write_reference: also save the clean reference and the noisy input as 16-bit PNG and float32 ``.npy``, and
            the scoring mask as an 8-bit PNG.
    """

    def __init__(
        self,
        output_dir: str | Path | None = None,
        write_sigma: bool = False,
        write_previews: bool = False,
        write_reference: bool = False,
    ) -> None:
        super().__init__(write_interval="batch")
        self.output_dir = None if output_dir is None else Path(output_dir)
        self.write_sigma = write_sigma
        self.write_previews = write_previews
        self.write_reference = write_reference
        self.written: list[Path] = []

    def _root(self, trainer: pl.Trainer) -> Path:
        return self.output_dir if self.output_dir is not None else Path(trainer.default_root_dir) / "predictions"

    @staticmethod
    def _set_name(trainer: pl.Trainer, dataloader_idx: int) -> str:
        names = getattr(trainer.datamodule, "test_set_names", None) if trainer.datamodule is not None else None
        if names and dataloader_idx < len(names):
            return str(names[dataloader_idx])
        return "predict" if dataloader_idx == 0 else f"predict_{dataloader_idx}"

    def write_on_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        prediction: Any,
        batch_indices: Sequence[int] | None,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        pred = prediction["pred_mm"] if isinstance(prediction, dict) else prediction
        root = self._root(trainer) / self._set_name(trainer, dataloader_idx)
        names = batch.get("name") if isinstance(batch, dict) else None
        index = batch.get("index") if isinstance(batch, dict) else None
        for i in range(pred.shape[0]):
            if names is not None:
                stem = Path(str(names[i])).stem
            elif index is not None:
                stem = f"{int(index[i]):06d}"
            elif batch_indices is not None:
                stem = f"{int(batch_indices[i]):06d}"
            else:
                stem = f"{batch_idx:06d}_{i:02d}"
            depth = batch_plane(pred, i)
            write_depth_png16(root / "png" / f"{stem}.png", depth)
            save_npy_atomic(root / "npy" / f"{stem}.npy", depth.astype(np.float32))
            self.written.append(root / "png" / f"{stem}.png")
            if self.write_sigma and isinstance(batch, dict) and "sigma" in batch:
                save_npy_atomic(root / "sigma_npy" / f"{stem}.npy", batch_plane(batch["sigma"], i))
            if self.write_reference and isinstance(batch, dict):
                if "clean" in batch:
                    clean = batch_plane(batch["clean"], i)
                    write_depth_png16(root / "reference_png" / f"{stem}.png", clean)
                    save_npy_atomic(root / "reference_npy" / f"{stem}.npy", clean.astype(np.float32))
                if "noisy" in batch:
                    noisy = batch_plane(batch["noisy"], i)
                    write_depth_png16(root / "noisy_png" / f"{stem}.png", noisy)
                    save_npy_atomic(root / "noisy_npy" / f"{stem}.npy", noisy.astype(np.float32))
                if "mask" in batch:
                    scored = np.where(batch_plane(batch["mask"], i) > 0, 255, 0).astype(np.uint8)
                    atomic_write_png(root / "mask" / f"{stem}.png", scored)
            if self.write_previews and isinstance(batch, dict):
                atomic_write_png(root / "preview" / f"{stem}.png", self._preview(batch, depth, i))

    @staticmethod
    def _preview(batch: dict, depth_mm: np.ndarray, i: int) -> np.ndarray:
        maps: dict[str, np.ndarray] = {}
        if "noisy" in batch:
            maps["noisy"] = batch_plane(batch["noisy"], i)
        maps["restored"] = depth_mm
        if "clean" in batch:
            maps["clean"] = batch_plane(batch["clean"], i)
        mask = batch_plane(batch["mask"], i) > 0 if "mask" in batch else None
        sigma = batch_plane(batch["sigma"], i) if "sigma" in batch else None
        return visualize.prediction_preview(maps, sigma_mm=sigma, mask=mask)
