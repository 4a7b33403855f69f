"""Calibration from captures: round trip on simulated stacks, fits, and capture-format errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tofdenoise.physics.calibrate import (
    calibrate_from_folders,
    estimate_dark,
    fit_range_sigma,
    fit_tap_response,
    signal_interval,
)
from tofdenoise.physics.calibration import TapResponse, default_calibration
from tofdenoise.physics.capture_io import CaptureFormatError, load_stack, read_index, write_capture_folder
from tofdenoise.physics.synthetic_captures import write_dark_folder, write_distances_folder, write_sweep_folder
from tofdenoise.physics.uncertainty import sigma_depth_mm


def test_fit_tap_response_exact_on_noise_free_samples():
    true = TapResponse(1.0, (0.4, 0.03, 0.02), (0.25, -0.01, 0.005))
    psi = np.linspace(0, 2 * np.pi, 17, endpoint=False)
    theta = 2 * np.pi * np.arange(4) / 4
    signal = np.linspace(1000, 9000, 17)[:, None]  # per-step signal changes (e.g. target distance)
    taps = signal * true.value(psi[:, None] - theta[None, :]) + 300.0
    got = fit_tap_response(psi, taps, dark_mean_e=300.0, num_harmonics=3)
    assert got.c0 == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(got.cos, true.cos, atol=1e-12)
    np.testing.assert_allclose(got.sin, true.sin, atol=1e-12)
    with pytest.raises(ValueError, match="distinct sample phases"):
        fit_tap_response(psi[:1], taps[:1], 300.0, num_harmonics=3)


def test_fit_range_sigma_recovers_polynomial():
    d = np.arange(500.0, 1501.0, 100.0)
    s = 2.0 - 0.001 * d + 4e-6 * d**2
    np.testing.assert_allclose(fit_range_sigma(d, s), (2.0, -0.001, 4e-6), rtol=1e-8, atol=1e-12)
    with pytest.raises(ValueError, match="3 distinct"):
        fit_range_sigma([1.0, 2.0], [1.0, 2.0])


def test_dark_and_signal_interval_estimators():
    rng = np.random.default_rng(0)
    stack = 500.0 + 30.0 * rng.standard_normal((100, 4, 10, 10))
    m, s = estimate_dark([stack])
    assert m == pytest.approx(500.0, abs=0.5) and s == pytest.approx(30.0, rel=0.02)
    lo, hi = signal_interval(np.concatenate([np.linspace(0, 1000, 1001), [np.nan, -5.0]]), 1.0, 99.0)
    assert lo == pytest.approx(10.99, rel=1e-3) and hi == pytest.approx(990.01, rel=1e-3)


def test_round_trip_calibration(tmp_path):
    """Captures simulated with a known calibration are calibrated back within tolerance."""
    true = default_calibration().replace(
        tap_response=TapResponse(1.0, (0.45, 0.02, 0.015), (0.2, 0.0, -0.01)), dark_mean_e=1500.0, dark_std_e=40.0
    )
    sweep = write_sweep_folder(true, tmp_path / "sweep", num_steps=24, num_frames=20)
    dark = write_dark_folder(true, tmp_path / "dark", num_frames=100)
    distances = np.arange(550.0, 1500.0, 100.0)
    dist = write_distances_folder(true, tmp_path / "dist", distances, num_frames=100, signal_spread=(0.3, 1.0))
    rep = calibrate_from_folders(sweep, dark, dist)
    got = rep.calibration
    assert got.num_taps == 4 and got.modulation_frequency_hz == true.modulation_frequency_hz
    assert got.tap_response.c0 == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(got.tap_response.cos, true.tap_response.cos, atol=2e-3)
    np.testing.assert_allclose(got.tap_response.sin, true.tap_response.sin, atol=2e-3)
    assert got.dark_mean_e == pytest.approx(1500.0, abs=2.0)
    assert got.dark_std_e == pytest.approx(40.0, rel=0.02)
    assert got.full_well_e == true.full_well_e and got.adc_gain_e_per_dn == true.adc_gain_e_per_dn
    # signal interval: percentiles of the per-pixel returned signal of the captured tap stacks
    from tofdenoise.physics.synthetic_captures import planar_signal_e

    ramp = np.linspace(0.3, 1.0, 8)[None, :] * np.ones((8, 8))
    true_signals = np.concatenate(
        [np.full(24 * 64, 20000.0)] + [(planar_signal_e(d, 0.9) * ramp).ravel() for d in distances]
    )
    lo, hi = np.percentile(true_signals, [1.0, 99.0])
    assert got.signal_min_e == pytest.approx(lo, rel=0.03)
    assert got.signal_max_e == pytest.approx(hi, rel=0.03)
    assert rep.dark_frames == 100 and rep.sweep_points == 24 and len(rep.range_points) == len(distances)
    # the range-aware fit reproduces the measured std of the sequence
    pred = np.polyval(got.range_sigma_mm[::-1], distances)
    meas = np.array([s for _, s in rep.range_points])
    assert np.mean(np.abs(pred - meas) / meas) < 0.08
    # the recovered calibration predicts the same sigma_D as the true one
    d, a = np.array([600.0, 1000.0, 1400.0]), np.array([30000.0, 10000.0, 3000.0])
    np.testing.assert_allclose(sigma_depth_mm(d, a, got), sigma_depth_mm(d, a, true), rtol=0.02)


def _good_index(tmp_path, **over):
    arr = np.zeros((3, 4, 2, 2), np.float32)
    fields = dict(modulation_frequency_hz=5e7)
    fields.update(over)
    return write_capture_folder(tmp_path / "sw", "sweep", 4, [("s0", arr, {"phase_rad": 0.0})], **fields)


def test_capture_format_errors_name_file_and_shape(tmp_path):
    folder = _good_index(tmp_path)
    idx = read_index(folder, "sweep")
    assert idx.num_taps == 4 and idx.units == "e"
    with pytest.raises(CaptureFormatError, match="expected a 'dark'"):
        read_index(folder, "dark")
    # wrong tap count in a stack
    np.save(folder / "s0.npy", np.zeros((3, 3, 2, 2), np.float32))
    dark = write_dark_folder(default_calibration(), tmp_path / "dark", num_frames=5, shape=(2, 2))
    with pytest.raises(CaptureFormatError, match=r"s0\.npy.*\(frames, 4, H, W\)"):
        calibrate_from_folders(folder, dark)
    np.save(folder / "s0.npy", np.zeros((3, 4, 2), np.float32))
    with pytest.raises(CaptureFormatError, match=r"s0\.npy: shape \(3, 4, 2\)"):
        calibrate_from_folders(folder, dark)
    np.save(folder / "s0.npy", np.zeros((3, 4, 2, 2), np.complex64))
    with pytest.raises(CaptureFormatError, match="dtype complex64"):
        calibrate_from_folders(folder, dark)
    (folder / "s0.npy").unlink()
    with pytest.raises(FileNotFoundError, match="s0.npy"):
        calibrate_from_folders(folder, dark)
    with pytest.raises(FileNotFoundError, match="index.json"):
        read_index(tmp_path)


@pytest.mark.parametrize(
    "patch,needle",
    [
        ({"units": "dn"}, "adc_gain_e_per_dn"),
        ({"modulation_frequency_hz": None}, "modulation_frequency_hz"),
        ({"num_taps": 2}, "num_taps"),
        ({"kind": "foo"}, "kind"),
        ({"roi": [0, 1, 2]}, "roi"),
        ({"stacks": []}, "stacks"),
        ({"stacks": [{"file": "s0.npy"}]}, "phase_rad"),
    ],
)
def test_index_errors(tmp_path, patch, needle):
    folder = _good_index(tmp_path)
    index = json.loads((folder / "index.json").read_text())
    for k, v in patch.items():
        if v is None:
            index.pop(k)
        else:
            index[k] = v
    (folder / "index.json").write_text(json.dumps(index))
    with pytest.raises(CaptureFormatError, match=needle):
        read_index(folder)


def test_fit_tap_response_with_missing_taps_is_exact_on_noise_free_samples():
    true = TapResponse(1.0, (0.5, 0.03, 0.01), (0.1, 0.0, -0.02))
    psi = 2 * np.pi * (np.arange(12) + 0.3) / 12
    theta = 2 * np.pi * np.arange(4) / 4
    a_s = np.linspace(8000.0, 30000.0, 12)[:, None]  # the signal changes from step to step
    taps = 100.0 + a_s * true.value(psi[:, None] - theta[None, :])
    taps[::2, 1] = np.nan  # a tap above the full well at every other step
    taps[3, 2] = np.nan
    got = fit_tap_response(psi, taps, dark_mean_e=100.0, num_harmonics=3)
    assert got.c0 == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(got.cos, true.cos, atol=1e-9)
    np.testing.assert_allclose(got.sin, true.sin, atol=1e-9)


def test_partly_clipped_sweep_is_calibrated_from_its_unclipped_samples(tmp_path):
    """A quarter of the tap samples at the full well (the brightest tap of most steps): left out and counted,
    the fit still gives cos1 = 0.5 (with them it gave ~0.46; the issue saw 0.378)."""
    cal = default_calibration()  # cos = (0.5, 0, 0.01), full well 100000 e-, dark 2000 e-
    # peak tap a (1 + 0.5 cos x) + dark reaches the full well for cos x >= 0.707: 25 % of the phases
    sweep = write_sweep_folder(cal, tmp_path / "sweep", num_steps=24, num_frames=10, signal_e=72400.0)
    dark = write_dark_folder(cal, tmp_path / "dark", num_frames=20)
    rep = calibrate_from_folders(sweep, dark)
    assert rep.tap_samples == 24 * 10 * 4 * 64
    assert rep.clipped_samples / rep.tap_samples == pytest.approx(0.25, abs=0.02)
    assert len(rep.clipped_by_file) >= 20 and "25.00 %" in rep.clipping_summary()
    tr = rep.calibration.tap_response
    assert tr.cos[0] == pytest.approx(0.5, abs=0.003) and tr.contrast == pytest.approx(0.5, abs=0.003)
    np.testing.assert_allclose(tr.cos[1:], cal.tap_response.cos[1:], atol=0.003)
    # the returned signal of every pixel is recovered too (not the clipped remainder)
    assert rep.calibration.signal_min_e == pytest.approx(72400.0, rel=0.01)
    assert rep.calibration.signal_max_e == pytest.approx(72400.0, rel=0.01)


def test_sweep_or_distance_step_at_the_full_well_is_an_error_naming_the_file(tmp_path):
    cal = default_calibration()
    dark = write_dark_folder(cal, tmp_path / "dark", num_frames=20)
    sweep = write_sweep_folder(cal, tmp_path / "sat", num_steps=12, num_frames=5, signal_e=200000.0)
    with pytest.raises(CaptureFormatError, match=r"sat/step_000\.npy: 100\.0 % of the tap samples are clipped"):
        calibrate_from_folders(sweep, dark)
    good = write_sweep_folder(cal, tmp_path / "sweep", num_steps=12, num_frames=5)
    dist = write_distances_folder(cal, tmp_path / "dist", [300.0, 800.0, 1200.0], num_frames=5, reflectance=20.0)
    with pytest.raises(CaptureFormatError, match=r"dist/dist_000\.npy: only 0\.0 % of the pixels are unclipped"):
        calibrate_from_folders(good, dark, dist)


def test_clipped_samples_at_the_full_well_or_the_dtype_maximum(tmp_path):
    from tofdenoise.physics.capture_io import clipped_samples, write_capture_folder

    raw = np.array([0, 100, 65534, 65535], np.uint16).reshape(1, 4, 1, 1).repeat(2, axis=0)
    folder = write_capture_folder(
        tmp_path / "c",
        "sweep",
        4,
        [("s", raw, {"phase_rad": 0.0})],
        modulation_frequency_hz=5e7,
        units="dn",
        adc_gain_e_per_dn=2.0,
    )
    idx = read_index(folder, "sweep")
    values = load_stack(idx, "s.npy")
    assert clipped_samples(idx, "s.npy", values, None)[0, :, 0, 0].tolist() == [False, False, False, True]
    assert clipped_samples(idx, "s.npy", values, 200.0)[0, :, 0, 0].tolist() == [False, True, True, True]


def test_calibration_errors_name_the_folder_or_file(tmp_path):
    from tofdenoise.physics.capture_io import write_capture_folder

    cal = default_calibration()
    sweep = write_sweep_folder(cal, tmp_path / "sweep", num_steps=12, num_frames=5)
    dark = write_dark_folder(cal, tmp_path / "dark", num_frames=10)
    zero = write_capture_folder(
        tmp_path / "dark0",
        "dark",
        4,
        [("d", np.zeros((4, 4, 8, 8), np.uint16), {})],
        units="dn",
        adc_gain_e_per_dn=25.0,
    )
    with pytest.raises(CaptureFormatError, match=rf"{re.escape(str(zero))}: the dark frames have no temporal noise"):
        calibrate_from_folders(sweep, zero)
    int8 = write_capture_folder(
        tmp_path / "sweep8",
        "sweep",
        4,
        [(f"s{i}", np.full((3, 4, 8, 8), 100 + i, np.int8), {"phase_rad": 0.5 * i}) for i in range(12)],
        modulation_frequency_hz=5e7,
        full_well_e=1e5,
    )
    with pytest.raises(CaptureFormatError, match=r"sweep8/s0\.npy: no returned signal .*dtype int8"):
        calibrate_from_folders(int8, dark)


def test_photometric_gain_is_measured_from_a_target_of_known_reflectance(tmp_path):
    """K = a (D / 1 m)^2 / rho: a uniform board whose index names its reflectance gives the camera's gain back;
    a sequence without reflectances leaves it unset; a bad reflectance field is named."""
    true = default_calibration().replace(signal_at_1m_e=30000.0)
    sweep = write_sweep_folder(true, tmp_path / "sweep", num_steps=12, num_frames=4)
    dark = write_dark_folder(true, tmp_path / "dark", num_frames=20)
    dist = write_distances_folder(
        true, tmp_path / "dist", [800.0, 1200.0, 1500.0], num_frames=10, reflectance=0.5, signal_at_1m_e=30000.0
    )
    report = calibrate_from_folders(sweep, dark, dist)
    assert report.calibration.signal_at_1m_e == pytest.approx(30000.0, rel=0.01)
    ramp = write_distances_folder(
        true, tmp_path / "ramp", [800.0, 1200.0, 1500.0], num_frames=10, signal_spread=(0.3, 1.0)
    )
    assert calibrate_from_folders(sweep, dark, ramp).calibration.signal_at_1m_e is None
    index = json.loads((dist / "index.json").read_text())
    index["stacks"][0]["reflectance"] = "white"
    (dist / "index.json").write_text(json.dumps(index))
    with pytest.raises(CaptureFormatError, match="'reflectance' must be a number"):
        calibrate_from_folders(sweep, dark, dist)


def test_few_dark_frames_are_used_with_a_warning_and_mixed_sweep_sizes_are_refused(tmp_path):
    true = default_calibration()
    sweep = write_sweep_folder(true, tmp_path / "sweep", num_steps=12, num_frames=4)
    few = write_dark_folder(true, tmp_path / "dark10", num_frames=10)
    report = calibrate_from_folders(sweep, few)
    assert report.dark_frames == 10
    assert len(report.warnings) == 1 and "10 dark frames used" in report.warnings[0] and "100" in report.warnings[0]
    enough = write_dark_folder(true, tmp_path / "dark100", num_frames=100)
    assert calibrate_from_folders(sweep, enough).warnings == []
    # one sweep step of another size: refused, naming the file
    index = json.loads((sweep / "index.json").read_text())
    odd = index["stacks"][5]["file"]
    np.save(sweep / odd, np.load(sweep / odd)[:, :, :4, :])
    with pytest.raises(CaptureFormatError, match=re.escape(odd) + r".*frames of 4x8 px"):
        calibrate_from_folders(sweep, enough)


def test_circular_depth_stats_hand_case():
    """U = 1000 mm; a pixel at the wrap reports 990, 995, 5, 10 mm: unwrapped 990, 995, 1005, 1010 around the
    circular mean, so mean 1000 mm = 0 (mod U) and std sqrt((100 + 25 + 25 + 100) / 3) = 9.129 mm. The linear std
    of the wrapped values (the old measurement) is 567.6 mm."""
    from tofdenoise.physics.calibrate import circular_depth_stats_mm

    d = np.array([990.0, 995.0, 5.0, 10.0])[:, None]
    mean, std = circular_depth_stats_mm(d, 1000.0)
    assert std[0] == pytest.approx(np.sqrt(250.0 / 3.0), rel=1e-12)
    assert min(mean[0], 1000.0 - mean[0]) == pytest.approx(0.0, abs=1e-9)
    lin_mean, lin_std = circular_depth_stats_mm(d, None)
    assert lin_std[0] == pytest.approx(np.std(d, ddof=1), rel=1e-12) and lin_std[0] > 500.0
    # away from the wrap the circular statistics are the ordinary ones
    far = np.array([[400.0, 410.0], [420.0, 390.0], [380.0, 400.0]])
    m, s = circular_depth_stats_mm(far, 1000.0)
    np.testing.assert_allclose(m, far.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(s, far.std(axis=0, ddof=1), rtol=1e-12)
    with pytest.raises(ValueError, match="unambiguous_range_mm"):
        circular_depth_stats_mm(d, 0.0)


def test_temporal_std_is_the_unwrapped_std_near_the_unambiguous_range():
    """Monte Carlo: Gaussian depth noise of 30 mm at 1900 mm and 16 mm at 1960 mm of a U = 1998.6 mm camera (cam75),
    wrapped mod U as the camera reports it. The circular std equals the std of the unwrapped samples (to 1e-9); the
    linear std of the wrapped samples is far too large."""
    from tofdenoise.physics.calibrate import temporal_std_roi_mm

    u = 1998.6163866666666
    rng = np.random.default_rng(5)
    for truth, noise, ratio in ((1900.0, 30.0, 1.3), (1960.0, 16.0, 5.0)):
        unwrapped = truth + noise * rng.standard_normal((2000, 4, 4))
        wrapped = np.mod(unwrapped, u)
        assert (wrapped != unwrapped).any()
        got, n = temporal_std_roi_mm(wrapped, unambiguous_range_mm=u)
        want = float(unwrapped.std(axis=0, ddof=1).mean())
        assert n == 16 and got == pytest.approx(want, rel=1e-9)
        old, _ = temporal_std_roi_mm(wrapped, unambiguous_range_mm=None)
        assert old > ratio * want


def test_calibrate_measures_the_circular_std_of_a_distance_near_the_unambiguous_range(tmp_path):
    """cam75 (U = 1998.6 mm), a 10 % target at 300, 600, 1000 and 1960 mm: at 1960 mm some frames wrap to a few mm.
    The range point is the std of the demodulated frames unwrapped around the truth (17.4 mm); the linear std of
    the wrapped frames (what calibrate used) is several times larger."""
    import torch

    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.simulator import default_min_amplitude_e, demodulate

    cam = resolve_calibration("cam75")
    u = cam.unambiguous_range_mm
    sweep = write_sweep_folder(cam, tmp_path / "sweep", num_steps=12, num_frames=4)
    dark = write_dark_folder(cam, tmp_path / "dark", num_frames=10)
    dists = [300.0, 600.0, 1000.0, 1960.0]
    folder = write_distances_folder(
        cam, tmp_path / "dist", dists, num_frames=60, reflectance=0.1, signal_at_1m_e=cam.signal_at_1m_e
    )
    rep = calibrate_from_folders(sweep, dark, folder)
    assert [d for d, _ in rep.range_points] == dists
    taps = np.load(folder / "dist_003.npy")
    depth, amp = demodulate(torch.from_numpy(taps), rep.calibration, tap_axis=1)
    depth = depth.numpy().astype(np.float64)
    ok = ((amp.numpy() >= default_min_amplitude_e(rep.calibration)) & (depth > 0)).all(axis=0)
    assert ok.sum() > 32
    assert (np.abs(depth[:, ok] - 1960.0) > u / 2).any()  # frames wrapped to near 0 mm
    unwrapped = np.mod(depth[:, ok] - 1960.0 + u / 2, u) - u / 2 + 1960.0
    want = float(unwrapped.std(axis=0, ddof=1).mean())
    assert rep.range_points[-1][1] == pytest.approx(want, rel=1e-6)
    assert 12.0 < want < 25.0
    assert float(depth[:, ok].std(axis=0, ddof=1).mean()) > 3 * want


def test_fit_range_sigma_refuses_non_finite_points():
    """A NaN std (a distance without valid pixels) made every coefficient NaN; now an error naming the point."""
    d = [550.0, 650.0, 750.0, 850.0]
    with pytest.raises(ValueError, match=r"point 0 is \(distance 550.0 mm, std nan mm\)"):
        fit_range_sigma(d, [np.nan, 2.0, 2.5, 3.0])
    with pytest.raises(ValueError, match="finite"):
        fit_range_sigma([550.0, np.inf, 750.0], [1.0, 2.0, 3.0])


def _cam3h():
    """The audit's 3-tap camera with a third harmonic: N = 3, 30 MHz, c(x) = 1 + 0.5 cos x + 0.08 cos 3x."""
    return default_calibration().replace(
        num_taps=3,
        modulation_frequency_hz=30e6,
        tap_response=TapResponse(1.0, (0.5, 0.0, 0.08), (0.0, 0.0, 0.0)),
        dark_mean_e=500.0,
        dark_std_e=20.0,
        signal_min_e=300.0,
        signal_max_e=30000.0,
        full_well_e=200000.0,
        adc_gain_e_per_dn=2.0,
        range_sigma_mm=None,
        signal_at_1m_e=None,
        vignetting_cos_power=None,
    )


