"""Noise models: std formulas, reproducible sampling, invalid pixels, variance matching."""

from __future__ import annotations

import math

import pytest
import torch

from tofdenoise.physics.calibration import default_calibration
from tofdenoise.physics.noise_models import (
    DEFAULT_FIXED_SIGMA_MM,
    available_noise_models,
    build_noise_model,
    variance_matching_scale,
)
from tofdenoise.physics.uncertainty import sigma_depth_mm


def _scene(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    depth = 400.0 + 2000.0 * torch.rand(2, 1, 32, 48, generator=g)
    signal = 3000.0 + 47000.0 * torch.rand(2, 1, 32, 48, generator=g)
    valid = torch.rand(2, 1, 32, 48, generator=g) > 0.1
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    sigma = sigma_depth_mm(depth, signal, default_calibration())
    return depth, sigma, valid


def test_registry_and_errors():
    assert available_noise_models() == ["hetero", "range", "fixed", "blind", "none"]
    with pytest.raises(ValueError, match="hetero"):
        build_noise_model("gauss")
    with pytest.raises(ValueError, match="range_sigma_mm|alpha_mm"):
        build_noise_model("range", calib=default_calibration().replace(range_sigma_mm=None))
    with pytest.raises(ValueError, match="sigma"):
        build_noise_model("hetero", sigma_mm=3.0)
    with pytest.raises(ValueError, match="scale"):
        build_noise_model("fixed", scale=-1.0)
    with pytest.raises(ValueError, match="sigma_lo_mm and sigma_hi_mm"):
        build_noise_model("blind")
    with pytest.raises(ValueError, match="must not exceed"):
        build_noise_model("blind", sigma_lo_mm=5.0, sigma_hi_mm=2.0)
    with pytest.raises(ValueError, match="sigma_lo_mm"):
        build_noise_model("blind", sigma_lo_mm=0.0, sigma_hi_mm=2.0)


def test_std_formulas():
    depth, sigma, valid = _scene()
    calib = default_calibration()
    torch.testing.assert_close(build_noise_model("hetero", scale=2.0).std_mm(depth, sigma), 2.0 * sigma, equal_nan=True)
    a0, a1, a2 = calib.range_sigma_mm
    rng = build_noise_model("range", calib=calib)
    torch.testing.assert_close(rng.std_mm(depth), (a0 + a1 * depth + a2 * depth**2).clamp_min(0))
    rng2 = build_noise_model("range", alpha_mm=[1.0, 0.002, 1e-6], scale=0.5)
    torch.testing.assert_close(rng2.std_mm(torch.tensor([1000.0])), torch.tensor([0.5 * (1.0 + 2.0 + 1.0)]))
    fixed = build_noise_model("fixed")
    assert torch.all(fixed.std_mm(depth) == DEFAULT_FIXED_SIGMA_MM)
    assert torch.all(build_noise_model("fixed", sigma_mm=2.5, scale=2.0).std_mm(depth) == 5.0)
    assert torch.all(build_noise_model("none").std_mm(depth) == 0)


@pytest.mark.parametrize("name", ["hetero", "range", "fixed", "blind", "none"])
def test_sampling_reproducible_and_invalid_untouched(name):
    depth, sigma, valid = _scene()
    kwargs = {"sigma_lo_mm": 2.0, "sigma_hi_mm": 20.0} if name == "blind" else {}
    model = build_noise_model(name, calib=default_calibration(), **kwargs)
    n1 = model.sample(depth, sigma, valid, generator=torch.Generator().manual_seed(5))
    n2 = model.sample(depth, sigma, valid, generator=torch.Generator().manual_seed(5))
    n3 = model.sample(depth, sigma, valid, generator=torch.Generator().manual_seed(6))
    assert torch.equal(n1, n2)
    assert torch.equal(n1[~valid], depth[~valid])
    if name == "none":
        assert torch.equal(n1, depth)
    else:
        assert not torch.equal(n1, n3)
        assert (n1[valid] != depth[valid]).float().mean() > 0.99


def test_hetero_sample_statistics():
    """Normalised residuals (noisy - D) / sigma_D are standard normal."""
    calib = default_calibration()
    depth = torch.full((200, 200), 1200.0, dtype=torch.float64)
    signal = torch.linspace(3000, 50000, 200, dtype=torch.float64).expand(200, 200)
    sigma = sigma_depth_mm(depth, signal, calib)
    noisy = build_noise_model("hetero").sample(depth, sigma, generator=torch.Generator().manual_seed(0))
    z = (noisy - depth) / sigma
    assert abs(float(z.mean())) < 0.02
    assert float(z.std()) == pytest.approx(1.0, abs=0.02)
    # the per-column std follows sigma_D (signal varies along columns)
    col_std = (noisy - depth).std(dim=0)
    torch.testing.assert_close(col_std / sigma[0], torch.ones(200, dtype=torch.float64), atol=0.25, rtol=0)


def test_variance_matching_equalises_mean_variance():
    samples = [_scene(0), _scene(1), _scene(2)]
    hetero_mean_var = torch.cat([s[1][s[2]] ** 2 for s in samples]).mean()
    for name in ("range", "fixed"):
        model = build_noise_model(name, calib=default_calibration(), scale=3.0)  # own scale is ignored
        k = variance_matching_scale(model, samples)
        matched = model.with_scale(k)
        var = torch.cat([matched.std_mm(d, s)[v] ** 2 for d, s, v in samples]).mean()
        assert float(var) == pytest.approx(float(hetero_mean_var), rel=1e-6)
        # and the empirical perturbation variance agrees (Monte Carlo)
        g = torch.Generator().manual_seed(3)
        emp = torch.cat([(matched.sample(d, s, v, generator=g) - d)[v] ** 2 for d, s, v in samples]).mean()
        assert float(emp) == pytest.approx(float(hetero_mean_var), rel=0.05)
    assert variance_matching_scale(build_noise_model("hetero"), samples) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="zero variance"):
        variance_matching_scale(build_noise_model("none"), samples)


