"""Sensor calibration value types: the calibrated tap response c(x) and the sensor constants.

Paper (Sec. III-A): theta_n = 2 pi n / N, psi(D) = 4 pi f D / c_light, r_n(D) = c(psi(D) - theta_n),
mu_n = a r_n + mu_dark, sigma_n^2 = a r_n + sigma_dark^2. The calibrated tap response is stored as a
Fourier series c(x) = c0 + sum_k cos[k-1] cos(k x) + sin[k-1] sin(k x), k = 1..K.

Convention: c0 = 1 for calibrations produced by `tofdenoise.physics.calibrate`, so that the signal level
`a` is the returned-signal photo-electrons per tap averaged over a modulation period (above the dark
offset). Any c0 > 0 is accepted when loading.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tofdenoise.atomic import atomic_write_text
from tofdenoise.paths import CONFIG_DIR
from tofdenoise.physics import _backend as arrays

C_LIGHT_M_PER_S: float = 299_792_458.0
C_LIGHT_MM_PER_S: float = C_LIGHT_M_PER_S * 1000.0

FIELDS: tuple[str, ...] = (
    "num_taps",
    "modulation_frequency_hz",
    "tap_response",
    "dark_mean_e",
    "dark_std_e",
    "signal_min_e",
    "signal_max_e",
    "full_well_e",
    "adc_gain_e_per_dn",
    "range_sigma_mm",
    "signal_at_1m_e",
    "vignetting_cos_power",
    "fixed_pattern",
)
# optional fields that are left out of to_dict() (and so of the fingerprint) while unset: calibrations written
# before they existed keep their fingerprints
OPTIONAL_FIELDS: tuple[str, ...] = ("signal_at_1m_e", "vignetting_cos_power", "fixed_pattern")
FIXED_PATTERN_FIELDS: tuple[str, ...] = ("pixel_offset_e", "column_phase_rad", "prnu", "seed")
TAP_FIELDS: tuple[str, ...] = ("c0", "cos", "sin")


class CalibrationError(ValueError):
    """A calibration field is missing, malformed or out of range (message names the field)."""


def _where(source: str | None) -> str:
    return f"{source}: " if source else ""


def _field_error(
    source: str | None, unknown: list[str], missing: list[str], valid: Sequence[str], prefix: str = ""
) -> CalibrationError | None:
    """One error for the unknown and the missing fields of one mapping (``prefix``: its dotted path): each unknown
    field is named with the closest valid one (a missing one first: a typo), then the missing fields."""
    if not unknown and not missing:
        return None
    parts = []
    for key in unknown:
        close = difflib.get_close_matches(key, missing, n=1, cutoff=0.6) or difflib.get_close_matches(
            key, [v for v in valid if v not in missing], n=1, cutoff=0.6
        )
        hint = f" (did you mean '{prefix}{close[0]}'?)" if close else ""
        parts.append(f"unknown field '{prefix}{key}'{hint}")
    if missing:
        parts.append(f"missing field(s) {[prefix + m for m in missing]}")
    expected = f"; expected {[prefix + v for v in valid]}" if unknown else ""
    return CalibrationError(f"{_where(source)}{'; '.join(parts)}{expected}")


def _as_float(value: Any, name: str, source: str | None) -> float:
    if isinstance(value, bool) or value is None:
        raise CalibrationError(f"{_where(source)}field '{name}' must be a number, got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise CalibrationError(f"{_where(source)}field '{name}' must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise CalibrationError(f"{_where(source)}field '{name}' must be finite, got {value!r}")
    return out


def _as_float_tuple(value: Any, name: str, source: str | None, length: int | None = None) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise CalibrationError(f"{_where(source)}field '{name}' must be a list of numbers, got {value!r}")
    items = tuple(_as_float(v, f"{name}[{i}]", source) for i, v in enumerate(value))
    if length is not None and len(items) != length:
        raise CalibrationError(f"{_where(source)}field '{name}' must have {length} entries, got {len(items)}")
    return items


# ----------------------------------------------------------------------------------------------------
# Tap response
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TapResponse:
    """Calibrated tap response c(x) = c0 + sum_k cos[k-1] cos(kx) + sin[k-1] sin(kx) (paper Eq. 3)."""

    c0: float
    cos: tuple[float, ...]
    sin: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "c0", float(self.c0))
        object.__setattr__(self, "cos", tuple(float(v) for v in self.cos))
        object.__setattr__(self, "sin", tuple(float(v) for v in self.sin))
        if len(self.cos) != len(self.sin):
            raise CalibrationError(
                f"tap_response: 'cos' and 'sin' must have the same length (harmonics), "
                f"got {len(self.cos)} and {len(self.sin)}"
            )

    @property
    def num_harmonics(self) -> int:
        return len(self.cos)

    def harmonic(self, k: int) -> tuple[float, float]:
        """(cos, sin) coefficients of harmonic k >= 1 (zeros beyond K)."""
        if k < 1:
            raise ValueError(f"harmonic index must be >= 1, got {k}")
        if k > self.num_harmonics:
            return 0.0, 0.0
        return self.cos[k - 1], self.sin[k - 1]

    @property
    def first_harmonic_amplitude(self) -> float:
        """|C1| = sqrt(cos[0]^2 + sin[0]^2): the first-harmonic amplitude of c per unit signal."""
        c1, s1 = self.harmonic(1)
        return math.hypot(c1, s1)

    @property
    def contrast(self) -> float:
        """Demodulation contrast |C1| / c0 (1 for a full-contrast 0.5(1 + cos x) response)."""
        return self.first_harmonic_amplitude / self.c0

    def value(self, x: Any) -> Any:
        """c(x) for a numpy array or torch tensor of phases x [rad]."""
        xp = arrays.namespace(x)
        x = arrays.as_float_array(x)
        out = arrays.full_like(x, self.c0)
        for k, (ck, sk) in enumerate(zip(self.cos, self.sin), start=1):
            if ck:
                out = out + ck * xp.cos(k * x)
            if sk:
                out = out + sk * xp.sin(k * x)
        return out

    def derivative(self, x: Any) -> Any:
        """c'(x) = sum_k k (-cos[k-1] sin(kx) + sin[k-1] cos(kx))."""
        xp = arrays.namespace(x)
        x = arrays.as_float_array(x)
        out = arrays.full_like(x, 0.0)
        for k, (ck, sk) in enumerate(zip(self.cos, self.sin), start=1):
            if ck:
                out = out - (k * ck) * xp.sin(k * x)
            if sk:
                out = out + (k * sk) * xp.cos(k * x)
        return out

    def tap_matrices(self, num_taps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Constant matrices that give every tap from the harmonics of psi in one product.

        With h(psi) = [cos(psi), ..., cos(K psi), sin(psi), ..., sin(K psi)] (length 2K):
        c(psi - theta_n) = c0 + (h @ R)[n] and c'(psi - theta_n) = (h @ G)[n], theta_n = 2 pi n / N.
        Returns (R, G, theta, k) with R, G of shape (2K, N).
        """
        K = self.num_harmonics
        theta = 2.0 * np.pi * np.arange(num_taps) / num_taps
        k = np.arange(1, K + 1, dtype=np.float64)
        ck = np.asarray(self.cos, dtype=np.float64)[:, None]
        sk = np.asarray(self.sin, dtype=np.float64)[:, None]
        kt = k[:, None] * theta[None, :]
        # c_k cos(k(psi - t)) + s_k sin(k(psi - t))
        #   = cos(k psi) [c_k cos(kt) - s_k sin(kt)] + sin(k psi) [c_k sin(kt) + s_k cos(kt)]
        a_nk = ck * np.cos(kt) - sk * np.sin(kt)  # multiplies cos(k psi)
        b_nk = ck * np.sin(kt) + sk * np.cos(kt)  # multiplies sin(k psi)
        R = np.concatenate([a_nk, b_nk], axis=0)
        # derivative: d/dpsi [A cos(k psi) + B sin(k psi)] = k(-A sin(k psi) + B cos(k psi))
        G = np.concatenate([k[:, None] * b_nk, -k[:, None] * a_nk], axis=0)
        # exact zeros where cos/sin(k theta_n) vanish analytically (e.g. cos(pi/2) = 6e-17), so that
        # vectorised evaluations can skip them; relative change <= 1e-12
        tol = 1e-12 * max(1.0, float(np.max(np.abs(R))), float(np.max(np.abs(G))))
        R[np.abs(R) < tol] = 0.0
        G[np.abs(G) < tol] = 0.0
        return R, G, theta, k

    def minimum(self, samples: int = 4096) -> float:
        x = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
        return float(np.min(self.value(x)))

    def to_dict(self) -> dict[str, Any]:
        return {"c0": self.c0, "cos": list(self.cos), "sin": list(self.sin)}

    @classmethod
    def from_dict(cls, d: Any, source: str | None = None) -> TapResponse:
        if not isinstance(d, Mapping):
            raise CalibrationError(f"{_where(source)}field 'tap_response' must be a mapping with c0, cos, sin")
        missing = [name for name in TAP_FIELDS if name not in d]
        unknown = sorted(str(k) for k in d if k not in TAP_FIELDS)
        error = _field_error(source, unknown, missing, TAP_FIELDS, "tap_response.")
        if error is not None:
            raise error
        c0 = _as_float(d["c0"], "tap_response.c0", source)
        cos = _as_float_tuple(d["cos"], "tap_response.cos", source)
        sin = _as_float_tuple(d["sin"], "tap_response.sin", source)
        if len(cos) != len(sin):
            raise CalibrationError(
                f"{_where(source)}fields 'tap_response.cos' and 'tap_response.sin' must have the same length, "
                f"got {len(cos)} and {len(sin)}"
            )
        return cls(c0=c0, cos=cos, sin=sin)


# ----------------------------------------------------------------------------------------------------
# Fixed-pattern noise of a (simulated) camera
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FixedPatternNoise:
    """Spatial noise that is the same in every frame of a camera (the capture simulator's; not in the WLS model).

    pixel_offset_e    std [e-] of a per-pixel, per-tap dark offset (DSNU): it does not cancel in the N-phase
                      demodulation, so its depth error falls as 1 / signal
    column_phase_rad  std [rad] of a per-column phase offset (modulation-clock skew across the column drivers):
                      a depth offset that does not change with signal or exposure
    prnu              std of a per-pixel relative gain (photo-response non-uniformity), the same on every tap
    seed              the pattern's seed: one camera, one pattern (drawn per frame size from it)
    """

    pixel_offset_e: float = 0.0
    column_phase_rad: float = 0.0
    prnu: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("pixel_offset_e", "column_phase_rad", "prnu"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v < 0:
                raise CalibrationError(f"field 'fixed_pattern.{name}' must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, v)
        if self.prnu >= 0.5:
            raise CalibrationError(f"field 'fixed_pattern.prnu' must be < 0.5 (a relative gain std), got {self.prnu}")
        seed = self.seed
        if isinstance(seed, bool) or int(seed) != seed or seed < 0:
            raise CalibrationError(f"field 'fixed_pattern.seed' must be an integer >= 0, got {seed!r}")
        object.__setattr__(self, "seed", int(seed))

    @property
    def is_zero(self) -> bool:
        return self.pixel_offset_e == 0 and self.column_phase_rad == 0 and self.prnu == 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "pixel_offset_e": self.pixel_offset_e,
            "column_phase_rad": self.column_phase_rad,
            "prnu": self.prnu,
            "seed": self.seed,
        }

    @classmethod
    def from_dict(cls, d: Any, source: str | None = None) -> FixedPatternNoise:
        d = _plain_mapping(d)
        if not isinstance(d, Mapping):
            raise CalibrationError(f"{_where(source)}field 'fixed_pattern' must be a mapping, got {type(d).__name__}")
        unknown = sorted(str(k) for k in d if k not in FIXED_PATTERN_FIELDS)
        error = _field_error(source, unknown, [], FIXED_PATTERN_FIELDS, "fixed_pattern.")
        if error is not None:
            raise error
        values: dict[str, Any] = {}
        for name in ("pixel_offset_e", "column_phase_rad", "prnu"):
            if name in d:
                values[name] = _as_float(d[name], f"fixed_pattern.{name}", source)
        if "seed" in d:
            seed = d["seed"]
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
                raise CalibrationError(f"{_where(source)}field 'fixed_pattern.seed' must be an integer, got {seed!r}")
            values["seed"] = int(seed)
        try:
            return cls(**values)
        except CalibrationError as exc:
            raise CalibrationError(f"{_where(source)}{exc}") from None


# ----------------------------------------------------------------------------------------------------
# Sensor calibration
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorCalibration:
    """All sensor constants the depth-uncertainty model and the capture simulator need.

    Frozen; every field is checked when the calibration is made, and a bad one raises ``CalibrationError``
    naming it. Stored as YAML or JSON in the ``to_dict()`` layout (``load_calibration``, ``save_calibration``);
    ``replace`` gives a changed copy.

    Args:
        num_taps: N >= 3 phase-shifted taps per modulation cycle (theta_n = 2 pi n / N).
        modulation_frequency_hz: f; the unambiguous range is c / (2 f).
        tap_response: the calibrated tap response c(x), a Fourier series (a ``TapResponse`` or its mapping).
        dark_mean_e: mu_dark, the mean dark/ambient offset per tap [e-].
        dark_std_e: sigma_dark, the residual dark/read (+ ambient shot, + ADC) noise std per tap [e-].
        signal_min_e: a_min, the low end of the empirical returned-signal interval [e-].
        signal_max_e: a_max, its high end [e-].
        full_well_e: the tap full-well capacity [e-]; taps clip there (saturation).
        adc_gain_e_per_dn: the ADC conversion gain [e-/DN], or None (no quantisation).
        range_sigma_mm: (alpha0 [mm], alpha1 [mm/mm], alpha2 [mm/mm^2]) of the range-aware baseline
            sigma(D) = alpha0 + alpha1 D + alpha2 D^2 (D in mm), or None.
        signal_at_1m_e: the photometric gain K: returned signal per tap [e-] of a white (reflectance 1)
            Lambertian target, frontal, at 1 m, exposure 1 (emitter power, optics and quantum efficiency folded
            in), for the physical signal route (``tofdenoise.physics.photometry``). None: the camera has no
            photometric model.
        vignetting_cos_power: the lens fall-off V = cos^k(field angle) of the physical signal route (None: none).
        fixed_pattern: the camera's fixed-pattern noise (``FixedPatternNoise``: per-pixel tap offsets, column
            phase offsets, PRNU), applied by the capture simulator only; the WLS model does not contain it
            (paper Sec. III-A assumes it calibrated away). None: none.
    """

    num_taps: int
    modulation_frequency_hz: float
    tap_response: TapResponse
    dark_mean_e: float
    dark_std_e: float
    signal_min_e: float
    signal_max_e: float
    full_well_e: float
    adc_gain_e_per_dn: float | None = None
    range_sigma_mm: tuple[float, float, float] | None = field(default=None)
    signal_at_1m_e: float | None = None
    vignetting_cos_power: float | None = None
    fixed_pattern: FixedPatternNoise | None = None

    def __post_init__(self) -> None:
        if isinstance(self.tap_response, Mapping):
            object.__setattr__(self, "tap_response", TapResponse.from_dict(self.tap_response))
        if isinstance(self.fixed_pattern, Mapping):
            object.__setattr__(self, "fixed_pattern", FixedPatternNoise.from_dict(self.fixed_pattern))
        if self.range_sigma_mm is not None:
            object.__setattr__(self, "range_sigma_mm", tuple(float(v) for v in self.range_sigma_mm))
        validate_calibration(self)

    # -- derived quantities -------------------------------------------------------------------------
    @property
    def unambiguous_range_mm(self) -> float:
        """c_light / (2 f) in millimetres."""
        return C_LIGHT_MM_PER_S / (2.0 * self.modulation_frequency_hz)

    @property
    def phase_per_mm(self) -> float:
        """d psi / dD = 4 pi f / c_light [rad/mm] (paper Eq. 2)."""
        return 4.0 * math.pi * self.modulation_frequency_hz / C_LIGHT_MM_PER_S

    @property
    def tap_phases_rad(self) -> np.ndarray:
        """theta_n = 2 pi n / N (paper Eq. 1)."""
        return 2.0 * np.pi * np.arange(self.num_taps) / self.num_taps

    def replace(self, **changes: Any) -> SensorCalibration:
        """A copy with some fields changed, checked like a new calibration.

        Args:
            **changes: field names and their new values (``calib.replace(dark_std_e=8.0)``).

        Raises:
            CalibrationError: a name is not a field, or a new value is out of range.
        """
        d = self.to_dict()
        for key, value in changes.items():
            if key not in FIELDS:
                raise CalibrationError(f"unknown calibration field '{key}'")
            d[key] = value.to_dict() if isinstance(value, (TapResponse, FixedPatternNoise)) else value
        return SensorCalibration.from_dict(d, source="replace()")

    # -- serialisation ------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain values (numbers, lists, mappings), the layout of the YAML and JSON files; optional fields that
        are None are left out."""
        d: dict[str, Any] = {
            "num_taps": int(self.num_taps),
            "modulation_frequency_hz": float(self.modulation_frequency_hz),
            "tap_response": self.tap_response.to_dict(),
            "dark_mean_e": float(self.dark_mean_e),
            "dark_std_e": float(self.dark_std_e),
            "signal_min_e": float(self.signal_min_e),
            "signal_max_e": float(self.signal_max_e),
            "full_well_e": float(self.full_well_e),
            "adc_gain_e_per_dn": None if self.adc_gain_e_per_dn is None else float(self.adc_gain_e_per_dn),
            "range_sigma_mm": None if self.range_sigma_mm is None else [float(v) for v in self.range_sigma_mm],
        }
        if self.signal_at_1m_e is not None:
            d["signal_at_1m_e"] = float(self.signal_at_1m_e)
        if self.vignetting_cos_power is not None:
            d["vignetting_cos_power"] = float(self.vignetting_cos_power)
        if self.fixed_pattern is not None:
            d["fixed_pattern"] = self.fixed_pattern.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: Any, source: str | None = None) -> SensorCalibration:
        """Build from a mapping in the ``to_dict()`` layout; keys starting with '_' are ignored.

        Args:
            d: the mapping (a plain dict or a Hydra/OmegaConf node).
            source: what the mapping came from (a file name), put in front of error messages.

        Raises:
            CalibrationError: a field is missing, unknown, malformed or out of range; the message names it.
        """
        d = _plain_mapping(d)
        if not isinstance(d, Mapping):
            raise CalibrationError(f"{_where(source)}a calibration must be a mapping, got {type(d).__name__}")
        d = {k: v for k, v in d.items() if not str(k).startswith("_")}
        missing = [name for name in FIELDS if name not in d]
        # adc_gain_e_per_dn and range_sigma_mm are optional (None when absent)
        missing = [m for m in missing if m not in ("adc_gain_e_per_dn", "range_sigma_mm", *OPTIONAL_FIELDS)]
        unknown = sorted(str(k) for k in d if k not in FIELDS)
        error = _field_error(source, unknown, missing, FIELDS)
        if error is not None:
            raise error
        num_taps_raw = d["num_taps"]
        if (
            isinstance(num_taps_raw, bool)
            or not isinstance(num_taps_raw, (int, np.integer))
            and not (isinstance(num_taps_raw, float) and num_taps_raw.is_integer())
        ):
            raise CalibrationError(f"{_where(source)}field 'num_taps' must be an integer >= 3, got {num_taps_raw!r}")
        gain = d.get("adc_gain_e_per_dn")
        rs = d.get("range_sigma_mm")
        k1m = d.get("signal_at_1m_e")
        vig = d.get("vignetting_cos_power")
        fpn = d.get("fixed_pattern")
        try:
            return cls(
                num_taps=int(num_taps_raw),
                modulation_frequency_hz=_as_float(d["modulation_frequency_hz"], "modulation_frequency_hz", source),
                tap_response=TapResponse.from_dict(d["tap_response"], source=source),
                dark_mean_e=_as_float(d["dark_mean_e"], "dark_mean_e", source),
                dark_std_e=_as_float(d["dark_std_e"], "dark_std_e", source),
                signal_min_e=_as_float(d["signal_min_e"], "signal_min_e", source),
                signal_max_e=_as_float(d["signal_max_e"], "signal_max_e", source),
                full_well_e=_as_float(d["full_well_e"], "full_well_e", source),
                adc_gain_e_per_dn=None if gain is None else _as_float(gain, "adc_gain_e_per_dn", source),
                range_sigma_mm=None if rs is None else _as_float_tuple(rs, "range_sigma_mm", source, length=3),  # type: ignore[arg-type]
                signal_at_1m_e=None if k1m is None else _as_float(k1m, "signal_at_1m_e", source),
                vignetting_cos_power=None if vig is None else _as_float(vig, "vignetting_cos_power", source),
                fixed_pattern=None if fpn is None else FixedPatternNoise.from_dict(fpn, source=source),
            )
        except CalibrationError as exc:
            msg = str(exc)
            if source and not msg.startswith(f"{source}:"):
                msg = f"{source}: {msg}"
            raise CalibrationError(msg) from None

    def to_json(self) -> str:
        """``to_dict()`` as indented JSON."""
        return json.dumps(self.to_dict(), indent=2)

    def fingerprint(self) -> str:
        """Hex sha256 of the canonical JSON (sorted keys, no spaces): a cache key for derived data."""
        canonical = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def _plain_mapping(d: Any) -> Any:
    """Convert an omegaconf DictConfig (e.g. a Hydra node) to a plain dict; leave others alone."""
    from omegaconf import DictConfig, OmegaConf

    return OmegaConf.to_container(d, resolve=True) if isinstance(d, DictConfig) else d


