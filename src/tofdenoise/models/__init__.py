"""Restoration backbones (registered by name), the selective scan, and tiled inference."""

from . import bilateral as _bilateral  # noqa: F401  (the classical row: joint bilateral filter, not trainable)
from . import deeptof as _deeptof  # noqa: F401
from . import dvss as _dvss  # noqa: F401  (registers dvss, dvss_no_local, dvss_no_dwconv, dvss_se)
from . import rcf as _rcf  # noqa: F401
from . import restormer as _restormer  # noqa: F401
from . import tofkpn as _tofkpn  # noqa: F401
from . import unet as _unet  # noqa: F401
from .common import count_parameters
from .registry import available_backbones, build_backbone, is_trainable, register_backbone, trainable_backbones
from .scan import available_scan_backends, resolve_scan_backend, selective_scan
from .tiling import tiled_forward

__all__ = [
    "available_backbones",
    "build_backbone",
    "count_parameters",
    "is_trainable",
    "register_backbone",
    "trainable_backbones",
    "available_scan_backends",
    "resolve_scan_backend",
    "selective_scan",
    "tiled_forward",
]
