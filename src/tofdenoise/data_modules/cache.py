"""On-disk cache of per-sample maps (clean depth, signal, sigma_D, mask, amplitude).

Layout (``cache_dir`` = ``data.cache_dir``)::

    cache_dir/<source>-<source digest>/source.json          what the source is (root, size, seed ...)
    cache_dir/<source>-<source digest>/split_seed<S>_<r>.json the seeded split (inspect / reuse)
    cache_dir/<source>-<source digest>/maps-<key digest>/key.json
    cache_dir/<source>-<source digest>/maps-<key digest>/<sample id>.npz
    cache_dir/<source>-<source digest>/maps-<key digest>/index.json          valid-pixel count per sample
    cache_dir/<source>-<source digest>/maps-<key digest>/variance_scale_*.json  Gaussian-baseline scales

The key digest covers the format version, the source description, the calibration fingerprint and the
signal-mapping settings, so a changed calibration never reuses stale maps (it gets a new folder).

A file-backed source (one with ``files(sample_id)``: folder, flyingthings3d) changes under the same key when a file
is rewritten. Each of its entries therefore records the stamps of the files it was computed from
(``file_stamps``: size, mtime, ctime, inode and SHA-256, taken before the files are read) and is used only while
those files have that content: an entry whose files changed (another size or SHA-256, another set of files) is
"stale", recomputed and rewritten; one whose files were only touched or copied (stat moved, same SHA-256) is
rewritten with the new stamps. An entry of such a source without stamps is stale. Entries of a source without
files (procedural) hold no stamps, as before.

Entries are uncompressed ``.npz`` files written to a unique temporary name and renamed into place
(``os.replace``), so concurrent DataLoader workers and processes never read a partial file; the last writer
wins and every version is complete. Each entry also stores its own key digest and sample id. A truncated or
corrupt entry (zip CRC error, missing array, wrong key, shape mismatch) is detected on read, recomputed and
rewritten; it is never used.
"""

from __future__ import annotations

import hashlib
import json
import re
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.atomic import atomic_write, atomic_write_text
from tofdenoise.data_modules.file_stamps import file_stamps, stamps_state

FORMAT_VERSION = 1
MAP_NAMES = ("depth_mm", "signal_e", "sigma_mm", "mask", "amplitude")


@dataclass
class SampleMaps:
    """Per-sample maps, each (H, W): float32 except ``mask`` (bool). Invalid pixels hold 0."""

    depth_mm: np.ndarray
    signal_e: np.ndarray
    sigma_mm: np.ndarray
    mask: np.ndarray
    amplitude: np.ndarray

    @property
    def num_valid(self) -> int:
        return int(self.mask.sum())

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in MAP_NAMES}


