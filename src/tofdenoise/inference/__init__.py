"""Inference on camera frames: ``denoise`` (arrays), ``tofdenoise denoise`` (files), LightningCLI ``predict``
(``FramesDataModule`` + ``FramesPredictionWriter``), sharing one restoration path (``denoise.restore_frame``).

Names are imported lazily so that ``import tofdenoise`` stays light.
"""

from __future__ import annotations

from tofdenoise.lazy import lazy_getattr

_LAZY = {
    "denoise": "tofdenoise.inference.denoise",
    "load_restorer": "tofdenoise.inference.denoise",
    "restore_frame": "tofdenoise.inference.denoise",
    "sigma_map_mm": "tofdenoise.inference.denoise",
    "CheckpointError": "tofdenoise.inference.denoise",
    "find_frames": "tofdenoise.inference.frames",
    "load_frame": "tofdenoise.inference.frames",
    "read_depth_frame": "tofdenoise.inference.frames",
    "FrameError": "tofdenoise.inference.frames",
    "write_frame_outputs": "tofdenoise.inference.outputs",
    "FramesDataModule": "tofdenoise.inference.predict",
    "FramesDataset": "tofdenoise.inference.predict",
    "FramesPredictionWriter": "tofdenoise.inference.predict",
}

__all__ = sorted(_LAZY)

__getattr__ = lazy_getattr(__name__, _LAZY)
