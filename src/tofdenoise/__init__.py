"""tofdenoise: iToF depth denoising with sensor-intrinsic uncertainty modelling."""

__version__ = "0.1.0"
