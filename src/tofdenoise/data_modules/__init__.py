"""Data: sources (procedural / ToF-FlyingThings3D / folder), seeded splits, cached sigma_D maps, capture sets.

``ToFDataModule`` is imported lazily so that the light parts (readers, capture sets, the
``tofdenoise sensor`` commands) do not pay for importing Lightning.
"""

from __future__ import annotations

from typing import Any

from tofdenoise.data_modules.cache import MapCache, SampleMaps
from tofdenoise.data_modules.maps import compute_sample_maps
from tofdenoise.data_modules.splits import make_split, split_sizes

__all__ = ["MapCache", "SampleMaps", "ToFDataModule", "compute_sample_maps", "make_split", "split_sizes"]


def __getattr__(name: str) -> Any:
    if name == "ToFDataModule":
        from tofdenoise.data_modules.datamodule import ToFDataModule

        return ToFDataModule
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