def _check_optional_number(calib: SensorCalibration, name: str, allow_zero: bool) -> None:
    """An optional field is null or a finite number > 0 (>= 0 with ``allow_zero``), stored as float."""
    value = getattr(calib, name)
    if value is None:
        return
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise CalibrationError(f"field '{name}' must be a finite number {bound} or null, got {value!r}")
    object.__setattr__(calib, name, v)


def validate_calibration(calib: SensorCalibration) -> None:
    """Range checks; raises CalibrationError naming the offending field."""
    if isinstance(calib.num_taps, bool) or int(calib.num_taps) != calib.num_taps or calib.num_taps < 3:
        raise CalibrationError(f"field 'num_taps' must be an integer >= 3, got {calib.num_taps!r}")
    object.__setattr__(calib, "num_taps", int(calib.num_taps))
    checks_positive = {
        "modulation_frequency_hz": calib.modulation_frequency_hz,
        "dark_std_e": calib.dark_std_e,
        "signal_min_e": calib.signal_min_e,
        "signal_max_e": calib.signal_max_e,
        "full_well_e": calib.full_well_e,
    }
    for name, value in checks_positive.items():
        v = float(value)
        if not math.isfinite(v) or v <= 0:
            raise CalibrationError(f"field '{name}' must be a finite number > 0, got {value!r}")
        object.__setattr__(calib, name, v)
    dm = float(calib.dark_mean_e)
    if not math.isfinite(dm) or dm < 0:
        raise CalibrationError(f"field 'dark_mean_e' must be a finite number >= 0, got {calib.dark_mean_e!r}")
    object.__setattr__(calib, "dark_mean_e", dm)
    if calib.signal_max_e <= calib.signal_min_e:
        raise CalibrationError(
            f"field 'signal_max_e' ({calib.signal_max_e}) must be greater than 'signal_min_e' ({calib.signal_min_e})"
        )
    if calib.full_well_e <= calib.dark_mean_e:
        raise CalibrationError(
            f"field 'full_well_e' ({calib.full_well_e}) must exceed 'dark_mean_e' ({calib.dark_mean_e})"
        )
    _check_optional_number(calib, "adc_gain_e_per_dn", allow_zero=False)
    if calib.range_sigma_mm is not None:
        if len(calib.range_sigma_mm) != 3 or not all(math.isfinite(v) for v in calib.range_sigma_mm):
            raise CalibrationError(
                f"field 'range_sigma_mm' must be 3 finite numbers [alpha0, alpha1, alpha2] or null, "
                f"got {calib.range_sigma_mm!r}"
            )
        a0, a1, a2 = calib.range_sigma_mm
        depths = np.linspace(10.0, calib.unambiguous_range_mm, 256)
        sigma = a0 + a1 * depths + a2 * depths**2
        if not np.all(sigma > 0):
            bad = float(depths[np.argmax(sigma <= 0)])
            raise CalibrationError(
                f"field 'range_sigma_mm' {list(calib.range_sigma_mm)} gives sigma(D) = alpha0 + alpha1 D + alpha2 D^2 "
                f"<= 0 at D = {bad:.0f} mm: the range-aware baseline's std must be > 0 from 10 mm to the unambiguous "
                f"range ({calib.unambiguous_range_mm:.0f} mm)"
            )
    _check_optional_number(calib, "signal_at_1m_e", allow_zero=False)
    _check_optional_number(calib, "vignetting_cos_power", allow_zero=True)
    tr = calib.tap_response
    if not isinstance(tr, TapResponse):
        raise CalibrationError(f"field 'tap_response' must be a TapResponse, got {type(tr).__name__}")
    if tr.num_harmonics < 1:
        raise CalibrationError("field 'tap_response.cos'/'tap_response.sin' must hold at least the first harmonic")
    if tr.c0 <= 0:
        raise CalibrationError(f"field 'tap_response.c0' must be > 0, got {tr.c0}")
    if tr.first_harmonic_amplitude <= 0:
        raise CalibrationError("field 'tap_response': the first harmonic (cos[0], sin[0]) must not be zero")
    if tr.minimum() < -1e-9 * tr.c0:
        raise CalibrationError(
            f"field 'tap_response': c(x) must be >= 0 for all x (a tap collects a non-negative charge); "
            f"minimum is {tr.minimum():.6g}"
        )


