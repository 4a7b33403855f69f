"""sigma_D: closed form vs generic inverse, Monte Carlo WLS fit, numerics, invalid pixels, amplitude map."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tofdenoise.physics.calibration import SensorCalibration, TapResponse, default_calibration
from tofdenoise.physics.uncertainty import (
    amplitude_to_signal_e,
    depth_variance_mm2,
    information_matrix,
    sigma_depth_mm,
    tap_jacobian,
    tap_mean_e,
    tap_variance_e2,
)


def _calibs() -> list[SensorCalibration]:
    base = default_calibration()
    return [
        base,
        base.replace(num_taps=3, tap_response=TapResponse(0.5, (0.5,), (0.0,)), dark_std_e=12.0),  # full contrast
        base.replace(num_taps=5, tap_response=TapResponse(1.0, (0.4, 0.05, 0.02), (0.15, -0.03, 0.0))),
        base.replace(num_taps=8, modulation_frequency_hz=100e6, tap_response=TapResponse(2.0, (0.9,), (-0.5,))),
    ]


def _generic_sigma(depth, signal, calib):
    """[(J^T Sigma^-1 J)^-1]_DD through a full matrix inverse per pixel (float64 reference)."""
    g, r = tap_jacobian(depth, signal, calib)
    var = tap_variance_e2(depth, signal, calib)
    J = np.stack([g, r], axis=-1)  # (P, N, 2)
    M = np.einsum("pni,pn,pnj->pij", J, 1.0 / var, J)
    return np.sqrt(np.linalg.inv(M)[:, 0, 0])


@pytest.mark.parametrize("idx", range(4))
def test_closed_form_equals_generic_inverse(idx):
    calib = _calibs()[idx]
    rng = np.random.default_rng(idx)
    depth = rng.uniform(50.0, 0.99 * calib.unambiguous_range_mm, 4000)
    signal = np.exp(rng.uniform(np.log(50.0), np.log(2e5), 4000))
    got = sigma_depth_mm(depth, signal, calib)
    ref = _generic_sigma(depth, signal, calib)
    np.testing.assert_allclose(got, ref, rtol=1e-6)
    # also equal to I_aa / (I_DD I_aa - I_Da^2)
    i_dd, i_da, i_aa = information_matrix(depth, signal, calib)
    np.testing.assert_allclose(depth_variance_mm2(depth, signal, calib), i_aa / (i_dd * i_aa - i_da**2), rtol=1e-6)


def test_hand_computed_read_noise_limit():
    """Constant tap variance (read noise >> shot noise), pure cosine: sigma_D = s / (a k c1 sqrt(N/2))."""
    for n in (3, 4, 6):
        calib = default_calibration().replace(num_taps=n, tap_response=TapResponse(1.0, (0.5,), (0.0,)), dark_std_e=1e4)
        a = 1.0
        expected = 1e4 / (a * calib.phase_per_mm * 0.5 * math.sqrt(n / 2))
        got = sigma_depth_mm(np.array([321.0, 1234.0]), np.array([a, a]), calib)
        np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_tap_model_equations():
    calib = default_calibration()
    d, a = np.array([700.0]), np.array([9000.0])
    psi = 4 * math.pi * calib.modulation_frequency_hz / 299792458000.0 * 700.0
    r = calib.tap_response.value(psi - calib.tap_phases_rad)
    np.testing.assert_allclose(tap_mean_e(d, a, calib)[0], 9000.0 * r + calib.dark_mean_e, rtol=1e-12)
    np.testing.assert_allclose(tap_variance_e2(d, a, calib)[0], 9000.0 * r + calib.dark_std_e**2, rtol=1e-12)
    g, rr = tap_jacobian(d, a, calib)
    h = 1e-4
    num = (tap_mean_e(d + h, a, calib) - tap_mean_e(d - h, a, calib)) / (2 * h)
    np.testing.assert_allclose(g, num, rtol=1e-6)


def _gauss_newton_wls(y, var, calib, d0, a0, iters=6):
    """Weighted Gauss-Newton fit of (D, a) to tap vectors y (P, N) with known tap variances."""
    d, a = d0.copy(), a0.copy()
    w = 1.0 / var
    for _ in range(iters):
        mu = tap_mean_e(d, a, calib)
        g, r = tap_jacobian(d, a, calib)
        res = y - mu
        m11, m12, m22 = (w * g * g).sum(-1), (w * g * r).sum(-1), (w * r * r).sum(-1)
        b1, b2 = (w * g * res).sum(-1), (w * r * res).sum(-1)
        det = m11 * m22 - m12**2
        d = d + (m22 * b1 - m12 * b2) / det
        a = a + (m11 * b2 - m12 * b1) / det
    return d, a


@pytest.mark.parametrize("depth_mm,signal_e", [(600.0, 40000.0), (1000.0, 12000.0), (1450.0, 3000.0), (2222.0, 1500.0)])
def test_monte_carlo_wls_fit_matches_sigma(depth_mm, signal_e):
    calib = default_calibration()
    rng = np.random.default_rng(7)
    p = 20000
    d = np.full(p, depth_mm)
    a = np.full(p, signal_e)
    lam = tap_mean_e(d, a, calib) - calib.dark_mean_e
    y = rng.poisson(lam).astype(np.float64) + calib.dark_mean_e + rng.normal(0.0, calib.dark_std_e, lam.shape)
    var = tap_variance_e2(d, a, calib)
    d_hat, _ = _gauss_newton_wls(y, var, calib, d, a)
    measured = d_hat.std()
    predicted = float(sigma_depth_mm(depth_mm, signal_e, calib))
    # std of a sample std with n = 20000 is ~0.5 %; allow 3 %
    assert measured == pytest.approx(predicted, rel=0.03)
    assert abs(d_hat.mean() - depth_mm) < 4 * predicted / math.sqrt(p) + 0.01 * predicted


def test_monotone_decreasing_in_signal():
    for calib in _calibs():
        a = np.geomspace(10.0, 1e6, 200)
        for depth in (123.0, 777.0, 1500.0):
            s = sigma_depth_mm(np.full_like(a, depth), a, calib)
            assert np.all(np.diff(s) < 0)


def test_float32_matches_float64_numpy_and_torch():
    calib = default_calibration()
    rng = np.random.default_rng(1)
    d64 = rng.uniform(100, 2900, 10000)
    a64 = np.exp(rng.uniform(np.log(100), np.log(1e5), 10000))
    ref = sigma_depth_mm(d64, a64, calib)
    got32 = sigma_depth_mm(d64.astype(np.float32), a64.astype(np.float32), calib)
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, ref, rtol=2e-5)
    t32 = sigma_depth_mm(torch.tensor(d64, dtype=torch.float32), torch.tensor(a64, dtype=torch.float32), calib)
    assert t32.dtype == torch.float32
    np.testing.assert_allclose(t32.numpy(), ref, rtol=2e-5)
    t64 = sigma_depth_mm(torch.tensor(d64), torch.tensor(a64), calib)
    assert t64.dtype == torch.float64
    np.testing.assert_allclose(t64.numpy(), ref, rtol=1e-12)


def test_shapes_broadcast_and_invalid_give_nan():
    calib = default_calibration()
    d = torch.tensor([[0.0, -5.0, float("nan"), float("inf")], [1000.0, 1000.0, 1000.0, 1000.0]])
    a = torch.tensor([[5000.0, 5000.0, 5000.0, 5000.0], [0.0, -1.0, float("nan"), float("inf")]])
    s = sigma_depth_mm(d, a, calib)
    assert s.shape == (2, 4) and torch.isnan(s).all()
    # scalar signal broadcast over a (B,1,H,W) depth map
    dm = torch.full((2, 1, 3, 5), 900.0)
    s2 = sigma_depth_mm(dm, 8000.0, calib)
    assert s2.shape == (2, 1, 3, 5)
    assert torch.allclose(s2, torch.full_like(s2, float(sigma_depth_mm(900.0, 8000.0, calib))))


@pytest.mark.gpu
def test_cuda_matches_cpu():
    calib = default_calibration()
    d = torch.rand(64, 64) * 2500 + 100
    a = torch.rand(64, 64) * 40000 + 1000
    cpu = sigma_depth_mm(d, a, calib)
    gpu = sigma_depth_mm(d.cuda(), a.cuda(), calib)
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=0)


def test_amplitude_to_signal_map():
    calib = default_calibration()
    amp = np.linspace(0.0, 100.0, 101)
    amp[50] = 1e6  # outlier must not stretch the scale
    sig = amplitude_to_signal_e(amp, calib, lower_percentile=0.0, upper_percentile=99.0)
    assert np.isnan(sig[0])  # zero amplitude -> invalid
    assert sig[50] == pytest.approx(calib.signal_max_e)
    hi = np.percentile(amp[1:], 99.0)
    assert sig[10] == pytest.approx(
        calib.signal_min_e + (calib.signal_max_e - calib.signal_min_e) * (10.0 - 1.0) / (hi - 1.0)
    )
    assert np.nanmin(sig) == pytest.approx(calib.signal_min_e)
    valid = amp < 90
    sig_v = amplitude_to_signal_e(torch.tensor(amp), calib, valid=torch.tensor(valid), fill_value=0.0)
    assert float(sig_v[95]) == 0.0
    ref = amplitude_to_signal_e(amp, calib, valid=valid, fill_value=0.0)
    np.testing.assert_allclose(sig_v.numpy(), ref, rtol=1e-9)
    const = amplitude_to_signal_e(np.full(10, 3.0), calib)
    np.testing.assert_allclose(const, 0.5 * (calib.signal_min_e + calib.signal_max_e))
    with pytest.raises(ValueError, match="percentile"):
        amplitude_to_signal_e(amp, calib, lower_percentile=50, upper_percentile=10)


def test_two_pass_fallback_matches_single_pass(monkeypatch):
    """Ill-conditioned pixels (rho^2 above the bound) are recomputed with the two-pass residual form;
    forcing that path for every pixel gives the same numbers."""
    import tofdenoise.physics.uncertainty_numpy as UN

    calib = default_calibration()
    rng = np.random.default_rng(3)
    d = rng.uniform(100, 2900, 5000)
    a = np.exp(rng.uniform(np.log(100), np.log(1e5), 5000))
    single = sigma_depth_mm(d, a, calib)
    monkeypatch.setattr(UN, "RHO2_SINGLE_PASS_MAX", -1.0)
    forced = sigma_depth_mm(d, a, calib)
    np.testing.assert_allclose(forced, single, rtol=1e-10)
    np.testing.assert_allclose(forced, _generic_sigma(d, a, calib), rtol=1e-6)


def test_large_map_blocks_threads_and_mixed_inputs():
    """Maps larger than one block (threaded) equal the per-pixel evaluation; torch x python scalar mixes."""
    calib = default_calibration()
    g = torch.Generator().manual_seed(0)
    d = 100 + 2800 * torch.rand(300, 400, generator=g, dtype=torch.float64)
    a = 1000 + 50000 * torch.rand(300, 400, generator=g, dtype=torch.float64)
    d[0, :7] = torch.tensor([0.0, -1.0, float("nan"), float("inf"), 5.0, 6.0, 7.0], dtype=torch.float64)
    full = sigma_depth_mm(d, a, calib)
    with np.errstate(invalid="ignore"):  # the reference itself is not NaN-safe
        ref = _generic_sigma(d.numpy().reshape(-1), a.numpy().reshape(-1), calib).reshape(300, 400)
    ref[0, :4] = np.nan
    np.testing.assert_allclose(full.numpy(), ref, rtol=1e-6)
    assert torch.isnan(full[0, :4]).all() and torch.isfinite(full[0, 4:]).all()
    s = sigma_depth_mm(torch.tensor([[900.0]]), 8000.0, calib)
    assert isinstance(s, torch.Tensor) and s.shape == (1, 1) and s.dtype == torch.float32


def test_torch_kernel_path_matches_numpy_kernel():
    """The torch kernel (used for CUDA tensors) gives the same numbers as the CPU numpy kernel."""
    from tofdenoise.physics.sigma_kernels import variance_two_pass

    calib = default_calibration().replace(tap_response=TapResponse(1.0, (0.45, 0.03, 0.01), (0.1, 0.0, -0.02)))
    rng = np.random.default_rng(5)
    d = rng.uniform(100, 2900, 3000)
    a = np.exp(rng.uniform(np.log(100), np.log(1e5), 3000))
    R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
    torch_var = variance_two_pass(torch.tensor(d), torch.tensor(a), calib, R, G)
    np.testing.assert_allclose(torch_var.numpy(), depth_variance_mm2(d, a, calib), rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(torch_var.numpy()), _generic_sigma(d, a, calib), rtol=1e-6)


def test_threaded_blocks_work_after_fork():
    """The block thread pool is per process: a forked child (e.g. a DataLoader worker) must not deadlock
    on the parent's (thread-less) pool. Pure numpy in the child (torch's OpenMP is not fork-safe)."""
    import multiprocessing as mp

    import tofdenoise.physics.uncertainty_numpy as UN

    calib = default_calibration()
    d = np.full((400, 400), 1000.0, np.float32)
    a = np.full((400, 400), 8000.0, np.float32)
    expected = float(UN.depth_variance_numpy(d, a, calib, workers=2)[0, 0])  # creates the pool in the parent
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        got = pool.apply_async(_child_variance, (calib,)).get(timeout=60)
    assert got == pytest.approx(expected, rel=1e-6)


def _child_variance(calib):
    import tofdenoise.physics.uncertainty_numpy as UN

    d = np.full((400, 400), 1000.0, np.float32)
    a = np.full((400, 400), 8000.0, np.float32)
    return float(UN.depth_variance_numpy(d, a, calib, workers=2)[0, 0])


def test_trailing_zero_harmonics_change_nothing():
    base = default_calibration()
    short = base.replace(tap_response=TapResponse(1.0, (0.5,), (0.1,)))
    padded = base.replace(tap_response=TapResponse(1.0, (0.5, 0.0, 0.0), (0.1, 0.0, 0.0)))
    d = np.linspace(10.0, 2900.0, 777)
    a = np.linspace(100.0, 90000.0, 777)
    np.testing.assert_allclose(sigma_depth_mm(d, a, padded), sigma_depth_mm(d, a, short), rtol=1e-12)
    np.testing.assert_allclose(sigma_depth_mm(d, a, padded), _generic_sigma(d, a, padded), rtol=1e-6)