def test_common_amplitude_fit_recovers_the_harmonic_at_a_multiple_of_n():
    """Noise-free taps a c(psi_s - theta_n), a = 20000 e- at every step, N = 3: with one common amplitude the fit is
    exact (c3 = 0.08); normalising each step by its tap mean divides cos 3x out (mean_n cos 3(psi - theta_n) =
    cos 3 psi) and leaves c3 = 0 and a spurious c2 = -0.08 x 0.5 / 2 = -0.020 (to first order), what calibrate gave."""
    from tofdenoise.physics.calibrate import tap_sum_ripple

    true = TapResponse(1.0, (0.5, 0.0, 0.08), (0.0, 0.0, 0.0))
    psi = 2 * np.pi * (np.arange(24) + 0.5) / 24
    theta = 2 * np.pi * np.arange(3) / 3
    taps = 500.0 + 20000.0 * np.asarray(true.value(psi[:, None] - theta[None, :]))
    got = fit_tap_response(psi, taps, 500.0, 3, common_amplitude=True)
    assert got.c0 == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(got.cos, true.cos, atol=1e-12)
    np.testing.assert_allclose(got.sin, true.sin, atol=1e-12)
    per_step = fit_tap_response(psi, taps, 500.0, 3)
    assert abs(per_step.cos[2]) < 1e-12
    assert per_step.cos[1] == pytest.approx(-0.020, abs=5e-4)
    # the per-step tap sums show the harmonic: sum_n c(psi - theta_n) = 3 (1 + 0.08 cos 3 psi)
    ripple = tap_sum_ripple(psi, taps, 500.0, 3)
    assert set(ripple.harmonics) == {3} and ripple.steps == 24
    np.testing.assert_allclose(ripple.harmonics[3], (0.08, 0.0), atol=1e-12)
    assert ripple.drift < 1e-12 and ripple.amplitude == pytest.approx(0.08)
    # missing taps (clipped): left out of the one linear fit, which stays exact
    taps[::3, 0] = np.nan
    got = fit_tap_response(psi, taps, 500.0, 3, common_amplitude=True)
    np.testing.assert_allclose(got.cos, true.cos, atol=1e-12)
    # N = 4 with K = 3: no multiple of N among the fitted harmonics, nothing to tell apart
    assert tap_sum_ripple(psi, np.ones((24, 4)) * 1000.0, 0.0, 3).harmonics == {}


