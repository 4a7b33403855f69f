"""On-disk capture stacks for calibration and validation (format `tofdenoise-captures-v1`).

A capture folder holds `.npy` stacks and one `index.json`:

    {
      "format": "tofdenoise-captures-v1",
      "kind": "sweep" | "dark" | "distances" | "validation",
      "num_taps": 4,
      "modulation_frequency_hz": 50000000.0,   # required for kind "sweep"
      "units": "e",                            # "e" (electrons, default) or "dn" (ADC numbers)
      "adc_gain_e_per_dn": 25.0,               # required when units == "dn" (DN are multiplied by it)
      "full_well_e": 100000.0,                 # optional (sweep): tap full-well capacity
      "roi": [y0, y1, x0, x1],                 # optional: region used for statistics (default: all)
      "stacks": [ {"file": "step_000.npy", ...per-stack fields...}, ... ]
    }

Stack arrays (any real dtype: float32/float64/uint16/int16/int32/uint32):
- tap stack (F, N, H, W): F repeated frames of the N taps;
- depth stack (F, H, W) in millimetres (kind "distances"/"validation" only), for "validation" with an
  `amplitude_file` (F, H, W) [e-] next to it.
Per-stack fields: sweep -> `phase_rad` (target phase psi) or `distance_mm`; dark -> none;
distances -> `distance_mm`; validation -> `group` ("range" | "signal" | "range_fit"), `distance_mm`,
optional `surface`, `exposure`, `amplitude_file`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.atomic import atomic_write_text, save_npy_atomic

FORMAT = "tofdenoise-captures-v1"
KINDS = ("sweep", "dark", "distances", "validation")
INDEX_NAME = "index.json"
_REAL_KINDS = "fiu"  # float, signed int, unsigned int


class CaptureFormatError(ValueError):
    """A capture folder, index or stack does not follow the documented format (message names the file)."""


@dataclass
class CaptureIndex:
    folder: Path
    kind: str
    num_taps: int
    units: str = "e"
    adc_gain_e_per_dn: float | None = None
    modulation_frequency_hz: float | None = None
    full_well_e: float | None = None
    roi: tuple[int, int, int, int] | None = None
    stacks: list[dict[str, Any]] = field(default_factory=list)

    @property
    def scale_to_e(self) -> float:
        return 1.0 if self.units == "e" else float(self.adc_gain_e_per_dn)  # type: ignore[arg-type]


def _positive(value: Any, name: str, where: Path) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CaptureFormatError(f"{where}: field '{name}' must be a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise CaptureFormatError(f"{where}: field '{name}' must be a finite number > 0, got {value!r}")
    return v


def read_index(folder: str | os.PathLike[str], expected_kind: str | None = None) -> CaptureIndex:
    """Read and check `folder/index.json`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"capture folder not found: {folder}")
    path = folder / INDEX_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing capture index (see docs/physics.md, 'Capture files')")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CaptureFormatError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CaptureFormatError(f"{path}: the index must be a JSON object")
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise CaptureFormatError(f"{path}: field 'format' must be '{FORMAT}', got {fmt!r}")
    kind = data.get("kind")
    if kind not in KINDS:
        raise CaptureFormatError(f"{path}: field 'kind' must be one of {list(KINDS)}, got {kind!r}")
    if expected_kind is not None and kind != expected_kind:
        raise CaptureFormatError(f"{path}: expected a '{expected_kind}' capture folder, index says kind={kind!r}")
    n = data.get("num_taps")
    if isinstance(n, bool) or not isinstance(n, int) or n < 3:
        raise CaptureFormatError(f"{path}: field 'num_taps' must be an integer >= 3, got {n!r}")
    units = data.get("units", "e")
    if units not in ("e", "dn"):
        raise CaptureFormatError(f"{path}: field 'units' must be 'e' or 'dn', got {units!r}")
    gain = data.get("adc_gain_e_per_dn")
    if gain is not None:
        gain = _positive(gain, "adc_gain_e_per_dn", path)
    if units == "dn" and gain is None:
        raise CaptureFormatError(f"{path}: units 'dn' need field 'adc_gain_e_per_dn' (electrons per DN)")
    freq = data.get("modulation_frequency_hz")
    if freq is not None:
        freq = _positive(freq, "modulation_frequency_hz", path)
    if kind == "sweep" and freq is None:
        raise CaptureFormatError(f"{path}: a sweep index needs field 'modulation_frequency_hz'")
    fw = data.get("full_well_e")
    if fw is not None:
        fw = _positive(fw, "full_well_e", path)
    roi = data.get("roi")
    if roi is not None:
        if not isinstance(roi, list) or len(roi) != 4 or not all(isinstance(v, int) for v in roi):
            raise CaptureFormatError(f"{path}: field 'roi' must be [y0, y1, x0, x1] (integers), got {roi!r}")
        if roi[0] < 0 or roi[2] < 0 or roi[1] <= roi[0] or roi[3] <= roi[2]:
            raise CaptureFormatError(f"{path}: field 'roi' must satisfy 0 <= y0 < y1 and 0 <= x0 < x1, got {roi}")
        roi = tuple(roi)
    stacks = data.get("stacks")
    if not isinstance(stacks, list) or not stacks:
        raise CaptureFormatError(f"{path}: field 'stacks' must be a non-empty list of {{'file': ...}} entries")
    for i, entry in enumerate(stacks):
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
            raise CaptureFormatError(f"{path}: stacks[{i}] must be an object with a 'file' name")
        if kind == "sweep" and ("phase_rad" in entry) == ("distance_mm" in entry):
            raise CaptureFormatError(f"{path}: stacks[{i}] needs exactly one of 'phase_rad' or 'distance_mm'")
        if kind in ("distances", "validation"):
            if "distance_mm" not in entry:
                raise CaptureFormatError(f"{path}: stacks[{i}] needs field 'distance_mm'")
            _positive(entry["distance_mm"], f"stacks[{i}].distance_mm", path)
        if kind == "validation" and entry.get("group") not in ("range", "signal", "range_fit"):
            raise CaptureFormatError(
                f"{path}: stacks[{i}].group must be 'range', 'signal' or 'range_fit', got {entry.get('group')!r}"
            )
    return CaptureIndex(
        folder=folder,
        kind=kind,
        num_taps=n,
        units=units,
        adc_gain_e_per_dn=gain,
        modulation_frequency_hz=freq,
        full_well_e=fw,
        roi=roi,
        stacks=stacks,  # type: ignore[arg-type]
    )


