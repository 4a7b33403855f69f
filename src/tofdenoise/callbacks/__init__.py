"""Lightning callbacks of tofdenoise.

- :class:`~tofdenoise.callbacks.checkpointing.BestAndLastCheckpoint`: the one ``ModelCheckpoint``
  (``checkpoints/best.ckpt`` = lowest ``val/mae_mm``, and ``checkpoints/last.ckpt``).
- :class:`~tofdenoise.callbacks.summary.RunSummary`: a readable one-line summary after fit and test.
- :class:`~tofdenoise.callbacks.predict_writer.DepthPredictionWriter`: 16-bit PNG (mm) + ``.npy`` predictions.
- :class:`~tofdenoise.callbacks.image_panels.ImagePanelLogger`: a fixed panel of validation samples per epoch.
- ``metrics_writer``: ``metrics.json`` and per-image CSV writers (functions).
"""

from tofdenoise.callbacks.checkpointing import BestAndLastCheckpoint
from tofdenoise.callbacks.image_panels import ImagePanelLogger
from tofdenoise.callbacks.predict_writer import DepthPredictionWriter
from tofdenoise.callbacks.summary import RunSummary

__all__ = ["BestAndLastCheckpoint", "DepthPredictionWriter", "ImagePanelLogger", "RunSummary"]