def test_ripple_sigma_error_is_the_sigma_error_of_the_per_step_fit():
    """The sigma_D error that ``ripple_sigma_error`` names for a per-step fit of the N = 3 camera is the one the
    per-step fit makes against the true c(x): over a period at 2000 e- the per-step fit is -10.9 % / +13.3 % off
    (lowest / highest), the tap sums' estimate says -10.8 % / +13.5 %."""
    from tofdenoise.physics.calibrate import ripple_sigma_error, tap_sum_ripple

    cam = _cam3h()
    psi = 2 * np.pi * (np.arange(24) + 0.5) / 24
    theta = 2 * np.pi * np.arange(3) / 3
    taps = 500.0 + 20000.0 * np.asarray(cam.tap_response.value(psi[:, None] - theta[None, :]))
    fitted = cam.replace(tap_response=fit_tap_response(psi, taps, 500.0, 3))
    lo, hi = ripple_sigma_error(fitted, tap_sum_ripple(psi, taps, 500.0, 3), 2000.0)
    depth = np.linspace(0.0, cam.unambiguous_range_mm, 257)[1:]
    ratio = sigma_depth_mm(depth, np.full_like(depth, 2000.0), fitted) / sigma_depth_mm(
        depth, np.full_like(depth, 2000.0), cam
    )
    assert lo == pytest.approx(ratio.min() - 1, abs=0.005) and hi == pytest.approx(ratio.max() - 1, abs=0.005)
    assert lo < -0.09 and hi > 0.11


