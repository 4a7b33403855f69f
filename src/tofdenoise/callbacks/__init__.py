"""Lightning callbacks of tofdenoise.

- :class:`~tofdenoise.callbacks.checkpointing.BestAndLastCheckpoint`: the one ``ModelCheckpoint``
  (``checkpoints/best.ckpt`` = lowest ``val/mae_mm``, and ``checkpoints/last.ckpt``).
- :class:`~tofdenoise.callbacks.csv_log.ResumableCSVLogger` + :class:`~tofdenoise.callbacks.csv_log.CSVLogResume`:
  a ``metrics.csv`` that keeps the rows of an interrupted run when it is resumed.
- :class:`~tofdenoise.callbacks.summary.RunSummary`: a readable one-line summary after fit and test.
- :class:`~tofdenoise.callbacks.run_outputs.RunOutputs`: the run's records (``run_info.json``, ``metrics.json``,
  ``per_image/<set>.csv``), the same for both front ends.
- :class:`~tofdenoise.callbacks.training_cost.TrainingCost`: training time (summed over resumes), images per
  second and peak memory, written into ``run_info.json`` by ``RunOutputs``.
- :class:`~tofdenoise.callbacks.predict_writer.DepthPredictionWriter`: 16-bit PNG (mm) + ``.npy`` predictions.
- :class:`~tofdenoise.callbacks.image_panels.ImagePanelLogger`: a fixed panel of validation samples per epoch.

The run-results schema and its writers (``metrics.json``, per-image CSVs, the file names) live in
:mod:`tofdenoise.records`.
The classes are imported lazily, so that importing this package does not pay for importing Lightning.
"""

from __future__ import annotations

from tofdenoise.lazy import lazy_getattr

_LAZY = {
    "BestAndLastCheckpoint": "tofdenoise.callbacks.checkpointing",
    "CSVLogResume": "tofdenoise.callbacks.csv_log",
    "DepthPredictionWriter": "tofdenoise.callbacks.predict_writer",
    "ImagePanelLogger": "tofdenoise.callbacks.image_panels",
    "ResumableCSVLogger": "tofdenoise.callbacks.csv_log",
    "RunOutputs": "tofdenoise.callbacks.run_outputs",
    "RunSummary": "tofdenoise.callbacks.summary",
    "TrainingCost": "tofdenoise.callbacks.training_cost",
}

__all__ = sorted(_LAZY)

__getattr__ = lazy_getattr(__name__, _LAZY)
