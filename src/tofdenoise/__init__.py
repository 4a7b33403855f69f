"""tofdenoise: iToF depth denoising with sensor-intrinsic uncertainty modelling."""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name == "denoise":  # imported lazily: `import tofdenoise` stays light
        from tofdenoise.inference.denoise import denoise

        return denoise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