# ----------------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------------


def _suffix_kind(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return "yaml"
    if suffix == ".json":
        return "json"
    raise CalibrationError(f"{path}: calibration files must end in .yaml, .yml or .json, got '{path.suffix}'")


def load_calibration(path: str | os.PathLike[str]) -> SensorCalibration:
    """Read a calibration from YAML or JSON (chosen by the file suffix).

    Args:
        path: a ``.yaml``, ``.yml`` or ``.json`` file in the ``SensorCalibration.to_dict()`` layout.

    Raises:
        FileNotFoundError: there is no such file.
        CalibrationError: another suffix, not UTF-8, not parseable, or a field missing or out of range; the
            message names the file and the field.
    """
    path = Path(path)
    kind = _suffix_kind(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CalibrationError(
            f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); save the "
            f"calibration file as UTF-8"
        ) from None
    try:
        data = yaml.safe_load(text) if kind == "yaml" else json.loads(text)
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot parse {kind.upper()}: {exc}") from None
    return SensorCalibration.from_dict(data, source=str(path))


def check_calibration_out(path: str | os.PathLike[str]) -> Path:
    """A path a calibration can be written to: a .yaml/.yml/.json file name, not an existing folder (checked
    before the work that produces the calibration)."""
    path = Path(path)
    if path.is_dir():
        raise CalibrationError(f"{path} is a folder: give a calibration file name, e.g. {path / 'calibration.yaml'}")
    _suffix_kind(path)
    return path


def save_calibration(calib: SensorCalibration, path: str | os.PathLike[str], header: str | None = None) -> Path:
    """Write a calibration as YAML or JSON (by the suffix), atomically: a reader never sees half a file.

    Args:
        calib: the calibration.
        path: a ``.yaml``, ``.yml`` or ``.json`` file name (not an existing folder).
        header: comment lines written above the YAML fields (JSON has no comments and leaves it out).

    Returns:
        The path written.

    Raises:
        CalibrationError: the path is a folder or has another suffix.
    """
    path = check_calibration_out(path)
    kind = _suffix_kind(path)
    d = calib.to_dict()
    if kind == "json":
        text = json.dumps(d, indent=2) + "\n"
    else:
        text = yaml.safe_dump(d, sort_keys=False, default_flow_style=None)
        if header:
            text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines()) + text
    atomic_write_text(path, text)
    return path


