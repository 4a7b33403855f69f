"""Training holes: seeded and pure, low-signal holes at the simulator's threshold, edges, blobs, datamodule plumbing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tofdenoise.data_modules import ToFDataModule
from tofdenoise.data_modules.holes import HoleModel, apply_holes, blob_holes, edge_holes, low_signal_holes
from tofdenoise.physics.calibration import resolve_calibration
from tofdenoise.physics.simulator import default_min_amplitude_e, simulate_frames

CALIB = resolve_calibration(None)


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def ramp_signal(h: int = 64, w: int = 256) -> torch.Tensor:
    return torch.linspace(CALIB.signal_min_e, CALIB.signal_max_e, w, dtype=torch.float64).expand(h, w).clone()


def test_low_signal_holes_hit_the_target_fraction_on_the_darkest_pixels():
    signal = ramp_signal()
    valid = torch.ones_like(signal, dtype=torch.bool)
    holes = low_signal_holes(signal, valid, CALIB, 0.2, gen())
    share = float(holes.double().mean())
    assert share == pytest.approx(0.2, abs=0.03)
    column_share = holes.double().mean(0)
    assert float(column_share[:15].min()) > 0.95 and float(column_share[100:].max()) < 0.05  # dark side only
    assert not low_signal_holes(signal, valid, CALIB, 0.0, gen()).any()
    assert not low_signal_holes(signal, torch.zeros_like(valid), CALIB, 0.2, gen()).any()
    with pytest.raises(ValueError, match="fraction"):
        low_signal_holes(signal, valid, CALIB, 1.0, gen())


def test_low_signal_rule_matches_the_simulator_decision_statistics():
    """A pixel whose darkened signal puts its expected amplitude exactly at the threshold is dropped about half
    the time by the simulator's own decision (taps, noise, demodulation); the hole model agrees."""
    c1 = CALIB.tap_response.first_harmonic_amplitude
    thr = default_min_amplitude_e(CALIB)
    signal_at_thr = thr / c1
    n = 20000
    sim = simulate_frames(
        torch.full((n,), 1000.0), torch.full((n,), signal_at_thr), CALIB, 1, generator=gen(1), quantize=False
    )
    sim_drop = 1.0 - float(sim.valid.double().mean())
    # one column at the threshold (after the fraction's scaling): fraction f of a two-level image
    signal = torch.cat([torch.full((n,), CALIB.signal_min_e), torch.full((n,), CALIB.signal_max_e)])[None]
    holes = low_signal_holes(signal.double(), torch.ones_like(signal, dtype=torch.bool), CALIB, 0.25, gen(2))
    model_drop = float(holes[0, :n].double().mean())
    assert sim_drop == pytest.approx(0.5, abs=0.03)
    assert model_drop == pytest.approx(sim_drop, abs=0.03)
    assert float(holes[0, n:].double().mean()) == 0.0  # 16x brighter: never below the threshold


def test_edge_holes_only_at_depth_jumps():
    depth = torch.full((20, 20), 1000.0, dtype=torch.float64)
    depth[:, 10:] = 1500.0
    valid = torch.ones((20, 20), dtype=torch.bool)
    holes = edge_holes(depth, valid, 0.05, 1.0, gen())
    expected = torch.zeros_like(valid)
    expected[:, 9:11] = True
    assert torch.equal(holes, expected)
    assert not edge_holes(depth, valid, 0.6, 1.0, gen()).any()  # 50 % jump below a 60 % threshold
    half = edge_holes(depth, valid, 0.05, 0.5, gen()).double().sum() / expected.sum()
    assert 0.25 < float(half) < 0.75


def test_blob_holes_count_and_size():
    shape = (200, 200)
    areas = []
    counts = []
    for seed in range(20):
        holes = blob_holes(shape, 0.5, (5.0, 5.0), gen(seed))
        counts.append(int(holes.any()))
        areas.append(float(holes.double().sum()))
    # mean 2 blobs of radius 5 (ellipse axis ratio U(0.5, 1): mean area pi 25 x 0.75), overlaps rare
    mean_area = float(np.mean(areas))
    assert mean_area == pytest.approx(2 * math.pi * 25 * 0.75, rel=0.35)
    assert not blob_holes(shape, 0.0, (5.0, 5.0), gen()).any()


