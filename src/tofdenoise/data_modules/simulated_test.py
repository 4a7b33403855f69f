"""The simulator-noised test split: the test samples captured by the tap-level simulator instead of noised by the
WLS closed form.

The paper's protocol synthesises the test inputs as the training inputs are synthesised, D + sigma_D(p) eps
(``data.eval_noise=hetero``): for a network trained on hetero noise that test is in-distribution by
construction. This split keeps the same clean targets (the test split's depth and valid mask, the same scoring
rule) and replaces the noise by a capture: per test sample, one standard-exposure frame of the capture simulator
(``tofdenoise.physics.simulator``):

- the returned signal a(p) of the sample's maps (``maps.signal_e``, the a the WLS sigma_D is computed from) and
  its clean depth give each tap's expected photo-electrons; Poisson shot noise, the dark offset with its Gaussian
  dark/read noise, full-well clipping and ADC quantisation follow, and the camera's N-phase atan2 demodulation
  (not a weighted fit: it does not reach the WLS bound when the taps' variances differ) decodes depth and
  amplitude;
- mixed pixels (``mixed_pixels`` = s > 1, a source that can render on a finer grid: the procedural scenes): each
  pixel's taps integrate s x s samples of the scene rendered at s times the resolution, so a pixel at a depth edge
  is a flying pixel between the surfaces; the target stays the 1x render, as in the stand-in capture set;
- fixed-pattern noise: the calibration's own when it has one, else ``DEFAULT_FIXED_PATTERN`` (the stand-in camera's
  magnitudes: 6 e- tap offsets, 0.016 rad column phase, 1 % PRNU; a calibration estimated from captures has none);
- validity as the camera decides it: a pixel whose measured amplitude is below the simulator's threshold or that
  saturates is invalid (0 in the input and out of ``mask``), on top of the test split's own mask. No hole model
  runs: the camera's own low-signal decision makes the holes.

Conventions, so the split scores like the paper-protocol split: depth in mm along the same axis as the targets (the
simulator's D is the sample's depth, the axis sigma_D is computed on); the decoded phase wraps at the unambiguous
range, and the estimate is unwrapped with the target's own phase cycle (``unwrap_to_reference_mm``: the integer
ambiguity a multi-frequency camera resolves, not the noise), so a scene that reaches the unambiguous range is not
scored as a metre-sized error. The network input is the captured depth and the measured amplitude, as on a capture
set; ``sigma`` carries the maps' WLS sigma_D (what a hetero-trained loss would weight with).

Every sample draws from its own generator (``stable_seed(seed, "test_simulated", sample id)``): the same inputs in
every run. Captures are computed once and stored atomically in a cache folder of their own, keyed on the maps'
digest, the seed and the settings (``SimulatedTestSettings.key``), as :class:`~tofdenoise.data_modules.cache.SampleMaps`
whose ``depth_mm`` is the captured depth and ``amplitude`` the measured amplitude.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from tofdenoise.data_modules.cache import MapCache, SampleMaps
from tofdenoise.data_modules.datasets import stable_seed
from tofdenoise.data_modules.maps import signal_from_amplitude_e
from tofdenoise.data_modules.sources.procedural import ProceduralSource
from tofdenoise.physics.calibration import FixedPatternNoise
from tofdenoise.physics.mixed_pixels import footprint_tap_means_e
from tofdenoise.physics.photometry import field_cosine
from tofdenoise.physics.simulator import simulate_frames, simulate_tap_mean_frames

__all__ = [
    "DEFAULT_FIXED_PATTERN",
    "SIMULATED_SET",
    "SimulatedCaptures",
    "SimulatedTestSettings",
    "simulate_test_capture",
    "simulated_cache",
    "unwrap_to_reference_mm",
]

#: the test set's name in ``metrics.json`` and ``datamodule.test_set_names``
SIMULATED_SET = "simulated"
#: fixed-pattern noise of a calibration that has none: the stand-in camera's (configs/sensor/cam75.yaml)
DEFAULT_FIXED_PATTERN = {"pixel_offset_e": 6.0, "column_phase_rad": 0.016, "prnu": 0.01, "seed": 75}


@dataclass(frozen=True)
class SimulatedTestSettings:
    """``data.simulated_test_kwargs``: mixed_pixels (samples per pixel side, 1 = one surface per pixel),
    fixed_pattern (a ``FixedPatternNoise`` mapping used when the calibration has none; ``{}`` or all-zero: none)."""

    mixed_pixels: int = 3
    fixed_pattern: dict[str, Any] = field(default_factory=lambda: dict(DEFAULT_FIXED_PATTERN))

    def __post_init__(self) -> None:
        s = self.mixed_pixels
        if isinstance(s, bool) or int(s) != s or s < 1:
            raise ValueError(f"data.simulated_test_kwargs.mixed_pixels must be an integer >= 1, got {s!r}")
        object.__setattr__(self, "mixed_pixels", int(s))
        pattern = dict(self.fixed_pattern or {})
        if pattern:
            try:
                FixedPatternNoise(**pattern)
            except TypeError as exc:
                raise ValueError(f"data.simulated_test_kwargs.fixed_pattern: {exc}") from None
            except ValueError as exc:
                raise ValueError(f"data.simulated_test_kwargs.{exc}") from None
        object.__setattr__(self, "fixed_pattern", pattern)

    @classmethod
    def from_kwargs(cls, kwargs: dict[str, Any] | None) -> SimulatedTestSettings:
        kwargs = dict(kwargs or {})
        unknown = sorted(set(kwargs) - {"mixed_pixels", "fixed_pattern"})
        if unknown:
            raise ValueError(
                f"data.simulated_test_kwargs: unknown key(s) {unknown}; valid: mixed_pixels, fixed_pattern"
            )
        return cls(**kwargs)

    def camera(self, calib: Any) -> Any:
        """The calibration the captures are simulated with: ``calib`` with its own fixed pattern, or this one's."""
        if getattr(calib, "fixed_pattern", None) is not None or not self.fixed_pattern:
            return calib
        return replace(calib, fixed_pattern=FixedPatternNoise(**self.fixed_pattern))

    def key(self, maps_digest: str, seed: int, calib: Any) -> dict[str, Any]:
        """What the cached captures depend on: the maps, the seed, these settings and the simulated camera."""
        return {
            "simulated_test": asdict(self),
            "maps": maps_digest,
            "seed": int(seed),
            "camera": self.camera(calib).fingerprint(),
            "version": 1,
        }


