"""The simulator-noised test split: its error against the WLS sigma_D on a flat scene, its conventions (units,
validity, phase wrap), its cache and its place among the test sets."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tofdenoise.data_modules import ToFDataModule
from tofdenoise.data_modules.cache import SampleMaps
from tofdenoise.data_modules.simulated_test import (
    SimulatedTestSettings,
    simulate_test_capture,
    unwrap_to_reference_mm,
)
from tofdenoise.physics.calibration import default_calibration
from tofdenoise.physics.uncertainty import sigma_depth_mm


def _flat(depth_mm: float, signal_e: float, shape=(200, 400)) -> SampleMaps:
    calib = default_calibration()
    depth = np.full(shape, depth_mm, dtype=np.float32)
    signal = np.full(shape, signal_e, dtype=np.float32)
    sigma = np.asarray(sigma_depth_mm(depth, signal, calib), dtype=np.float32)
    mask = np.ones(shape, dtype=bool)
    return SampleMaps(depth, signal, sigma, mask, np.ones(shape, dtype=np.float32))


def _error(maps: SampleMaps, calib, seed: int = 0) -> tuple[np.ndarray, SampleMaps]:
    captured = simulate_test_capture(maps, calib, torch.Generator().manual_seed(seed))
    assert captured.mask.mean() > 0.999  # a bright flat wall: every pixel valid
    return (captured.depth_mm - maps.depth_mm)[captured.mask].astype(np.float64), captured


@pytest.mark.parametrize("depth_mm, signal_e", [(800.0, 20000.0), (1500.0, 4000.0)])
def test_flat_scene_error_matches_the_wls_sigma_within_the_demodulation_gap(depth_mm, signal_e):
    """Without fixed-pattern noise, the simulated capture's per-pixel error std equals the WLS sigma_D up to the
    camera's demodulation: atan2 of the first DFT bin is not the weighted fit the WLS bound describes. At the default
    contrast 0.5 its excess is at most 7 % (shared notes, Monte Carlo), ADC quantisation adds well under 1 %. With
    80 000 pixels the std is estimated to 0.25 %: the ratio must lie in [1.00, 1.09]."""
    calib = default_calibration()
    assert calib.fixed_pattern is None
    maps = _flat(depth_mm, signal_e)
    err, _ = _error(maps, calib)
    sigma = float(maps.sigma_mm[0, 0])
    ratio = err.std() / sigma
    assert 1.0 <= ratio <= 1.09, ratio
    assert abs(err.mean()) < 4 * err.std() / math.sqrt(err.size) + 0.05 * sigma  # unbiased (decoder, calibrated c)


def test_fixed_pattern_adds_the_column_phase_in_quadrature():
    """With the stand-in camera's fixed pattern (0.016 rad column phase = 7.6 mm at 50 MHz), the error variance is
    the shot/read part plus the column offsets' variance: the std grows from ~sigma_D to sqrt(sigma^2 + 7.6^2).
    400 columns estimate the column std to 3.5 %: the prediction must hold within 8 %."""
    settings = SimulatedTestSettings(mixed_pixels=1)
    calib = settings.camera(default_calibration())
    assert calib.fixed_pattern is not None and calib.fixed_pattern.column_phase_rad == 0.016
    maps = _flat(1000.0, 20000.0)
    err_plain, _ = _error(maps, default_calibration())
    err, captured = _error(maps, calib)
    column_mm = 0.016 / calib.phase_per_mm
    assert column_mm == pytest.approx(7.64, abs=0.01)
    predicted = math.sqrt(err_plain.var() + column_mm**2)
    assert err.std() == pytest.approx(predicted, rel=0.08)
    # the excess is column-structured: column means scatter by ~column_mm, far beyond their shot-noise error
    cols = (captured.depth_mm - maps.depth_mm).mean(axis=0)
    assert cols.std() == pytest.approx(column_mm, rel=0.12)


def test_phase_wrap_is_resolved_with_the_targets_cycle():
    calib = default_calibration()
    period = calib.unambiguous_range_mm
    reference = torch.tensor([100.0, 2990.0, 3100.0, 5.0])
    # captures of these targets as the camera decodes them, in [0, period): the last three wrapped
    decoded = torch.tensor([103.0, 2.0, 98.0, period - 4.0])
    out = unwrap_to_reference_mm(decoded, reference, period)
    torch.testing.assert_close(out, torch.tensor([103.0, period + 2.0, period + 98.0, -4.0]), atol=1e-3, rtol=0)
    # a scene beyond the unambiguous range scores the capture's error, not a range-sized jump
    maps = _flat(period + 300.0, 30000.0, shape=(64, 64))
    err, _ = _error(maps, calib)
    assert np.abs(err).max() < 10 * float(maps.sigma_mm[0, 0])


def test_dark_pixels_are_invalid_as_the_camera_decides():
    calib = default_calibration()
    maps = _flat(1000.0, 20000.0, shape=(32, 64))
    maps.signal_e[:, :32] = 5.0  # far below the validity threshold: the camera drops them
    captured = simulate_test_capture(maps, calib, torch.Generator().manual_seed(1))
    assert not captured.mask[:, :32].any() and captured.mask[:, 32:].mean() > 0.99
    assert np.all(captured.depth_mm[~captured.mask] == 0) and np.all(captured.amplitude[~captured.mask] == 0)


def test_split_is_cached_fixed_and_independent_of_the_training_noise(tmp_path, monkeypatch):
    kw = dict(source_kwargs=dict(num_samples=10, height=48, width=64), crop_size=16, batch_size=2)
    dm = ToFDataModule(cache_dir=str(tmp_path / "cache"), noise="hetero", **kw)
    dm.prepare_data()
    dm.setup("test")
    sim = dm.test_dataloader()[1]
    first = [b["noisy"].clone() for b in sim]
    stored = sorted(dm.prepared.simulated_cache.folder.glob("*.npz"))
    assert len(stored) == len(dm.splits["test"])
    # a new instance with another training noise reads the stored captures (no simulation) and gets the same inputs
    import tofdenoise.data_modules.simulated_test as st

    monkeypatch.setattr(st, "simulate_test_capture", lambda *a, **k: pytest.fail("simulated again"))
    other = ToFDataModule(cache_dir=str(tmp_path / "cache"), noise="fixed", **kw)
    other.prepare_data()
    other.setup("test")
    again = [b["noisy"] for b in other.test_dataloader()[1]]
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    # mixed pixels: flying pixels at depth edges make the tail the hetero split does not have
    batch = next(iter(sim))
    valid = batch["mask"] > 0
    z = ((batch["noisy"] - batch["clean"]) / batch["sigma"])[valid]
    assert float(z.abs().max()) > 8
    assert dm.summary()["simulated_test"]["mixed_pixels"] == 3


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="data.simulated_test_kwargs: unknown key"):
        SimulatedTestSettings.from_kwargs({"mixed": 2})
    with pytest.raises(ValueError, match="mixed_pixels"):
        SimulatedTestSettings.from_kwargs({"mixed_pixels": 0})
    with pytest.raises(ValueError, match="fixed_pattern"):
        SimulatedTestSettings.from_kwargs({"fixed_pattern": {"prnu": -1}})