def load_stack(index: CaptureIndex, file: str, ndim: tuple[int, ...] = (4,), scale: bool = True) -> np.ndarray:
    """Load one `.npy` stack as float64 (taps converted to electrons), checking shape and dtype.

    ndim: accepted numbers of dimensions: 4 = tap stack (F, N, H, W), 3 = depth/amplitude (F, H, W).
    """
    path = index.folder / file
    if not path.is_file():
        raise FileNotFoundError(f"{path}: stack listed in {index.folder / INDEX_NAME} not found")
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as exc:
        raise CaptureFormatError(f"{path}: cannot read as a .npy array: {exc}") from None
    expected = " or ".join({4: f"(frames, {index.num_taps}, H, W) taps", 3: "(frames, H, W)"}[n] for n in ndim)
    if arr.dtype.kind not in _REAL_KINDS:
        raise CaptureFormatError(f"{path}: dtype {arr.dtype} not supported; expected a real number array of {expected}")
    if arr.ndim not in ndim:
        raise CaptureFormatError(f"{path}: shape {arr.shape} not supported; expected {expected}")
    if arr.ndim == 4 and arr.shape[1] != index.num_taps:
        raise CaptureFormatError(
            f"{path}: shape {arr.shape} has {arr.shape[1]} taps on axis 1; expected (frames, {index.num_taps}, H, W)"
        )
    if arr.shape[0] < 2:
        raise CaptureFormatError(f"{path}: shape {arr.shape}: need at least 2 frames on axis 0")
    if index.roi is not None:
        y0, y1, x0, x1 = index.roi
        if y1 > arr.shape[-2] or x1 > arr.shape[-1]:
            raise CaptureFormatError(f"{path}: roi {list(index.roi)} exceeds the frame size {arr.shape[-2:]}")
        arr = arr[..., y0:y1, x0:x1]
    out = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise CaptureFormatError(f"{path}: contains NaN or inf values")
    if scale and arr.ndim == 4 and index.units == "dn":
        out = out * index.scale_to_e
    return out


def clipped_samples(index: CaptureIndex, file: str, values_e: np.ndarray, full_well_e: float | None) -> np.ndarray:
    """Boolean mask of the samples of a tap stack that sit at a clipping level: at or above ``full_well_e``
    [e-], or (integer stacks) at the dtype's maximum, e.g. 65535 for uint16 (``values_e`` as returned by
    :func:`load_stack`, in electrons). Clipped samples carry no measurement: calibration leaves them out."""
    dtype = np.load(index.folder / file, mmap_mode="r", allow_pickle=False).dtype
    clipped = np.zeros(values_e.shape, dtype=bool)
    if full_well_e is not None:
        clipped |= values_e >= float(full_well_e)
    if dtype.kind in "iu":
        top = float(np.iinfo(dtype).max) * (index.scale_to_e if index.units == "dn" else 1.0)
        clipped |= values_e >= top
    return clipped


def write_capture_folder(
    folder: str | os.PathLike[str],
    kind: str,
    num_taps: int,
    stacks: list[tuple[str, np.ndarray, dict[str, Any]]],
    **index_fields: Any,
) -> Path:
    """Write stacks (name, array, per-stack fields) and index.json; returns the folder."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for name, array, meta in stacks:
        file = name if name.endswith(".npy") else f"{name}.npy"
        save_npy_atomic(folder / file, array)
        entries.append({"file": file, **meta})
    index = {"format": FORMAT, "kind": kind, "num_taps": int(num_taps), **index_fields, "stacks": entries}
    atomic_write_text(folder / INDEX_NAME, json.dumps(index, indent=2) + "\n")
    return folder


__all__ = [
    "FORMAT",
    "INDEX_NAME",
    "KINDS",
    "CaptureFormatError",
    "CaptureIndex",
    "clipped_samples",
    "load_stack",
    "read_index",
    "write_capture_folder",
]
