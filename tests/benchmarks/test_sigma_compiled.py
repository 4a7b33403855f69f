"""The fused (torch.compile) sigma_D kernel equals the reference closed form, invalid pixels included.

Only the default calibration is compiled here (``slow``: about a minute with a cold compile cache); the kernel's
arithmetic for other calibrations is checked by running the same kernel function eagerly, and its pieces (tap
expansion, float32 cos/sin) against closed forms."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tofdenoise.physics import default_calibration, depth_variance_mm2, sigma_depth_mm
from tofdenoise.physics.calibration import TapResponse

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmark code, not the package
import sigma_compiled as uc  # noqa: E402


@pytest.fixture(scope="module")
def maps():
    gen = torch.Generator().manual_seed(3)
    depth = 200 + 2600 * torch.rand(96, 128, generator=gen)
    signal = 500 + 60000 * torch.rand(96, 128, generator=gen)
    depth[0, :4] = torch.tensor([0.0, -5.0, math.nan, math.inf])
    signal[1, :3] = torch.tensor([0.0, -1.0, math.nan])
    return depth, signal


def _odd_calibration():
    """5 taps, sine terms, a second and a fourth harmonic: no term of the expansion vanishes by symmetry."""
    tr = TapResponse(c0=1.0, cos=(0.45, 0.03, 0.0, 0.01), sin=(0.05, -0.02, 0.0, 0.004))
    return default_calibration().replace(num_taps=5, tap_response=tr)


@pytest.mark.slow
def test_fused_kernel_matches_reference(maps):
    depth, signal = maps
    calib = default_calibration()
    sigma = uc.sigma_depth_mm_compiled(depth, signal, calib)
    ref = sigma_depth_mm(depth, signal, calib)
    assert sigma.dtype == torch.float32 and sigma.shape == depth.shape
    assert torch.equal(torch.isnan(sigma), torch.isnan(ref))
    assert int(torch.isnan(sigma).sum()) == 7
    ok = ~torch.isnan(ref)
    assert float(((sigma[ok] - ref[ok]).abs() / ref[ok]).max()) < 1e-5
    var = uc.depth_variance_mm2_compiled(depth, signal, calib)
    var_ref = depth_variance_mm2(depth, signal, calib)
    assert float(((var[ok] - var_ref[ok]).abs() / var_ref[ok]).max()) < 2e-5
    # broadcasting and float64 (float64 takes the library cos/sin inside the same kernel function)
    row = uc.sigma_depth_mm_compiled(depth[2:3].double(), torch.tensor(20000.0), calib)
    assert row.dtype == torch.float64 and row.shape == (1, 128)
    ref64 = sigma_depth_mm(depth[2:3].double(), torch.full((1, 128), 20000.0, dtype=torch.float64), calib)
    assert float(((row - ref64).abs() / ref64).max()) < 1e-12


@pytest.mark.slow
def test_ill_conditioned_pixels_take_the_reference_path(maps, monkeypatch):
    depth, signal = maps
    calib = default_calibration()
    calls = []
    real = uc.depth_variance_mm2

    def spy(d, a, c):
        calls.append(d.numel())
        return real(d, a, c)

    monkeypatch.setattr(uc, "ILL_CONDITIONED_RHO2", -1.0)  # every valid pixel counts as ill-conditioned
    monkeypatch.setattr(uc, "depth_variance_mm2", spy)
    got = uc.sigma_depth_mm_compiled(depth, signal, calib)
    ref = real(depth, signal, calib).sqrt()
    ok = ~torch.isnan(ref)
    assert calls == [int(ok.sum())]
    assert torch.equal(got[ok], ref[ok])


def test_tap_expansion_hand_computed_for_four_taps():
    """c(x) = 1 + 0.5 cos x + 0.01 cos 3x, theta_1 = pi/2: r_1 = 1 + 0.5 sin psi - 0.01 sin 3psi and
    r'_1 = c'(psi - pi/2) = 0.5 cos psi - 0.03 cos 3psi; the cos(pi/2) ~ 6e-17 terms are dropped."""
    calib = default_calibration().replace(tap_response=TapResponse(c0=1.0, cos=(0.5, 0.0, 0.01), sin=(0.0, 0.0, 0.0)))
    r_terms, dr_terms = uc.tap_expansion(calib)[1]
    assert [(k, kind) for _, k, kind in r_terms] == [(1, "sin"), (3, "sin")]
    assert [c for c, _, _ in r_terms] == pytest.approx([0.5, -0.01], abs=1e-15)
    assert [(k, kind) for _, k, kind in dr_terms] == [(1, "cos"), (3, "cos")]
    assert [c for c, _, _ in dr_terms] == pytest.approx([0.5, -0.03], abs=1e-15)
    assert all(len(r) == 2 and len(d) == 2 for r, d in uc.tap_expansion(calib))


def test_tap_expansion_reproduces_the_tap_response():
    calib = _odd_calibration()
    psi = np.linspace(-7.0, 20.0, 1001)
    basis = {(k, kind): (np.cos if kind == "cos" else np.sin)(k * psi) for k in range(1, 5) for kind in ("cos", "sin")}
    for n, (r_terms, dr_terms) in enumerate(uc.tap_expansion(calib)):
        x = psi - 2 * np.pi * n / calib.num_taps
        r = calib.tap_response.c0 + sum(c * basis[k, kind] for c, k, kind in r_terms)
        dr = sum(c * basis[k, kind] for c, k, kind in dr_terms)
        np.testing.assert_allclose(r, calib.tap_response.value(x), atol=1e-13)
        np.testing.assert_allclose(dr, calib.tap_response.derivative(x), atol=1e-13)


def test_float32_cos_sin_against_float64():
    psi = torch.cat(
        [
            torch.linspace(0.0, 4096.0, 400_001),
            torch.linspace(-10.0, 0.0, 10_001),
            torch.tensor([math.pi / 4, math.pi / 2, math.pi, 1.5 * math.pi]),
        ]
    ).float()
    cos_psi, sin_psi = uc._cos_sin_f32(psi)
    exact = psi.double()
    assert float((cos_psi.double() - exact.cos()).abs().max()) < 2e-7
    assert float((sin_psi.double() - exact.sin()).abs().max()) < 2e-7


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_arithmetic_for_a_general_calibration(dtype):
    """The kernel function itself (run eagerly, no compilation) for 5 taps with sine terms."""
    calib = _odd_calibration()
    gen = torch.Generator().manual_seed(5)
    depth = (100 + 2800 * torch.rand(4000, generator=gen)).to(dtype)
    signal = (100 + 90000 * torch.rand(4000, generator=gen)).to(dtype)
    depth[:3] = torch.tensor([0.0, math.nan, -math.inf], dtype=dtype)
    out, any_ill = uc._make_kernel(calib)(depth, signal, uc.ILL_CONDITIONED_RHO2)
    ref = sigma_depth_mm(depth, signal, calib)
    assert torch.isnan(out[:3]).all() and not bool(any_ill)
    tol = 1e-5 if dtype == torch.float32 else 1e-11
    assert float(((out[3:] - ref[3:]).abs() / ref[3:]).max()) < tol


def test_numpy_input_is_refused():
    with pytest.raises(TypeError, match="torch tensors"):
        uc.sigma_depth_mm_compiled(np.ones(3), np.ones(3), default_calibration())


@pytest.mark.gpu
def test_fused_kernel_on_cuda_matches_the_cpu_reference(maps):
    depth, signal = maps
    calib = default_calibration()
    got = uc.sigma_depth_mm_compiled(depth.cuda(), signal.cuda(), calib)
    assert got.device.type == "cuda"
    ref = sigma_depth_mm(depth, signal, calib)
    got = got.cpu()
    assert torch.equal(torch.isnan(got), torch.isnan(ref))
    ok = ~torch.isnan(ref)
    assert float(((got[ok] - ref[ok]).abs() / ref[ok]).max()) < 1e-5