def default_calibration() -> SensorCalibration:
    """The shipped default calibration, ``configs/sensor/default.yaml``."""
    return load_calibration(CONFIG_DIR / "sensor" / "default.yaml")


def resolve_calibration(spec: Any = None) -> SensorCalibration:
    """A calibration from any of the forms the configs and commands accept.

    Args:
        spec: None (the default calibration), a file path, the name of a shipped preset without suffix
            (``"default"``, ``"cam75"``: ``configs/sensor/<name>.yaml``), a mapping in the ``to_dict()`` layout
            (a Hydra DictConfig too) or a ``SensorCalibration`` (returned as it is).

    Raises:
        CalibrationError: no such file and no preset of that name (the presets are listed), or a bad field.
    """
    if spec is None:
        return default_calibration()
    if isinstance(spec, SensorCalibration):
        return spec
    if isinstance(spec, (str, os.PathLike)):
        p = Path(spec)
        if not p.suffix and not p.exists():
            preset = CONFIG_DIR / "sensor" / f"{spec}.yaml"
            if preset.is_file():
                return load_calibration(preset)
            presets = sorted(f.stem for f in (CONFIG_DIR / "sensor").glob("*.yaml"))
            raise CalibrationError(
                f"{spec}: no such file and no sensor preset of that name; presets: {', '.join(presets)} "
                f"(or a calibration file ending in .yaml, .yml or .json)"
            )
        return load_calibration(p)
    spec = _plain_mapping(spec)
    if isinstance(spec, Mapping):
        return SensorCalibration.from_dict(spec, source="calibration mapping")
    raise CalibrationError(
        f"cannot resolve a calibration from {type(spec).__name__}; expected None, a path, a mapping or a "
        f"SensorCalibration"
    )


__all__ = [
    "C_LIGHT_M_PER_S",
    "C_LIGHT_MM_PER_S",
    "CalibrationError",
    "FIELDS",
    "FixedPatternNoise",
    "check_calibration_out",
    "SensorCalibration",
    "TapResponse",
    "default_calibration",
    "load_calibration",
    "resolve_calibration",
    "save_calibration",
    "validate_calibration",
]
