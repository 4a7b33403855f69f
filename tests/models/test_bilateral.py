"""The classical row: amplitude-guided joint bilateral filter (closed forms, hand-computed weights, noise)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from tofdenoise.models import available_backbones, build_backbone, count_parameters, is_trainable, trainable_backbones
from tofdenoise.models.bilateral import JointBilateral, default_radius_px, joint_bilateral_filter


def b1hw(x, dtype=torch.float64):
    return torch.as_tensor(x, dtype=dtype)[None, None]


def bf(depth, amp=None, valid=None, **kw):
    amp = torch.ones_like(depth) if amp is None else amp
    return joint_bilateral_filter(depth, amp, valid, **kw)


def test_registered_without_parameters_and_not_trainable():
    assert "bilateral" in available_backbones() and "bilateral" not in trainable_backbones()
    assert not is_trainable("bilateral") and is_trainable("unet")
    net = build_backbone("bilateral", in_channels=2, sigma_spatial_px=1.5)
    assert isinstance(net, JointBilateral) and count_parameters(net, trainable_only=False) == 0
    assert net.radius_px == default_radius_px(1.5) == 3


def test_constant_plane_stays_exactly_constant():
    g = torch.Generator().manual_seed(0)
    depth = torch.full((2, 1, 23, 31), 1234.5678, dtype=torch.float32)
    amp = torch.rand(depth.shape, generator=g) + 0.01
    for sd in (0.5, 20.0, math.inf):
        out = bf(depth, amp, sigma_spatial_px=2.0, sigma_depth_mm=sd, amplitude_power=1.0)
        assert torch.equal(out, depth)


def test_huge_sigma_depth_equals_the_gaussian_blur():
    """sigma_d -> inf, gamma = 0, every pixel valid: a Gaussian blur normalised over the part of the disc window
    inside the frame (interior pixels: a plain convolution with the normalised kernel)."""
    g = torch.Generator().manual_seed(1)
    depth = 1000.0 + 50.0 * torch.rand(1, 1, 15, 17, generator=g, dtype=torch.float64)
    ss, r = 1.3, 2
    offsets = torch.arange(-r, r + 1.0, dtype=torch.float64)
    ys, xs = torch.meshgrid(offsets, offsets, indexing="ij")
    kernel = torch.exp(-(xs**2 + ys**2) / (2 * ss**2)) * ((xs**2 + ys**2) <= r * r)
    kernel = kernel[None, None]
    num = F.conv2d(F.pad(depth, (r,) * 4), kernel)
    den = F.conv2d(F.pad(torch.ones_like(depth), (r,) * 4), kernel)
    expected = num / den
    for sd in (math.inf, 1e12):
        out = bf(depth, sigma_spatial_px=ss, sigma_depth_mm=sd, amplitude_power=0.0, radius_px=r)
        torch.testing.assert_close(out, expected, rtol=0, atol=1e-9)
    interior = F.conv2d(depth, kernel / kernel.sum())
    torch.testing.assert_close(expected[..., r:-r, r:-r], interior, rtol=0, atol=1e-9)


def test_step_edge_preserved_with_small_sigma_depth_and_blurred_with_huge():
    depth = torch.full((1, 1, 9, 20), 1000.0, dtype=torch.float64)
    depth[..., 10:] = 1100.0  # a 100 mm step between columns 9 and 10
    sharp = bf(depth, sigma_spatial_px=2.0, sigma_depth_mm=5.0, amplitude_power=0.0, radius_px=4)
    # across the edge the range weight is exp(-100^2 / 50) = exp(-200): nothing leaks
    assert (sharp - depth).abs().max() < 1e-9
    blurred = bf(depth, sigma_spatial_px=2.0, sigma_depth_mm=math.inf, amplitude_power=0.0, radius_px=4)
    # the pixels next to the edge move by tens of mm towards each other (half way minus the one-sided weights)
    assert 20.0 < blurred[0, 0, 4, 9].item() - 1000.0 < 50.0
    assert 20.0 < 1100.0 - blurred[0, 0, 4, 10].item() < 50.0
    # far from the edge (farther than the radius) nothing changes
    assert (blurred[..., :5] - 1000.0).abs().max() < 1e-9


def test_masked_pixels_never_contribute():
    g = torch.Generator().manual_seed(2)
    depth = 1000.0 + 10.0 * torch.randn(2, 1, 19, 24, generator=g, dtype=torch.float64)
    amp = torch.rand(depth.shape, generator=g, dtype=torch.float64) + 0.1
    valid = torch.rand(depth.shape, generator=g) > 0.3
    kw = dict(sigma_spatial_px=1.5, sigma_depth_mm=15.0, amplitude_power=1.0)
    out = bf(depth, amp, valid, **kw)
    poisoned = torch.where(valid, depth, torch.full_like(depth, 1e9))
    amp_poisoned = torch.where(valid, amp, torch.full_like(amp, 1e9))
    out2 = bf(poisoned, amp_poisoned, valid, **kw)
    assert torch.equal(out[valid], out2[valid])
    # without range term and amplitude weight: the normalised convolution conv(v D) / conv(v) (hand-built kernel)
    r, ss = 2, 1.5
    offsets = torch.arange(-r, r + 1.0, dtype=torch.float64)
    ys, xs = torch.meshgrid(offsets, offsets, indexing="ij")
    kernel = (torch.exp(-(xs**2 + ys**2) / (2 * ss**2)) * ((xs**2 + ys**2) <= r * r))[None, None]
    v = valid.to(torch.float64)
    expected = F.conv2d(F.pad(poisoned * v, (r,) * 4), kernel) / F.conv2d(F.pad(v, (r,) * 4), kernel)
    out4 = bf(
        poisoned, amp_poisoned, valid, sigma_spatial_px=ss, sigma_depth_mm=math.inf, amplitude_power=0.0, radius_px=r
    )
    torch.testing.assert_close(out4[valid], expected[valid], rtol=0, atol=1e-9)
    # no neighbour with a weight: the input is returned (holes surrounded by holes, far from valid pixels)
    lone = torch.zeros_like(depth, dtype=torch.bool)
    lone[0, 0, 3, 3] = True
    out3 = bf(poisoned, amp, lone, **kw)
    assert out3[0, 0, 3, 3] == poisoned[0, 0, 3, 3]
    assert torch.equal(out3[0, 0, 15:, 15:], poisoned[0, 0, 15:, 15:])


def test_amplitude_guidance_hand_computed_three_pixels():
    """A 1 x 3 row, centre pixel p = 1. Weights: w_q = (a_q / a_max)^gamma exp(-|q-p|^2 / 2 ss^2)
    exp(-(D_q - D_p)^2 / 2 sd^2); the low-amplitude left neighbour gets the lower weight."""
    depth = b1hw([[1000.0, 1004.0, 1010.0]])
    amp = b1hw([[0.2, 1.0, 0.8]])
    ss, sd, gamma = 1.0, 10.0, 2.0
    out = bf(depth, amp, sigma_spatial_px=ss, sigma_depth_mm=sd, amplitude_power=gamma, radius_px=1)

    def w(q, p=1):
        return (
            (amp[0, 0, 0, q] / 1.0) ** gamma
            * math.exp(-((q - p) ** 2) / (2 * ss * ss))
            * math.exp(-((depth[0, 0, 0, q] - depth[0, 0, 0, p]) ** 2) / (2 * sd * sd))
        )

    ws = [float(w(q)) for q in range(3)]
    expected = sum(wq * float(depth[0, 0, 0, q]) for q, wq in enumerate(ws)) / sum(ws)
    assert out[0, 0, 0, 1].item() == pytest.approx(expected, rel=0, abs=1e-9)
    assert ws[0] < ws[2]  # 0.04 x 0.607 x 0.923 vs 0.64 x 0.607 x 0.835
    # without amplitude guidance the (closer in depth) left neighbour would weigh more, pulling the value down
    plain = bf(depth, amp, sigma_spatial_px=ss, sigma_depth_mm=sd, amplitude_power=0.0, radius_px=1)
    assert plain[0, 0, 0, 1].item() < out[0, 0, 0, 1].item()
    # a global amplitude scale cancels
    torch.testing.assert_close(
        bf(depth, 37.0 * amp, sigma_spatial_px=ss, sigma_depth_mm=sd, amplitude_power=gamma, radius_px=1),
        out,
        rtol=0,
        atol=1e-9,
    )


def test_noise_reduction_on_a_noisy_plane():
    g = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.arange(64.0), torch.arange(80.0), indexing="ij")
    clean = (1500.0 + 2.0 * xx + 1.0 * yy)[None, None]  # a tilted plane
    sigma = 8.0
    noisy = clean + sigma * torch.randn(clean.shape, generator=g)
    out = bf(noisy, sigma_spatial_px=2.0, sigma_depth_mm=3 * sigma, amplitude_power=0.0)
    raw_mae = (noisy - clean).abs().mean().item()
    mae = (out - clean).abs().mean().item()
    assert raw_mae == pytest.approx(sigma * math.sqrt(2 / math.pi), rel=0.05)
    # a radius-4 disc of sigma_s = 2 averages ~ 25 effective pixels: the noise falls by ~ 4x (3x with margin)
    assert mae < raw_mae / 3.0, (mae, raw_mae)


def test_amplitude_weighting_helps_on_heteroscedastic_noise():
    """Noise std ~ 1/amplitude: gamma = 2 (inverse-variance weights) beats gamma = 0 on the same frame."""
    g = torch.Generator().manual_seed(4)
    clean = torch.full((1, 1, 64, 64), 2000.0)
    amp = 0.05 + torch.rand(clean.shape, generator=g)
    noisy = clean + (2.0 / amp) * torch.randn(clean.shape, generator=g)
    kw = dict(sigma_spatial_px=2.0, sigma_depth_mm=math.inf)
    mae = {gm: (bf(noisy, amp, amplitude_power=gm, **kw) - clean).abs().mean().item() for gm in (0.0, 2.0)}
    assert mae[2.0] < 0.5 * mae[0.0], mae


def test_backbone_on_the_network_input_matches_the_function():
    g = torch.Generator().manual_seed(5)
    depth = 900.0 + 20.0 * torch.rand(1, 1, 12, 14, generator=g)
    amp = torch.rand(depth.shape, generator=g)
    amp[..., 2:4, 2:4] = 0.0  # invalid pixels: zero amplitude channel
    net = JointBilateral(sigma_spatial_px=1.0, sigma_depth_mm=10.0, amplitude_power=1.0, depth_scale_mm=100.0)
    y = net(torch.cat([depth / 100.0, amp / amp.max()], dim=1)) * 100.0
    ref = joint_bilateral_filter(
        depth, amp, amp > 0, sigma_spatial_px=1.0, sigma_depth_mm=10.0, amplitude_power=1.0, radius_px=2
    )
    torch.testing.assert_close(y, ref, rtol=0, atol=2e-3)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(sigma_spatial_px=0.0), "sigma_spatial_px"),
        (dict(sigma_depth_mm=-1.0), "sigma_depth_mm"),
        (dict(sigma_depth_mm=math.nan), "sigma_depth_mm"),
        (dict(amplitude_power=-0.5), "amplitude_power"),
        (dict(radius_px=1.5), "radius_px"),
        (dict(in_channels=1), "use_signal_channel"),
    ],
)
def test_bad_parameters_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        build_backbone("bilateral", **{"in_channels": 2, **kw})