def test_hole_model_is_seeded_and_stays_inside_valid():
    signal = ramp_signal(64, 64)
    depth = torch.full((64, 64), 1200.0, dtype=torch.float64)
    valid = torch.ones((64, 64), dtype=torch.bool)
    valid[:8] = False
    model = HoleModel(max_low_signal_fraction=0.3, blob_density=5.0)
    a = model.sample(depth, signal, valid, CALIB, gen(7))
    b = model.sample(depth, signal, valid, CALIB, gen(7))
    c = model.sample(depth, signal, valid, CALIB, gen(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.any() and not (a & ~valid).any()
    assert model.sample(depth[None], signal[None], valid[None], CALIB, gen(7)).shape == (1, 64, 64)
    maps = {"noisy": depth.float(), "mask": valid.float()}
    out = apply_holes(maps, a)
    assert torch.all(out["noisy"][a] == 0) and torch.all(out["mask"][a] == 0)
    assert torch.equal(out["noisy"][~a], maps["noisy"][~a]) and maps["noisy"].min() > 0  # input not changed
    for bad in ({"max_low_signal_fraction": 1.0}, {"edge_prob": 2.0}, {"blob_radius_px": (5, 1)}):
        with pytest.raises(ValueError, match="holes_kwargs"):
            HoleModel(**bad)


SMALL = dict(source_kwargs=dict(num_samples=10, height=48, width=64), crop_size=32, batch_size=2)


def test_datamodule_holes_fixed_in_eval_random_in_training(tmp_path):
    dm = ToFDataModule(**SMALL, cache_dir=str(tmp_path / "cache"))
    plain = ToFDataModule(**SMALL, cache_dir=str(tmp_path / "cache"), holes=False)
    for d in (dm, plain):
        d.prepare_data()
        d.setup("fit")
    for split in ("val", "test"):
        for i in range(len(dm.datasets[split])):
            a, b, ref = dm.datasets[split][i], dm.datasets[split][i], plain.datasets[split][i]
            assert torch.equal(a["mask"], b["mask"]) and torch.equal(a["noisy"], b["noisy"])  # fixed holes
            holes = (ref["mask"] > 0) & (a["mask"] == 0)
            assert holes.any()
            for key in ("noisy", "clean", "sigma", "amplitude"):
                assert torch.all(a[key][holes] == 0), key
                kept = a["mask"] > 0
                assert torch.equal(a[key][kept], ref[key][kept]), key  # same noise where not a hole
            assert "signal" not in a
    train = dm.datasets["train"]
    masks = [train[0]["mask"] for _ in range(4)]
    assert any(not torch.equal(masks[0], m) for m in masks[1:])  # fresh holes on every read
    share = 1 - float(torch.stack(masks).mean())
    assert 0.0 < share < 0.5
    with pytest.raises(ValueError, match="holes_kwargs"):
        ToFDataModule(**SMALL, cache_dir=str(tmp_path / "cache"), holes_kwargs={"nope": 1})


# ---------------------------------------------------------------- physical signal route
@pytest.mark.parametrize("level", [0.8, 1.0, 1.3])
def test_physical_low_signal_holes_follow_the_rice_distribution_of_the_measured_amplitude(level):
    """With the camera's own signal (s = 1) a pixel is a hole when |a |C1| + n| < thr: the share of holes of a
    uniform signal is the Rice CDF at thr (nu = a |C1|, sigma^2 = 2/N (a c0 + sigma_dark^2))."""
    from scipy.stats import rice

    from tofdenoise.data_modules.holes import measured_amplitude_below_threshold

    c1 = CALIB.tap_response.first_harmonic_amplitude
    thr = default_min_amplitude_e(CALIB)
    a = level * thr / c1
    signal = torch.full((200, 200), a, dtype=torch.float64)
    valid = torch.ones_like(signal, dtype=torch.bool)
    holes = measured_amplitude_below_threshold(signal, valid, CALIB, 1.0, gen(7))
    sigma = math.sqrt(2.0 / CALIB.num_taps * (a * CALIB.tap_response.c0 + CALIB.dark_std_e**2))
    expected = float(rice.cdf(thr / sigma, a * c1 / sigma))
    assert float(holes.double().mean()) == pytest.approx(expected, abs=4 * math.sqrt(expected * (1 - expected) / 4e4))


def test_physical_hole_model_uses_the_cameras_own_threshold_and_full_well():
    from tofdenoise.physics.photometry import saturated

    model = HoleModel(edge_prob=0.0, blob_density=0.0, physical_signal=True, max_low_signal_fraction=0.0)
    depth = torch.full((16, 64), 1000.0, dtype=torch.float64)
    thr_signal = default_min_amplitude_e(CALIB) / CALIB.tap_response.first_harmonic_amplitude
    signal = torch.logspace(math.log10(thr_signal / 4), math.log10(2e5), 64, dtype=torch.float64).expand(16, 64)
    valid = torch.ones_like(depth, dtype=torch.bool)
    holes = model.sample(depth, signal.clone(), valid, CALIB, gen(1))
    sat = torch.from_numpy(saturated(depth.numpy(), signal.numpy(), CALIB))
    assert sat.any() and bool(holes[sat].all())  # every saturated pixel is a hole
    assert float(holes[:, :3].double().mean()) > 0.95  # a quarter of the threshold: always below
    middle = (signal > 4 * thr_signal) & ~sat
    assert not holes[middle].any()  # well above the threshold and below the full well: never
    # the darkened-frame mechanism is off: a zero target fraction would give no low-signal holes at all
    assert (
        not HoleModel(edge_prob=0.0, blob_density=0.0, max_low_signal_fraction=0.0)
        .sample(depth, signal.clone(), valid, CALIB, gen(1))
        .any()
    )
