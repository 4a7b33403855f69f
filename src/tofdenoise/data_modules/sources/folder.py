"""A user's own clean depth + amplitude, listed in a text file.

``root/list.txt`` (or ``list_file``) holds one sample per line: ``<depth path> <amplitude path>
[<mask path>]``, paths relative to ``root`` (blank lines and ``#`` comments are skipped).

- depth: 16-bit PNG in mm (0 = invalid), ``.npy``/``.npz`` float in mm, or ``.exr`` float in mm
  (times ``depth_unit_mm`` if the files use other units, e.g. 1000 for metres); an EXR's depth channel is chosen
  by its name (``exr.depth_channel``: ``Z`` / ``*.Depth.Z`` first) or named by ``depth_channel``;
- amplitude: 8/16-bit PNG, ``.npy``/``.npz`` or ``.exr``, any units (normalised per image later); an EXR's
  amplitude channel is chosen by its name (``exr.amplitude_channels``, never a depth channel) or named by
  ``amplitude_channel``;
- optional mask: nonzero = valid.

NaN, inf, zero and negative depths are invalid pixels. Depths beyond ``max_valid_mm`` are invalid too. A file whose
median valid depth (after ``depth_unit_mm``) lies below ``io.MIN_MEDIAN_DEPTH_MM`` (20 mm) is refused, naming it: a
map in metres read as millimetres.

Settings (``data.source_kwargs``): every ``__init__`` argument, e.g.
``data.source=folder data.source_kwargs.root=/data/mine ++data.source_kwargs.list_file=list.txt``.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.data_modules.io import (
    MIN_MEDIAN_DEPTH_MM,
    DataFileError,
    check_same_shape,
    read_amplitude,
    read_array,
    read_depth_mm,
)
from tofdenoise.data_modules.sources.base import (
    RawSample,
    SourceContext,
    depth_validity,
    init_keywords,
    raise_if_missing,
    read_list_file,
    register_source,
)


@register_source("folder")
class FolderSource:
    name = "folder"

    def __init__(
        self,
        root: str | Path | None = None,
        list_file: str | Path | None = None,
        depth_unit_mm: float = 1.0,
        min_valid_mm: float = 0.0,
        max_valid_mm: float = float("inf"),
        depth_channel: str | None = None,
        amplitude_channel: str | None = None,
    ):
        if root is None or str(root) == "":
            raise ValueError("the folder source needs its dataset folder: set data.source_kwargs.root=/path/to/folder")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"folder dataset root not found: {self.root} (set data.source_kwargs.root)")
        list_path = Path(list_file) if list_file else Path("list.txt")
        self.list_path = list_path if list_path.is_absolute() else self.root / list_path
        self.depth_unit_mm = float(depth_unit_mm)
        self.min_valid_mm, self.max_valid_mm = float(min_valid_mm), float(max_valid_mm)
        self.depth_channel = str(depth_channel) if depth_channel else None
        self.amplitude_channel = str(amplitude_channel) if amplitude_channel else None
        self._entries: dict[str, tuple[Path, Path, Path | None]] | None = None
        self._rows: list[list[str]] = []  # the list's entries as written (list_digest)

    @classmethod
    def config_keys(cls) -> list[str]:
        """``data.source_kwargs``: every ``__init__`` argument."""
        return init_keywords(cls)

    @classmethod
    def from_config(cls, settings: dict[str, Any], context: SourceContext) -> FolderSource:
        """The datamodule supplies nothing a folder of files needs: ``settings`` are the ``__init__`` arguments."""
        return cls(**settings)

    def entries(self) -> dict[str, tuple[Path, Path, Path | None]]:
        if self._entries is None:
            entries: dict[str, tuple[Path, Path, Path | None]] = {}
            rows: list[list[str]] = []
            for number, line in enumerate(read_list_file(self.list_path, what="folder list file"), start=1):
                parts = line.split()
                if len(parts) not in (2, 3):
                    raise ValueError(
                        f"folder list file {self.list_path}, entry {number}: expected "
                        f"'<depth> <amplitude> [<mask>]', got {line!r}"
                    )
                depth, amplitude = self.root / parts[0], self.root / parts[1]
                mask = self.root / parts[2] if len(parts) == 3 else None
                sample_id = str(Path(parts[0]).with_suffix("")).replace("\\", "/")
                if sample_id in entries:
                    raise ValueError(f"folder list file {self.list_path}: depth file {parts[0]} listed twice")
                entries[sample_id] = (depth, amplitude, mask)
                rows.append(parts)
            self._entries, self._rows = entries, rows
        return self._entries

    def sample_ids(self) -> list[str]:
        return list(self.entries())

    def files(self, sample_id: str) -> list[Path]:
        """The depth, amplitude and (if listed) mask file of a sample: their stamps key its cached maps."""
        return [p for p in self.entries()[sample_id] if p is not None]

    def list_digest(self) -> str:
        """SHA-256 of the list's entries as parsed (which files each sample pairs; comments and spacing aside)."""
        self.entries()
        return hashlib.sha256(json.dumps(self._rows).encode("utf-8")).hexdigest()

    def check(self) -> None:
        missing = [str(p) for trio in self.entries().values() for p in trio if p is not None and not p.is_file()]
        raise_if_missing(missing, f"folder list file {self.list_path}")

    def load(self, sample_id: str) -> RawSample:
        depth_path, amplitude_path, mask_path = self.entries()[sample_id]
        depth = read_depth_mm(
            depth_path,
            what="folder depth",
            scale_mm=self.depth_unit_mm,
            exr_channel=self.depth_channel,
            channel_setting="data.source_kwargs.depth_channel",
        )
        amplitude = read_amplitude(
            amplitude_path,
            what="folder amplitude",
            exr_channel=self.amplitude_channel,
            channel_setting="data.source_kwargs.amplitude_channel",
        )
        check_same_shape(
            depth, amplitude, reference_path=depth_path, other_path=amplitude_path, what="folder amplitude"
        )
        valid = depth_validity(depth, self.min_valid_mm, self.max_valid_mm)
        if mask_path is not None:
            mask = read_array(mask_path, what="folder mask")
            check_same_shape(depth, mask, reference_path=depth_path, other_path=mask_path, what="folder mask")
            valid &= mask != 0
        valid &= np.isfinite(amplitude)
        median_mm = float(np.median(depth[valid])) if valid.any() else math.inf
        if median_mm < MIN_MEDIAN_DEPTH_MM:
            # a map in metres read as millimetres trained on sigma_D of a 1 mm scene and noise larger than the depth
            raise DataFileError(
                f"folder depth file {depth_path}: median valid depth {median_mm:.4g} mm is "
                f"implausible (below {MIN_MEDIAN_DEPTH_MM:g} mm) with data.source_kwargs.depth_unit_mm="
                f"{self.depth_unit_mm:g}; files in metres need depth_unit_mm=1000"
            )
        if np.any(amplitude[valid] < 0):
            raise DataFileError(f"folder amplitude file {amplitude_path} has negative values; expected amplitude >= 0")
        return RawSample(
            sample_id,
            np.where(valid, depth, 0.0).astype(np.float32),
            np.where(valid, amplitude, 0.0).astype(np.float32),
            valid,
        )

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "root": str(self.root.resolve()),
            "list_file": str(self.list_path.resolve()),
            # the list's content: a re-paired amplitude or an added mask column is another description (and cache)
            "list_entries_sha256": self.list_digest(),
            "depth_unit_mm": self.depth_unit_mm,
            "min_valid_mm": self.min_valid_mm,
            "max_valid_mm": self.max_valid_mm,
            # which EXR channels are read (None: chosen by name, exr.depth_channel / exr.amplitude_channels)
            "depth_channel": self.depth_channel,
            "amplitude_channel": self.amplitude_channel,
        }