def unwrap_to_reference_mm(depth_mm: torch.Tensor, reference_mm: torch.Tensor, period_mm: float) -> torch.Tensor:
    """``depth_mm`` shifted by the whole number of unambiguous ranges that puts it nearest ``reference_mm``: the
    decoded phase's integer ambiguity resolved with the target's cycle, the estimate's own error kept (while it is
    below half the range)."""
    cycles = torch.round((reference_mm.double() - depth_mm.double()) / period_mm)
    return (depth_mm.double() + cycles * period_mm).to(depth_mm.dtype)


def _fine_signal(source: Any, sample_id: str, factor: int, calib: Any, route: str, percentiles: tuple) -> tuple:
    """(depth, signal) of ``sample_id`` rendered ``factor`` times finer (procedural scenes), or None."""
    if factor == 1 or not isinstance(source, ProceduralSource):
        return None
    raw = source.supersampled(factor).load(sample_id)
    valid = raw.valid & np.isfinite(raw.depth_mm) & (raw.depth_mm > 0)
    cos_field = field_cosine(*raw.depth_mm.shape, source.hfov_deg) if route == "physical" else None
    signal = signal_from_amplitude_e(raw.amplitude, valid, calib, route, cos_field, *percentiles)
    return np.where(valid, raw.depth_mm, 0.0).astype(np.float32), signal


