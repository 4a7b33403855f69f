"""What every data source provides: a list of sample ids and, per id, clean depth + amplitude + validity."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from tofdenoise.registry import Registry


@dataclass
class RawSample:
    """One clean sample before sensor modelling.

    depth_mm: (H, W) float32 clean z-depth in mm; amplitude: (H, W) float32 ToF amplitude (source units);
    valid: (H, W) bool. Invalid pixels may hold anything in ``depth_mm`` (they are zeroed downstream).
    """

    name: str
    depth_mm: np.ndarray
    amplitude: np.ndarray
    valid: np.ndarray


class DataSource(Protocol):
    """A source of clean samples, selected by ``name`` in the datamodule."""

    name: str

    def sample_ids(self) -> list[str]:
        """All sample ids, in a fixed order (the split permutes positions in this list)."""

    def check(self) -> None:
        """Fail early (before training) if any listed sample's files are missing."""

    def load(self, sample_id: str) -> RawSample:
        """Read/render one sample."""

    def describe(self) -> dict[str, Any]:
        """Plain values that determine the samples' content (part of the cache key)."""


DATA_SOURCES: Registry[DataSource] = Registry("data source")


def register_source(name: str) -> Callable[[Callable[..., DataSource]], Callable[..., DataSource]]:
    """Decorator registering a data source class under ``name`` (the value of ``data.source``)."""
    return DATA_SOURCES.register(name)


def available_sources() -> list[str]:
    """Registered data source names, sorted."""
    return sorted(DATA_SOURCES.names())


def build_source(name: str, **kwargs: Any) -> DataSource:
    """Build the data source registered as ``name``; ValueError for an unknown name or keyword (listing the valid
    ones)."""
    return DATA_SOURCES.build(name, **kwargs)


def depth_validity(depth_mm: np.ndarray, min_depth_mm: float = 0.0, max_depth_mm: float = float("inf")) -> np.ndarray:
    """Valid where depth is finite and min_depth_mm < depth <= max_depth_mm (NaN/inf/negative/zero -> invalid)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth_mm) & (depth_mm > max(min_depth_mm, 0.0)) & (depth_mm <= max_depth_mm)


def read_list_file(path, *, what: str = "list file") -> list[str]:
    """Non-empty, non-comment lines of a text list file (stripped)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    lines = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if line and not line.startswith("#"):
            lines.append(line)
    if not lines:
        raise ValueError(f"{what} {path} lists no samples")
    return lines


def raise_if_missing(missing: list[str], where: str) -> None:
    """Fail before training when listed files are missing: ``where`` names the dataset/list file; shows the first 10."""
    if not missing:
        return
    shown = "\n  ".join(missing[:10])
    more = f"\n  ... and {len(missing) - 10} more" if len(missing) > 10 else ""
    raise FileNotFoundError(f"{where}: {len(missing)} listed file(s) missing:\n  {shown}{more}")
