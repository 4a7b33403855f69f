"""Fixed-pattern noise of the capture simulator: statistics of each term, fixed across frames, absent from the
WLS model; the stand-in camera (cam75) carries it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tofdenoise.physics.calibration import CalibrationError, FixedPatternNoise, resolve_calibration
from tofdenoise.physics.fixed_pattern import camera_pattern, fixed_pattern_maps
from tofdenoise.physics.mixed_pixels import footprint_tap_means_e
from tofdenoise.physics.simulator import simulate_dark_taps, simulate_frames, simulate_tap_mean_frames
from tofdenoise.physics.uncertainty import sigma_depth_mm

BASE = resolve_calibration("default").replace(adc_gain_e_per_dn=None)


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def with_pattern(**kw) -> object:
    return BASE.replace(fixed_pattern={"seed": 5, **kw})


def test_pattern_maps_are_seeded_and_have_the_stated_statistics():
    fpn = FixedPatternNoise(pixel_offset_e=6.0, column_phase_rad=0.02, prnu=0.01, seed=3)
    a = fixed_pattern_maps(fpn, 200, 300, 4)
    b = fixed_pattern_maps(fpn, 200, 300, 4)
    np.testing.assert_array_equal(a.tap_offset_e, b.tap_offset_e)
    np.testing.assert_array_equal(a.column_phase_rad, b.column_phase_rad)
    assert a.tap_offset_e.shape == (4, 200, 300) and a.column_phase_rad.shape == (300,) and a.gain.shape == (200, 300)
    assert a.tap_offset_e.std() == pytest.approx(6.0, rel=0.02)
    assert a.column_phase_rad.std() == pytest.approx(0.02, rel=0.15)  # 300 columns: ~4 % sampling error
    assert a.gain.mean() == pytest.approx(1.0, abs=1e-3) and a.gain.std() == pytest.approx(0.01, rel=0.02)
    other = fixed_pattern_maps(FixedPatternNoise(6.0, 0.02, 0.01, seed=4), 200, 300, 4)
    assert not np.allclose(other.tap_offset_e, a.tap_offset_e)
    assert camera_pattern(BASE, 8, 8) is None
    assert camera_pattern(BASE.replace(fixed_pattern={"seed": 1}), 8, 8) is None  # all-zero pattern: none


def test_bad_fixed_pattern_fields_are_named():
    with pytest.raises(CalibrationError, match="fixed_pattern.prnu"):
        BASE.replace(fixed_pattern={"prnu": -0.1})
    with pytest.raises(CalibrationError, match="fixed_pattern.colum"):
        BASE.replace(fixed_pattern={"colum_phase": 0.1})
    with pytest.raises(CalibrationError, match="fixed_pattern.seed"):
        BASE.replace(fixed_pattern={"seed": 1.5})


def mean_depth_error_mm(calib, shape, depth_mm, signal_e, frames, seed, axis) -> np.ndarray:
    """Mean decoded depth minus the truth of a flat scene, averaged over ``axis`` (frames, and rows for columns)."""
    depth = np.full(shape, depth_mm, np.float32)
    fr = simulate_frames(
        depth, np.full(shape, signal_e, np.float32), calib, frames, generator=gen(seed), quantize=False
    )
    return (fr.depth_mm.double().mean(dim=axis) - depth_mm).numpy()


def test_column_phase_is_a_per_column_depth_offset_that_does_not_change_with_signal():
    calib = with_pattern(column_phase_rad=0.02)
    shape = (40, 64)
    offsets = {s: mean_depth_error_mm(calib, shape, 1200.0, s, 60, 1, (0, 1)) for s in (3000.0, 30000.0)}
    expected = camera_pattern(calib, *shape).column_phase_rad / calib.phase_per_mm
    for signal, off in offsets.items():
        # temporal + row average of 60 x 40 samples; sigma_D(3000 e-) ~ 11 mm -> ~0.25 mm per column estimate
        np.testing.assert_allclose(off, expected, atol=1.2 if signal == 3000.0 else 0.3)
    assert np.corrcoef(offsets[3000.0], offsets[30000.0])[0, 1] > 0.9
    assert expected.std() > 3.0  # 0.02 rad at 50 MHz: 9.5 mm per rad -> ~9.5 mm std; the test sees it


def test_tap_offsets_bias_depth_as_one_over_signal_and_are_fixed_across_frames():
    calib = with_pattern(pixel_offset_e=20.0)
    bias = {s: mean_depth_error_mm(calib, (32, 32), 900.0, s, 200, 2, 0) for s in (1000.0, 4000.0)}
    # the same pattern in every frame: the per-pixel bias is the same map at both signals, 4 x smaller at 4 x signal
    slope = float((bias[1000.0] * bias[4000.0]).sum() / (bias[4000.0] ** 2).sum())
    assert slope == pytest.approx(4.0, rel=0.15)
    # temporal noise alone would leave a per-pixel mean error of sigma_D / sqrt(200); the fixed bias is far larger
    noise_only = float(sigma_depth_mm(900.0, 1000.0, calib)) / np.sqrt(200)
    assert bias[1000.0].std() > 3 * noise_only


def test_dark_frames_carry_the_tap_offsets_and_prnu_scales_amplitude_only():
    calib = with_pattern(pixel_offset_e=8.0, prnu=0.05)
    dark = simulate_dark_taps((24, 24), calib, 100, generator=gen(3), quantize=False)
    per_pixel = dark.double().mean(dim=0) - calib.dark_mean_e  # (N, H, W): the offsets
    expected = torch.from_numpy(camera_pattern(calib, 24, 24).tap_offset_e).double()
    assert float((per_pixel - expected).abs().max()) < 5 * calib.dark_std_e / 10  # 100 frames: std/10
    shape = (24, 24)
    fr = simulate_frames(
        np.full(shape, 700.0, np.float32), np.full(shape, 20000.0, np.float32), calib, 50, generator=gen(4)
    )
    ratio = fr.amplitude.double().mean(dim=0) / fr.amplitude.double().mean()
    gain = camera_pattern(calib, *shape).gain
    assert np.corrcoef(ratio.numpy().ravel(), gain.ravel())[0, 1] > 0.9


def test_mixed_pixel_path_gets_the_same_pattern():
    calib = with_pattern(pixel_offset_e=10.0, column_phase_rad=0.02, prnu=0.02)
    shape = (12, 16)
    depth = np.full(shape, 1000.0, np.float32)
    signal = np.full(shape, 8000.0, np.float32)
    means = footprint_tap_means_e(
        np.repeat(np.repeat(depth, 2, 0), 2, 1), np.repeat(np.repeat(signal, 2, 0), 2, 1), calib, 2
    )
    a = simulate_tap_mean_frames(means, calib, 3, generator=gen(5), quantize=False, return_taps=True)
    b = simulate_frames(depth, signal, calib, 3, generator=gen(5), quantize=False, return_taps=True)
    torch.testing.assert_close(a.taps, b.taps, rtol=0, atol=0.05)


def test_stand_in_camera_has_a_fixed_pattern_and_the_wls_model_ignores_it():
    cam = resolve_calibration("cam75")
    assert cam.fixed_pattern is not None and cam.fixed_pattern.column_phase_rad == pytest.approx(0.016)
    assert cam.fixed_pattern.pixel_offset_e > 0 and cam.fixed_pattern.prnu > 0
    plain = cam.replace(fixed_pattern=None)
    d, a = np.array([800.0, 1500.0]), np.array([2000.0, 30000.0])
    np.testing.assert_array_equal(sigma_depth_mm(d, a, cam), sigma_depth_mm(d, a, plain))