def simulate_test_capture(
    maps: SampleMaps,
    calib: Any,
    generator: torch.Generator,
    fine: tuple[np.ndarray, np.ndarray] | None = None,
    factor: int = 1,
) -> SampleMaps:
    """One standard-exposure capture of a test sample (module docstring): ``depth_mm`` the captured depth (0 where
    invalid), ``amplitude`` the measured amplitude [e-], ``mask`` the sample's mask and the camera's validity,
    ``signal_e`` / ``sigma_mm`` the sample's maps. ``fine``: (depth, signal) rendered ``factor`` times finer for
    mixed pixels (None: one surface per pixel)."""
    depth = np.where(maps.mask, maps.depth_mm, 0.0).astype(np.float32)
    signal = np.where(maps.mask, maps.signal_e, 0.0).astype(np.float32)
    if fine is not None and factor > 1:
        frames = simulate_tap_mean_frames(
            footprint_tap_means_e(fine[0], fine[1], calib, factor), calib, 1, generator=generator
        )
    else:
        frames = simulate_frames(depth, signal, calib, 1, generator=generator)
    captured = unwrap_to_reference_mm(frames.depth_mm[0], torch.from_numpy(depth), calib.unambiguous_range_mm)
    mask = maps.mask & frames.valid[0].numpy()
    zero = np.zeros_like(depth)
    return SampleMaps(
        depth_mm=np.where(mask, captured.numpy(), zero).astype(np.float32),
        signal_e=np.where(mask, maps.signal_e, zero).astype(np.float32),
        sigma_mm=np.where(mask, maps.sigma_mm, zero).astype(np.float32),
        mask=mask,
        amplitude=np.where(mask, frames.amplitude[0].numpy(), zero).astype(np.float32),
    )


def simulated_cache(
    base: Path, settings: SimulatedTestSettings, maps_digest: str, seed: int, calib: Any, enabled: bool
) -> MapCache:
    """The cache of the simulated captures (a folder of its own next to the maps)."""
    return MapCache(Path(base) / "simulated-test", settings.key(maps_digest, seed, calib), enabled=enabled)


def _as_tensor(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))[None]


class SimulatedCaptures(Dataset):
    """The simulator-noised test split: batch items as ``SyntheticPairs``' (``noisy``, ``clean``, ``sigma``,
    ``mask``, ``amplitude``, ``index``, ``name``), the input a simulated capture (module docstring), read from
    ``cache`` (computed and stored on a miss, in whichever process reads it first)."""

    def __init__(
        self,
        provider: Any,
        sample_ids: list[str],
        cache: MapCache,
        settings: SimulatedTestSettings,
        seed: int,
        percentiles: tuple = (None, None),
    ):
        self.provider, self.sample_ids, self.cache = provider, list(sample_ids), cache
        self.settings, self.seed, self.percentiles = settings, int(seed), tuple(percentiles)

    def __len__(self) -> int:
        return len(self.sample_ids)

    def generator(self, sample_id: str) -> torch.Generator:
        return torch.Generator().manual_seed(stable_seed(self.seed, "test_simulated", sample_id))

    def capture(self, sample_id: str) -> SampleMaps:
        """The simulated capture of one test sample with the settings' camera and mixed pixels."""

        def compute() -> SampleMaps:
            maps = self.provider.maps(sample_id)
            camera = self.settings.camera(self.provider.calib)
            factor = self.settings.mixed_pixels
            route = self.provider.signal_route
            fine = _fine_signal(self.provider.source, sample_id, factor, camera, route, self.percentiles)
            return simulate_test_capture(maps, camera, self.generator(sample_id), fine, factor if fine else 1)

        # stamped with the sample's files (a file-backed source): a changed file recomputes the capture too
        return self.cache.get_or_compute(sample_id, compute, self.provider.files(sample_id))[0]

    def __getitem__(self, index: int) -> dict[str, Any]:
        sample_id = self.sample_ids[index]
        maps, captured = self.provider.maps(sample_id), self.capture(sample_id)
        item = {
            "noisy": _as_tensor(captured.depth_mm),
            "clean": _as_tensor(np.where(captured.mask, maps.depth_mm, 0.0)),
            "sigma": _as_tensor(captured.sigma_mm),
            "mask": _as_tensor(captured.mask),
            "amplitude": _as_tensor(captured.amplitude),
        }
        return {**item, "index": index, "name": sample_id}