def test_variance_matching_weights_pixels_by_how_often_training_draws_them():
    """With weights w (a crop's coverage), k^2 sum(w s^2) = sum(w sigma_D^2): a hand-computed two-pixel case, and
    integer weights equal repeating each pixel that many times. Weight 0 leaves a pixel out; a negative or
    non-finite weight is refused."""
    depth = torch.tensor([[1000.0, 1000.0]], dtype=torch.float64)
    sigma = torch.tensor([[2.0, 6.0]], dtype=torch.float64)
    fixed = build_noise_model("fixed", sigma_mm=1.0)
    # unweighted: k^2 = (4 + 36) / 2 = 20; weights (3, 1): k^2 = (3*4 + 36) / 4 = 12; (1, 0): k^2 = 4
    assert variance_matching_scale(fixed, [(depth, sigma, None)]) == pytest.approx(math.sqrt(20.0))
    w = torch.tensor([[3.0, 1.0]], dtype=torch.float64)
    assert variance_matching_scale(fixed, [(depth, sigma, None, w)]) == pytest.approx(math.sqrt(12.0))
    assert variance_matching_scale(fixed, [(depth, sigma, None, torch.tensor([[1.0, 0.0]]))]) == pytest.approx(2.0)
    repeated = (depth[:, [0, 0, 0, 1]], sigma[:, [0, 0, 0, 1]], None)
    assert variance_matching_scale(fixed, [repeated]) == pytest.approx(math.sqrt(12.0))
    samples = [_scene(0), _scene(1)]
    weights = [
        torch.rand(d.shape, generator=torch.Generator().manual_seed(i), dtype=torch.float64)
        for i, (d, _, _) in enumerate(samples)
    ]
    model = build_noise_model("range", calib=default_calibration())
    k = variance_matching_scale(model, [(*s, w) for s, w in zip(samples, weights, strict=True)])
    num = sum(float((w[v] * s[v] ** 2).sum()) for (d, s, v), w in zip(samples, weights, strict=True))
    den = sum(float((w[v] * model.std_mm(d, s)[v] ** 2).sum()) for (d, s, v), w in zip(samples, weights, strict=True))
    assert k == pytest.approx(math.sqrt(num / den), rel=1e-9)
    assert k != pytest.approx(variance_matching_scale(model, samples), rel=1e-3)  # the weights do move it
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="weights must be finite and >= 0"):
            variance_matching_scale(fixed, [(depth, sigma, None, torch.tensor([[1.0, bad]]))])
    with pytest.raises(ValueError, match=r"samples\[0\] must be a \(depth_mm, sigma_d_mm, valid\[, weight\]\)"):
        variance_matching_scale(fixed, [(depth, sigma)])