def canonical_digest(obj: Any) -> str:
    """sha256 hex digest of the canonical JSON of a plain-value object."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def safe_name(sample_id: str) -> str:
    """A file-name-safe, collision-free name for a sample id (ids may contain '/')."""
    clean = re.sub(r"[^A-Za-z0-9._-]+", "_", sample_id).strip("._") or "sample"
    if clean == sample_id:
        return clean
    return f"{clean[:80]}-{hashlib.sha1(sample_id.encode()).hexdigest()[:10]}"


class CacheEntryError(ValueError):
    """A cache entry is unreadable, truncated or belongs to another key."""


@dataclass
class CacheStats:
    hits: int = 0
    misses: int = 0
    corrupt: int = 0
    corrupt_ids: list[str] = field(default_factory=list)
    stale: int = 0  # entries recomputed because the files they were computed from changed
    stale_ids: list[str] = field(default_factory=list)
    restamped: int = 0  # entries whose files were touched or copied with the same content: stamps rewritten


class MapCache:
    """Per-sample map files under ``folder`` for one key (see the module docstring)."""

    def __init__(self, folder: str | Path, key: dict[str, Any], enabled: bool = True):
        self.key = {"format_version": FORMAT_VERSION, **key}
        self.digest = canonical_digest(self.key)
        self.folder = Path(folder) / f"maps-{self.digest[:16]}"
        self.enabled = enabled
        self.stats = CacheStats()
        self.folder.mkdir(parents=True, exist_ok=True)
        key_file = self.folder / "key.json"
        if not key_file.is_file():
            atomic_write_text(key_file, json.dumps(self.key, indent=1, sort_keys=True, default=str) + "\n")

    def path(self, sample_id: str) -> Path:
        return self.folder / f"{safe_name(sample_id)}.npz"

    # ------------------------------------------------------------------ entries
    def read(self, sample_id: str) -> SampleMaps:
        """Read and verify one entry; raises FileNotFoundError (absent) or CacheEntryError (corrupt)."""
        return self._read(sample_id)[0]

    def _read(self, sample_id: str) -> tuple[SampleMaps, dict[str, Any]]:
        path = self.path(sample_id)
        if not path.is_file():
            raise FileNotFoundError(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(bytes(data["meta"]).decode("utf-8"))
                arrays = {name: data[name] for name in MAP_NAMES}  # reading to the end checks each zip CRC
        except FileNotFoundError:
            raise
        except (
            zipfile.BadZipFile,
            KeyError,
            ValueError,
            OSError,
            EOFError,
            json.JSONDecodeError,
            UnicodeDecodeError,
        ) as exc:
            raise CacheEntryError(f"cache entry {path} is unreadable: {exc}") from exc
        if not isinstance(meta, dict) or meta.get("key") != self.digest or meta.get("sample_id") != sample_id:
            raise CacheEntryError(f"cache entry {path} belongs to another key or sample")
        shape = tuple(meta.get("shape", ()))
        for name, array in arrays.items():
            if array.shape != shape:
                raise CacheEntryError(f"cache entry {path}: {name} has shape {array.shape}, expected {shape}")
        maps = SampleMaps(
            depth_mm=arrays["depth_mm"],
            signal_e=arrays["signal_e"],
            sigma_mm=arrays["sigma_mm"],
            mask=arrays["mask"].astype(bool),
            amplitude=arrays["amplitude"],
        )
        return maps, meta

    def write(self, sample_id: str, maps: SampleMaps, stamps: dict[str, Any] | None = None) -> Path:
        """Write one entry atomically; ``stamps`` (``file_stamps`` of the source files it was computed from) are
        recorded in its meta (a source without files: None, and the meta is what it always was)."""
        fields: dict[str, Any] = {
            "key": self.digest,
            "sample_id": sample_id,
            "shape": list(maps.depth_mm.shape),
            "format_version": FORMAT_VERSION,
        }
        if stamps is not None:
            fields["files"] = stamps
        meta = json.dumps(fields).encode("utf-8")
        arrays = maps.arrays()
        arrays["mask"] = arrays["mask"].astype(np.uint8)

        def _write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:
                np.savez(handle, meta=np.frombuffer(meta, dtype=np.uint8), **arrays)

        return atomic_write(self.path(sample_id), _write, suffix=".npz")

    def get_or_compute(
        self, sample_id: str, compute: Callable[[], SampleMaps], files: list[Path] | None = None
    ) -> tuple[SampleMaps, str]:
        """Return (maps, status) with status "hit", "miss" (computed, written), "corrupt" (recomputed), "stale"
        (``files`` changed since the entry was computed: recomputed) or "disabled" (computed, not stored).
        ``files``: the source files the maps are computed from (None for a source without files)."""
        maps, status, _ = self.get_or_compute_stamped(sample_id, compute, files, stamps_wanted=False)
        return maps, status

    def get_or_compute_stamped(
        self,
        sample_id: str,
        compute: Callable[[], SampleMaps],
        files: list[Path] | None = None,
        *,
        stamps_wanted: bool = True,
    ) -> tuple[SampleMaps, str, dict[str, Any] | None]:
        """``get_or_compute`` and the stamps of ``files`` the returned maps were computed from (None without
        ``files``; with the cache disabled, taken only when ``stamps_wanted``)."""
        if not self.enabled:
            stamps = file_stamps(files) if files is not None and stamps_wanted else None
            return compute(), "disabled", stamps
        try:
            maps, meta = self._read(sample_id)
        except FileNotFoundError:
            status = "miss"
            self.stats.misses += 1
        except CacheEntryError:
            status = "corrupt"
            self.stats.corrupt += 1
            self.stats.corrupt_ids.append(sample_id)
        else:
            if files is None:
                self.stats.hits += 1
                return maps, "hit", None
            state, new_stamps = stamps_state(meta.get("files"), files)
            if state == "fresh":
                self.stats.hits += 1
                return maps, "hit", meta["files"]
            if state == "restamped":
                self.write(sample_id, maps, new_stamps)
                self.stats.hits += 1
                self.stats.restamped += 1
                return maps, "hit", new_stamps
            status = "stale"
            self.stats.stale += 1
            self.stats.stale_ids.append(sample_id)
        stamps = file_stamps(files) if files is not None else None  # before the files are read
        maps = compute()
        self.write(sample_id, maps, stamps)
        return maps, status, stamps

    # ------------------------------------------------------------------ small JSON records next to the maps
    def record_path(self, name: str) -> Path:
        return self.folder / name

    def load_record(self, name: str, expected_key: dict[str, Any] | None = None) -> dict | None:
        """A JSON record written by ``save_record``; None if absent, unreadable, or saved under another key."""
        path = self.record_path(name)
        try:
            payload = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            return None
        if expected_key is not None and payload.get("key") != canonical_digest(expected_key):
            return None
        return payload

    def save_record(self, name: str, payload: dict, key: dict[str, Any] | None = None) -> Path:
        body = dict(payload)
        if key is not None:
            body["key"] = canonical_digest(key)
            body["key_fields"] = key
        return atomic_write_text(self.record_path(name), json.dumps(body, indent=1, default=str) + "\n")
