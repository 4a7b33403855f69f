"""What every data source provides: a list of sample ids and, per id, clean depth + amplitude + validity.

How a source is configured: ``data.source`` names it (the ``DATA_SOURCES`` registry) and ``data.source_kwargs``
holds its own settings, as ``data.noise`` / ``data.noise_kwargs`` do for a noise model. The datamodule does not
know any source's settings: :func:`source_from_config` checks the keys against the class's ``config_keys()`` and
builds it with the class's ``from_config(settings, context)``, where ``context`` (:class:`SourceContext`) carries
what the datamodule supplies to every source (``data.seed``, the calibration of ``data.sensor``). A new source is
a new module here with ``@register_source``, those two classmethods, and an import in ``sources/__init__.py``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from tofdenoise.registry import Registry

if TYPE_CHECKING:
    from tofdenoise.physics.calibration import SensorCalibration


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


@dataclass(frozen=True)
class SourceContext:
    """What the datamodule supplies to every source, beside the source's own ``data.source_kwargs``: settings of
    the datamodule or the camera, not of one source. A source takes the fields it needs in ``from_config``."""

    seed: int  # data.seed (the procedural scenes' seed)
    calibration: SensorCalibration  # data.sensor, resolved (the procedural depth range's default)


#: the datamodule's setting behind each ``SourceContext`` field (named when one is written in data.source_kwargs)
CONTEXT_SETTINGS = {"seed": "data.seed", "calibration": "data.sensor"}


class DataSource(Protocol):
    """A source of clean samples, selected by ``name`` in the datamodule (``data.source``)."""

    name: str

    @classmethod
    def config_keys(cls) -> list[str]:
        """The keys ``data.source_kwargs`` may hold for this source (usually :func:`init_keywords`)."""

    @classmethod
    def from_config(cls, settings: dict[str, Any], context: SourceContext) -> DataSource:
        """The source for ``settings`` (``data.source_kwargs``, keys already checked) and what the datamodule
        supplies (``context``)."""

    def sample_ids(self) -> list[str]:
        """All sample ids, in a fixed order (the split permutes positions in this list)."""

    def check(self) -> None:
        """Fail early (before training) if any listed sample's files are missing."""

    def load(self, sample_id: str) -> RawSample:
        """Read/render one sample."""

    def describe(self) -> dict[str, Any]:
        """Plain values that determine the samples' content (part of the cache key)."""

    # optional, for a source read from files (folder, flyingthings3d; the procedural source has none):
    # def files(self, sample_id: str) -> list[Path]: the files ``load(sample_id)`` reads. Their stamps (size, mtime,
    # ctime, inode, SHA-256: ``file_stamps``) are recorded with the sample's cached maps and index entry, and a
    # changed file recomputes them (``cache.MapCache``).


DATA_SOURCES: Registry[DataSource] = Registry("data source")


def register_source(name: str) -> Callable[[Callable[..., DataSource]], Callable[..., DataSource]]:
    """Decorator registering a data source class under ``name`` (the value of ``data.source``)."""
    return DATA_SOURCES.register(name)


def available_sources() -> list[str]:
    """Registered data source names, sorted."""
    return sorted(DATA_SOURCES.names())


def init_keywords(cls: type, *, leave_out: tuple[str, ...] = ()) -> list[str]:
    """The keyword parameters of ``cls.__init__`` but ``leave_out``, in signature order: the usual
    ``config_keys()`` of a source (``leave_out`` = the arguments its ``from_config`` takes from the context)."""
    params = inspect.signature(cls.__init__).parameters.values()
    return [
        p.name
        for p in params
        if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in leave_out
    ]


def check_source_kwargs(name: str, settings: Mapping[str, Any] | None) -> dict[str, Any]:
    """``settings`` as a plain dict after checking it against the source's ``config_keys()``: ValueError for an
    unknown source name (listing the valid ones), for a mapping that is not one, and for an unknown key, naming
    ``data.source_kwargs.<key>``, the source and its valid keys."""
    factory = DATA_SOURCES.get(name)
    source = str(name).lower()
    if settings is None:
        return {}
    if not isinstance(settings, Mapping):
        raise ValueError(
            f"data.source_kwargs must be a mapping of the {source} source's settings, got {settings!r}; "
            f"valid keys: {', '.join(factory.config_keys())}"
        )
    valid = factory.config_keys()
    unknown = [key for key in settings if key not in valid]
    if unknown:
        key = unknown[0]
        note = f" ({key} comes from the datamodule: {CONTEXT_SETTINGS[key]})" if key in CONTEXT_SETTINGS else ""
        raise ValueError(
            f"data.source_kwargs.{key}: not a setting of the {source} source{note}; valid keys: {', '.join(valid)}"
        )
    return dict(settings)


def source_from_config(name: str, settings: Mapping[str, Any] | None, context: SourceContext) -> DataSource:
    """The source ``data.source`` = ``name`` with ``data.source_kwargs`` = ``settings`` (checked:
    :func:`check_source_kwargs`) and what the datamodule supplies (``context``), built by the class's
    ``from_config``."""
    checked = check_source_kwargs(name, settings)
    return DATA_SOURCES.get(name).from_config(checked, context)


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