def test_calibrate_recovers_the_third_harmonic_of_a_3_tap_camera_against_monte_carlo(tmp_path):
    """Simulated captures of the N = 3 camera (c3 = 0.08): the phase_rad sweep is fitted with one common amplitude,
    c3 = 0.0800 (was 8e-17, with c2 = -0.020), and sigma_D at 800 / 1800 mm (a = 20000 e-) is -0.9 % / -2.2 % off
    the Monte Carlo std of the simulated camera (as the true calibration is: the linearisation), where the per-step
    fit is +11.6 % / -11.3 % off. Steps given by distance_mm (a moving target) are normalised per step, with a
    warning naming the sigma_D error it may carry (-11.5 % to +15.1 % at 20 ke-)."""
    import torch

    from tofdenoise.physics.simulator import simulate_frames

    cam = _cam3h()
    sweep = write_sweep_folder(cam, tmp_path / "sweep", num_steps=24, num_frames=20)
    dark = write_dark_folder(cam, tmp_path / "dark", num_frames=100)
    rep = calibrate_from_folders(sweep, dark)
    tr = rep.calibration.tap_response
    assert rep.sweep_amplitude == "common" and not rep.warnings
    np.testing.assert_allclose(tr.cos, (0.5, 0.0, 0.08), atol=2e-3)
    assert "harmonics at multiples of N fitted" in rep.tap_response_summary()
    assert "cos 3x +0.080" in rep.tap_response_summary()
    per_step = calibrate_from_folders(sweep, dark, sweep_amplitude="per-step").calibration
    assert abs(per_step.tap_response.cos[2]) < 1e-6 and per_step.tap_response.cos[1] == pytest.approx(-0.02, abs=2e-3)
    for d in (800.0, 1800.0):
        frames = simulate_frames(
            torch.full((1, 1), d), torch.full((1, 1), 20000.0), cam, 20000, generator=torch.Generator().manual_seed(1)
        )
        mc = float(frames.depth_mm.double().std())
        assert float(sigma_depth_mm(d, 20000.0, rep.calibration)) == pytest.approx(mc, rel=0.03)
        assert abs(float(sigma_depth_mm(d, 20000.0, per_step)) / mc - 1) > 0.08
    # a sweep that moves the target (distance_mm steps): per-step normalisation, and a warning with the sigma_D error
    index = json.loads((sweep / "index.json").read_text())
    for entry in index["stacks"]:
        entry["distance_mm"] = entry.pop("phase_rad") / cam.phase_per_mm
    (sweep / "index.json").write_text(json.dumps(index))
    moved = calibrate_from_folders(sweep, dark)
    assert moved.sweep_amplitude == "per-step" and abs(moved.calibration.tap_response.cos[2]) < 1e-6
    (warning,) = moved.warnings
    assert re.search(
        r"sweep: per-step tap sums vary by 8\.0\d % .*sigma_D is off by -1\d\.\d % to \+1\d\.\d %", warning
    )
    with pytest.raises(ValueError, match="sweep_amplitude must be one of"):
        calibrate_from_folders(sweep, dark, sweep_amplitude="fixed")
