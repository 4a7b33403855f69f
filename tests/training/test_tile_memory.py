"""Whole frame or tiles: the activation bytes counted on a probe, the memory budget, the plan, and restore_frame
and predict_step running a frame whole unless it does not fit (or --tile forces tiles)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import tofdenoise.training.module as module_module
from tofdenoise.inference.denoise import frame_tile_plan, load_restorer, restore_frame
from tofdenoise.training.tile_memory import (
    MIN_TILE_PX,
    PROBE_PX,
    SAFETY,
    TilePlan,
    activation_bytes_per_px,
    memory_budget_bytes,
    peak_tensor_bytes,
    tile_plan,
)


def test_peak_tensor_bytes_counts_what_is_alive_at_once():
    x = torch.zeros(1000)  # the input is not counted

    def three_steps(t):
        a = t * 2  # 4000 B alive
        b = a + 1  # 8000 B alive: the peak
        view = b.view(10, 100)  # a view adds nothing
        del a
        c = view * 3  # b and c: 8000 B again
        return c

    assert peak_tensor_bytes(three_steps, x) == 8000

    def one_at_a_time(t):
        for _ in range(5):
            t = t + 1  # each result frees the one before (the input stays)
        return t

    assert peak_tensor_bytes(one_at_a_time, x) == 8000


def test_the_probe_scales_to_a_larger_frame(restorer_ckpt):
    model = load_restorer(restorer_ckpt)
    per_px = activation_bytes_per_px(model.eval_net, 1, torch.device("cpu"), "fp32", torch.no_grad())
    assert per_px > 0
    full = peak_tensor_bytes(model.eval_net, torch.zeros(1, 1, 4 * PROBE_PX, 3 * PROBE_PX))
    assert per_px * 12 * PROBE_PX**2 == pytest.approx(full, rel=0.05)
    budget = memory_budget_bytes(torch.device("cpu"))
    assert budget is None or budget > 0


def test_tile_plan_tiles_only_what_does_not_fit_or_what_is_forced():
    per_px, budget = (lambda: 100.0), (lambda: 100.0 * 700 * 700 * SAFETY)
    assert tile_plan((576, 640), None, 512, per_px, budget) == TilePlan(
        None, need_bytes=100.0 * 576 * 640 * SAFETY, budget_bytes=budget()
    )
    big = tile_plan((1200, 1600), None, 512, per_px, budget)
    assert big.tile == 512 and big.tiled and not big.forced and big.need_bytes > big.budget_bytes
    # a budget that not even the checkpoint's tile fits: halved until a tile fits, down to MIN_TILE_PX
    assert tile_plan((1200, 1600), None, 512, per_px, lambda: 100.0 * 200 * 200 * SAFETY).tile == 128
    assert tile_plan((1200, 1600), None, 512, per_px, lambda: 1.0).tile == MIN_TILE_PX
    # ... and never below the smallest tile the network's overlap and padding multiple allow (models.tiling.min_tile_px)
    assert tile_plan((1200, 1600), None, 512, per_px, lambda: 1.0, min_tile=96).tile == 96
    # forced: tiles whenever a side exceeds it, without measuring
    never = lambda: pytest.fail("not measured when --tile forces tiles")  # noqa: E731
    assert tile_plan((576, 640), 512, 512, never, never) == TilePlan(512, forced=True)
    assert tile_plan((400, 500), 512, 512, never, never) == TilePlan(None, forced=True)
    # an unknown budget fits; a checkpoint that never tiles runs whole
    assert not tile_plan((5000, 5000), None, 512, per_px, lambda: None).tiled
    assert tile_plan((5000, 5000), None, None, never, never) == TilePlan(None)


def test_restore_frame_runs_a_frame_whole_unless_it_does_not_fit(tmp_path, make_restorer_ckpt, monkeypatch):
    """A frame larger than the checkpoint's tile runs whole when it fits the budget (faster, and exactly the whole
    frame's restoration); it runs in the checkpoint's tiles when it does not, or in --tile's when forced."""
    ckpt = make_restorer_ckpt(tmp_path / "t.ckpt", tiling={"predict_tile_px": 64, "overlap_px": 16})
    model = load_restorer(ckpt)
    torch.manual_seed(0)
    with torch.no_grad():  # weights away from the initialisation (whose zero output layer hides the seams)
        for param in model.parameters():
            param.add_(0.2 * torch.randn_like(param))
    y, x = np.mgrid[0:80, 0:100]
    depth = (900 + 3 * x + 2 * y + np.random.default_rng(0).normal(0, 5, (80, 100))).astype(np.float32)
    valid = np.ones(depth.shape, bool)
    batch = {"noisy": torch.from_numpy(depth)[None, None], "mask": torch.ones(1, 1, 80, 100)}
    with torch.no_grad():
        whole = model.restore_mm(batch, tile=None)[0, 0].numpy()
        tiled = model.restore_mm(batch, tile=64)[0, 0].numpy()
    assert not np.array_equal(whole, tiled)  # the two differ: the test tells them apart
    plan = frame_tile_plan(model, depth.shape)
    assert not plan.tiled and plan.need_bytes < plan.budget_bytes
    np.testing.assert_array_equal(restore_frame(model, depth, valid), whole)
    np.testing.assert_array_equal(restore_frame(model, depth, valid, tile=64), tiled)
    monkeypatch.setattr(module_module, "memory_budget_bytes", lambda device: 1.0)
    assert frame_tile_plan(model, depth.shape).tile == 64
    np.testing.assert_array_equal(restore_frame(model, depth, valid), tiled)


def test_predict_step_runs_the_batch_whole_unless_it_does_not_fit(tmp_path, make_restorer_ckpt, monkeypatch):
    """LightningCLI predict restores as tofdenoise denoise does: whole when the batch fits, else the checkpoint's
    tiles (the batch's frames counted together)."""
    model = load_restorer(make_restorer_ckpt(tmp_path / "t.ckpt", tiling={"predict_tile_px": 64, "overlap_px": 16}))
    torch.manual_seed(1)
    with torch.no_grad():
        for param in model.parameters():
            param.add_(0.2 * torch.randn_like(param))
    noisy = 900 + 100 * torch.rand(2, 1, 72, 90)
    batch = {"noisy": noisy, "mask": torch.ones_like(noisy)}
    with torch.no_grad():
        whole = model.restore_mm(batch, tile=None)
        tiled = model.restore_mm(batch, tile=64)
        assert not torch.equal(whole, tiled)
        torch.testing.assert_close(model.predict_step(batch, 0), whole, rtol=0, atol=0)
        per_px = activation_bytes_per_px(model.eval_net, 1, torch.device("cpu"), "fp32", torch.no_grad())
        one_frame = per_px * 72 * 90 * SAFETY
        # a budget that holds one frame but not the batch of two: tiles
        monkeypatch.setattr(module_module, "memory_budget_bytes", lambda device: 1.5 * one_frame)
        assert model.predict_tile_plan((1, 1, 72, 90)).tile is None
        assert model.predict_tile_plan((2, 1, 72, 90)).tile == 64
        torch.testing.assert_close(model.predict_step(batch, 0), tiled, rtol=0, atol=0)
