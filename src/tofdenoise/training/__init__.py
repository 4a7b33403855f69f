"""Training: the LightningModule, the losses and the metrics (a run's records: ``tofdenoise.records``).

- :mod:`~tofdenoise.training.module`: :class:`DepthRestorer`, the one LightningModule (conditioning, loss,
  validation/test metrics, the learned guard).
- :mod:`~tofdenoise.training.losses`: L1, L_nar (uncertainty-weighted Charbonnier) and L_full (+ gradient term),
  averaged over the valid pixels, in millimetres.
- :mod:`~tofdenoise.training.metrics`: PSNR (fixed D_max), MAE, MSE and SSIM per image over valid pixels.

Names are imported lazily, so that importing a sub-module does not import Lightning.
"""

from __future__ import annotations

from tofdenoise.lazy import lazy_getattr

_LAZY = {
    "DepthRestorer": "tofdenoise.training.module",
    "DepthLoss": "tofdenoise.training.losses",
    "build_loss": "tofdenoise.training.losses",
    "available_losses": "tofdenoise.training.losses",
    "DepthMetrics": "tofdenoise.training.metrics",
}

__all__ = sorted(_LAZY)

__getattr__ = lazy_getattr(__name__, _LAZY)