def test_with_scale_replaces():
    m = build_noise_model("fixed", sigma_mm=2.0, scale=3.0)
    assert m.with_scale(0.5).scale == 0.5
    assert float(m.with_scale(0.5).std_mm(torch.tensor([1.0]))) == pytest.approx(1.0)
    assert math.isclose(m.scale, 3.0)


def test_blind_noise_one_log_uniform_sigma_per_image_iid_gaussian():
    lo, hi = 3.0, 48.0
    model = build_noise_model("blind", sigma_lo_mm=lo, sigma_hi_mm=hi)
    g = torch.Generator().manual_seed(7)
    depth = torch.full((1, 96, 128), 1500.0, dtype=torch.float64)
    sigmas, first_lags = [], []
    for _ in range(400):
        noise = (model.sample(depth, generator=g) - depth)[0]
        s = float(noise.std())
        sigmas.append(s)
        # one sigma per image: the std of each quarter of the image agrees with the whole image's within sampling
        quarters = [float(q.std()) for q in (noise[:48, :64], noise[:48, 64:], noise[48:, :64], noise[48:, 64:])]
        assert max(abs(q / s - 1) for q in quarters) < 0.06  # 3072 px per quarter: sampling std 1.3 %
        # i.i.d. over pixels: neighbours are uncorrelated; Gaussian: kurtosis 3
        z = noise.flatten() / s
        first_lags.append(float((noise[:, 1:] * noise[:, :-1]).mean()) / s**2)
        assert float((z**4).mean()) == pytest.approx(3.0, abs=0.3)
    sig = torch.tensor(sigmas)
    # bounds: every per-image sigma lies in [lo, hi] (up to the 12288-px estimate's 0.7 % sampling error)
    assert float(sig.min()) >= lo * 0.97 and float(sig.max()) <= hi * 1.03
    # log-uniform: log sigma is uniform on [log lo, log hi]: mean at the middle, std (log hi - log lo) / sqrt(12)
    logs = torch.log(sig)
    span = math.log(hi) - math.log(lo)
    assert float(logs.mean()) == pytest.approx((math.log(lo) + math.log(hi)) / 2, abs=0.06 * span)
    assert float(logs.std()) == pytest.approx(span / math.sqrt(12), rel=0.1)
    # a quarter of the images per quarter of the log range (uniform, not clustered at the top as a uniform draw
    # in sigma would be: there the lowest quarter of the log range would get 4 % of the images)
    bins = torch.histc((logs - math.log(lo)) / span, bins=4, min=0.0, max=1.0) / len(sigmas)
    assert torch.all((bins - 0.25).abs() < 0.08), bins
    assert abs(sum(first_lags) / len(first_lags)) < 0.01
    # a (B, 1, H, W) batch draws one sigma per item
    batch = model.sample(depth.expand(6, 1, 96, 128).clone(), generator=g) - 1500.0
    per_item = batch.flatten(1).std(dim=1)
    assert per_item.unique().numel() == 6 and float(per_item.max() / per_item.min()) > 1.05
