"""Sensor physics: calibration, per-pixel depth uncertainty (WLS), noise models, capture simulator.

See docs/physics.md. Sub-modules: calibration, uncertainty, noise_models, simulator, mixed_pixels, calibrate,
validation.
"""

from tofdenoise.physics.calibration import (
    CalibrationError,
    SensorCalibration,
    TapResponse,
    default_calibration,
    load_calibration,
    resolve_calibration,
    save_calibration,
)
from tofdenoise.physics.noise_models import (
    NoiseModel,
    available_noise_models,
    build_noise_model,
    variance_matching_scale,
)
from tofdenoise.physics.uncertainty import amplitude_to_signal_e, depth_variance_mm2, sigma_depth_mm

__all__ = [
    "CalibrationError",
    "NoiseModel",
    "SensorCalibration",
    "TapResponse",
    "amplitude_to_signal_e",
    "available_noise_models",
    "build_noise_model",
    "default_calibration",
    "depth_variance_mm2",
    "load_calibration",
    "resolve_calibration",
    "save_calibration",
    "sigma_depth_mm",
    "variance_matching_scale",
]
