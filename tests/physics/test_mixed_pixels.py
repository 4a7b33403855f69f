"""Mixed pixels: closed forms of two-surface mixes, footprint integration, and the simulator fed with tap means."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tofdenoise.physics.calibration import SensorCalibration, TapResponse, default_calibration
from tofdenoise.physics.mixed_pixels import footprint_tap_means_e, mixed_pixel_map, mixed_tap_means_e
from tofdenoise.physics.simulator import demodulate, simulate_frames, simulate_tap_mean_frames


def sinusoidal_camera() -> SensorCalibration:
    """c(x) = 1 + 0.5 cos x: no harmonic, so the decoded phase is exactly the first-bin angle."""
    base = default_calibration()
    return base.replace(tap_response=TapResponse(c0=1.0, cos=(0.5,), sin=(0.0,)))


def decode(means: torch.Tensor, calib: SensorCalibration) -> tuple[float, float]:
    depth, amplitude = demodulate(means.double() + calib.dark_mean_e, calib, tap_axis=0)
    return float(depth.reshape(-1)[0]), float(amplitude.reshape(-1)[0])


@pytest.mark.parametrize("phi1, phi2", [(0.6, 1.8), (2.0, 3.5), (0.2, 2 * math.pi - 0.4)])
def test_equal_mix_of_two_surfaces_decodes_to_the_circular_mean_phase(phi1, phi2):
    calib = sinusoidal_camera()
    a = 20000.0
    d1, d2 = phi1 / calib.phase_per_mm, phi2 / calib.phase_per_mm
    means = mixed_tap_means_e(np.array([[d1], [d2]]), np.array([[a], [a]]), np.full((2, 1), 0.5), calib)
    assert means.shape == (calib.num_taps, 1)
    depth, amplitude = decode(means, calib)
    mean_phase = math.atan2(math.sin(phi1) + math.sin(phi2), math.cos(phi1) + math.cos(phi2)) % (2 * math.pi)
    assert depth == pytest.approx(mean_phase / calib.phase_per_mm, abs=1e-3)
    # amplitude: |cos((phi2 - phi1) / 2)| x the amplitude of one surface (a |C1| = a x 0.5)
    assert amplitude == pytest.approx(a * 0.5 * abs(math.cos((phi2 - phi1) / 2)), rel=1e-6)
    # the flying pixel lies between the surfaces (not at either one) unless they are in phase
    assert min(abs(depth - d1), abs(depth - d2)) > 10.0


def test_unequal_mix_is_the_weighted_phasor_sum():
    calib = sinusoidal_camera()
    phi = np.array([0.9, 2.1])
    a = np.array([30000.0, 10000.0])
    w = np.array([0.25, 0.75])
    means = mixed_tap_means_e((phi / calib.phase_per_mm)[:, None], a[:, None], w[:, None], calib)
    depth, amplitude = decode(means, calib)
    phasor = (w * a * np.exp(1j * phi)).sum()
    assert depth == pytest.approx(np.angle(phasor) / calib.phase_per_mm, abs=1e-3)
    assert amplitude == pytest.approx(0.5 * abs(phasor), rel=1e-6)
    # the DC level is the weighted signal: sum_n lambda_n / N = sum_k w_k a_k c0
    assert float(means.double().mean()) == pytest.approx(float((w * a).sum()), rel=1e-6)


def test_footprint_integration_mixes_only_across_edges():
    calib = default_calibration()
    s = 3
    depth = np.full((2 * s, 3 * s), 800.0, np.float32)
    depth[:, 4:] = 1400.0  # an edge inside pixel column 1 (samples 3, 4, 5: one near, two far)
    signal = np.full_like(depth, 20000.0)
    means = footprint_tap_means_e(depth, signal, calib, s)
    assert means.shape == (calib.num_taps, 2, 3)
    near = mixed_tap_means_e(np.full((1, 1), 800.0), np.full((1, 1), 20000.0), np.ones((1, 1)), calib)
    far = mixed_tap_means_e(np.full((1, 1), 1400.0), np.full((1, 1), 20000.0), np.ones((1, 1)), calib)
    torch.testing.assert_close(means[:, :, 0], near.expand(-1, 2))
    torch.testing.assert_close(means[:, :, 2], far.expand(-1, 2))
    torch.testing.assert_close(means[:, :, 1], (near / 3 + 2 * far / 3).expand(-1, 2), rtol=1e-6, atol=1e-3)
    np.testing.assert_array_equal(mixed_pixel_map(depth, s), [[False, True, False]] * 2)
    # a sample that sees no surface (depth 0) returns nothing: the pixel gets 8/9 of the signal
    depth[0, 0] = 0.0
    dim = footprint_tap_means_e(depth, signal, calib, s)
    torch.testing.assert_close(dim[:, 0, 0], near[:, 0] * 8 / 9, rtol=1e-6, atol=1e-3)
    assert mixed_pixel_map(depth, s)[0, 0]
    with pytest.raises(ValueError, match="divisible by factor 3"):
        footprint_tap_means_e(depth[:, :8], signal[:, :8], calib, s)
    with pytest.raises(ValueError, match="same shape"):
        mixed_tap_means_e(np.ones((2, 3)), np.ones((2, 3)), np.ones((1, 3)), calib)


def test_tap_mean_frames_equal_simulate_frames_for_one_surface():
    """factor 1 (one surface per pixel) through simulate_tap_mean_frames is simulate_frames, bit for bit."""
    calib = default_calibration()
    rng = np.random.default_rng(0)
    depth = rng.uniform(400, 2000, size=(6, 7)).astype(np.float32)
    signal = rng.uniform(3000, 40000, size=(6, 7)).astype(np.float32)
    depth[0, 0] = 0.0  # invalid input pixel
    a = simulate_frames(depth, signal, calib, 5, generator=torch.Generator().manual_seed(3), return_taps=True)
    b = simulate_tap_mean_frames(
        footprint_tap_means_e(depth, signal, calib, 1),
        calib,
        5,
        generator=torch.Generator().manual_seed(3),
        return_taps=True,
    )
    for name in ("depth_mm", "amplitude", "valid", "saturated", "taps"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not bool(b.valid[:, 0, 0].any())
    with pytest.raises(ValueError, match="taps on axis 0"):
        simulate_tap_mean_frames(torch.ones(3, 2, 2), calib, 1)


def test_mixed_pixel_frames_are_biased_toward_the_mix():
    """Monte Carlo: the mean decoded depth of a 50/50 edge pixel is the circular-mean depth (not either surface)."""
    calib = sinusoidal_camera()
    phi1, phi2 = 1.0, 2.0
    d = np.array([[[phi1 / calib.phase_per_mm]], [[phi2 / calib.phase_per_mm]]])
    means = mixed_tap_means_e(d, np.full_like(d, 30000.0), np.full_like(d, 0.5), calib)
    frames = simulate_tap_mean_frames(means, calib, 400, generator=torch.Generator().manual_seed(0))
    expected = 1.5 / calib.phase_per_mm
    assert float(frames.depth_mm.double().mean()) == pytest.approx(expected, abs=0.5)
