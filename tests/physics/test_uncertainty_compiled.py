"""The fused (torch.compile) sigma_D kernel equals the reference closed form, invalid pixels included."""

from __future__ import annotations

import math

import pytest
import torch

from tofdenoise.physics import default_calibration, depth_variance_mm2
from tofdenoise.physics import uncertainty_compiled as uc


@pytest.fixture(scope="module")
def maps():
    gen = torch.Generator().manual_seed(3)
    depth = 200 + 2600 * torch.rand(96, 128, generator=gen)
    signal = 500 + 60000 * torch.rand(96, 128, generator=gen)
    depth[0, :4] = torch.tensor([0.0, -5.0, math.nan, math.inf])
    signal[1, :3] = torch.tensor([0.0, -1.0, math.nan])
    return depth, signal


def test_fused_kernel_matches_reference(maps):
    depth, signal = maps
    calib = default_calibration()
    got = uc.depth_variance_mm2_compiled(depth, signal, calib)
    ref = depth_variance_mm2(depth, signal, calib)
    assert got.dtype == torch.float32 and got.shape == depth.shape
    assert torch.equal(torch.isnan(got), torch.isnan(ref))
    assert int(torch.isnan(got).sum()) == 7
    ok = ~torch.isnan(ref)
    assert float(((got[ok] - ref[ok]).abs() / ref[ok]).max()) < 2e-5
    sigma = uc.sigma_depth_mm_compiled(depth, signal, calib)
    assert torch.allclose(sigma[ok], got[ok].sqrt())


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
    got = uc.depth_variance_mm2_compiled(depth, signal, calib)
    n_valid = int((~torch.isnan(real(depth, signal, calib))).sum())
    assert calls == [n_valid]
    ref = real(depth, signal, calib)
    ok = ~torch.isnan(ref)
    assert torch.equal(got[ok], ref[ok])


def test_numpy_input_is_refused():
    import numpy as np

    with pytest.raises(TypeError, match="torch tensors"):
        uc.depth_variance_mm2_compiled(np.ones(3), np.ones(3), default_calibration())
