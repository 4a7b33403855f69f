"""Tap-level simulator and N-phase demodulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tofdenoise.physics.calibration import TapResponse, default_calibration
from tofdenoise.physics.simulator import (
    default_min_amplitude_e,
    demodulate,
    phase_decoder,
    signal_from_taps_e,
    simulate_dark_taps,
    simulate_frames,
)
from tofdenoise.physics.uncertainty import sigma_depth_mm, tap_mean_e


@pytest.mark.parametrize(
    "tap_response,num_taps",
    [
        (TapResponse(1.0, (0.5, 0.0, 0.015), (0.0, 0.0, 0.0)), 4),  # default: aliasing 3rd harmonic (LUT)
        (TapResponse(1.0, (0.3,), (0.4,)), 4),  # pure phase offset
        (TapResponse(1.0, (0.35, 0.05, 0.04), (-0.3, 0.02, 0.01)), 4),
        (TapResponse(1.0, (0.4, 0.05, 0.02, 0.01), (0.1, 0.0, 0.0, 0.01)), 5),  # 4th harmonic aliases for N=5
    ],
)
def test_noise_free_demodulation_is_exact(tap_response, num_taps):
    calib = default_calibration().replace(tap_response=tap_response, num_taps=num_taps)
    depth = np.linspace(1.0, calib.unambiguous_range_mm - 1.0, 5000)
    taps = tap_mean_e(depth, np.full_like(depth, 20000.0), calib)  # (P, N) noise-free, incl. dark offset
    d, amp = demodulate(torch.tensor(taps), calib, tap_axis=-1)
    np.testing.assert_allclose(d.numpy(), depth, atol=1e-3)
    c1 = tap_response.first_harmonic_amplitude
    assert np.allclose(amp.numpy() / (20000.0 * c1), 1.0, atol=0.12)


def test_decoder_rejects_non_invertible_response():
    calib = default_calibration().replace(tap_response=TapResponse(1.0, (0.5, 0.0, 0.3), (0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="non-monotonic"):
        phase_decoder(calib)


def test_depth_wraps_beyond_unambiguous_range():
    calib = default_calibration()
    u = calib.unambiguous_range_mm
    depth = np.array([300.0, u + 300.0])
    taps = tap_mean_e(depth, np.full(2, 10000.0), calib)
    d, _ = demodulate(torch.tensor(taps), calib, tap_axis=-1)
    np.testing.assert_allclose(d.numpy(), [300.0, 300.0], atol=1e-3)


def test_unbiased_and_temporal_std_matches_sigma_d():
    """Default calibration: atan2 pipeline std within a few percent of the WLS sigma_D (see docs)."""
    calib = default_calibration()
    depths = torch.linspace(500.0, 2500.0, 9)
    signals = torch.tensor([4000.0, 12000.0, 40000.0])
    depth = depths[None, :, None].expand(3, 9, 24).contiguous()
    signal = signals[:, None, None].expand(3, 9, 24).contiguous()
    frames = simulate_frames(depth, signal, calib, 300, generator=torch.Generator().manual_seed(0))
    assert frames.valid.all()
    d = frames.depth_mm.double()
    sigma = sigma_depth_mm(depth.double(), signal.double(), calib)
    ratio = d.std(dim=0).mean(-1) / sigma[..., 0]
    assert float(ratio.min()) > 0.95 and float(ratio.max()) < 1.10, ratio
    assert float(ratio.mean()) == pytest.approx(1.03, abs=0.03)
    bias = d.mean(dim=0).mean(-1) - depth[..., 0].double()
    se = sigma[..., 0] / math.sqrt(300 * 24)
    assert torch.all(bias.abs() < 5 * se + 0.05), bias


def test_outputs_shapes_flags_and_reproducibility():
    calib = default_calibration()
    depth = torch.full((6, 7), 1000.0)
    depth[0, 0] = 0.0  # invalid input
    signal = torch.full((6, 7), 20000.0)
    signal[1, 1] = 1e6  # saturates
    signal[2, 2] = 1.0  # far below the amplitude threshold
    f1 = simulate_frames(depth, signal, calib, 5, generator=torch.Generator().manual_seed(3), return_taps=True)
    f2 = simulate_frames(depth.numpy(), signal.numpy(), calib, 5, generator=torch.Generator().manual_seed(3))
    assert f1.depth_mm.shape == (5, 6, 7) and f1.depth_mm.dtype == torch.float32
    assert f1.amplitude.shape == (5, 6, 7) and f1.valid.dtype == torch.bool and f1.saturated.dtype == torch.bool
    assert f1.taps is not None and f1.taps.shape == (5, 4, 6, 7) and f2.taps is None
    assert torch.equal(f1.depth_mm, f2.depth_mm)
    assert not f1.valid[:, 0, 0].any() and torch.all(f1.depth_mm[:, 0, 0] == 0)
    assert f1.saturated[:, 1, 1].all() and not f1.valid[:, 1, 1].any()
    assert f1.taps[:, :, 1, 1].max() == calib.full_well_e
    assert not f1.valid[:, 2, 2].any()
    assert f1.valid.sum() == 5 * (42 - 3) and not f1.saturated.sum() > 5
    # ADC quantisation: taps on the gain grid
    g = calib.adc_gain_e_per_dn
    assert torch.allclose(f1.taps / g, torch.round(f1.taps / g))
    f3 = simulate_frames(
        depth, signal, calib, 2, generator=torch.Generator().manual_seed(3), quantize=False, return_taps=True
    )
    assert not torch.allclose(f3.taps / g, torch.round(f3.taps / g))


def test_exposure_scales_signal():
    calib = default_calibration()
    depth = torch.full((16, 16), 800.0)
    signal = torch.full((16, 16), 5000.0)
    f1 = simulate_frames(
        depth, signal, calib, 20, exposure=1.0, generator=torch.Generator().manual_seed(1), return_taps=True
    )
    f2 = simulate_frames(
        depth, signal, calib, 20, exposure=2.5, generator=torch.Generator().manual_seed(1), return_taps=True
    )
    a1 = float(signal_from_taps_e(f1.taps, calib, tap_axis=1).mean())
    a2 = float(signal_from_taps_e(f2.taps, calib, tap_axis=1).mean())
    assert a1 == pytest.approx(5000.0, rel=0.01)
    assert a2 == pytest.approx(12500.0, rel=0.01)
    assert float(f2.amplitude.mean() / f1.amplitude.mean()) == pytest.approx(2.5, rel=0.01)


def test_dark_frames_statistics():
    calib = default_calibration()
    taps = simulate_dark_taps((32, 32), calib, 100, generator=torch.Generator().manual_seed(0)).double()
    assert float(taps.mean()) == pytest.approx(calib.dark_mean_e, abs=0.5)
    # the calibrated sigma_dark includes the ADC share, so quantised dark frames reproduce it
    assert float(taps.var(dim=0).mean().sqrt()) == pytest.approx(calib.dark_std_e, rel=0.01)
    assert default_min_amplitude_e(calib) == pytest.approx(5 * math.sqrt(0.5) * calib.dark_std_e)


def test_errors():
    calib = default_calibration()
    with pytest.raises(ValueError, match="same shape"):
        simulate_frames(torch.ones(3, 3), torch.ones(3, 4), calib, 1)
    with pytest.raises(ValueError, match="num_frames"):
        simulate_frames(torch.ones(3, 3), torch.ones(3, 3), calib, 0)
    with pytest.raises(ValueError, match="exposure"):
        simulate_frames(torch.ones(3, 3), torch.ones(3, 3), calib, 1, exposure=-1)
    with pytest.raises(ValueError, match="taps"):
        demodulate(torch.ones(2, 3, 4, 4), calib)
