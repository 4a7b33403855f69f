"""Depth metrics: hand-computed cases, masking, per-image vs pooled averaging, torchmetrics agreement."""

from __future__ import annotations

import math

import pytest
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from tofdenoise.training.metrics import (
    METRIC_KEYS,
    DepthMetrics,
    depth_metrics_per_image,
    gaussian_window_1d,
    masked_ssim_map,
    psnr_from_mse_db,
    valid_pixel_mask,
)

C1 = (0.01 * 1000.0) ** 2
C2 = (0.03 * 1000.0) ** 2


def _scene(b: int = 2, h: int = 24, w: int = 32, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    base = 800.0 + 3.0 * xx + 2.0 * yy
    return (base + 20.0 * torch.rand(b, 1, h, w, generator=g)).to(torch.float32)


def test_metric_keys_contract():
    assert METRIC_KEYS == ("psnr_db", "mae_mm", "mse_mm2", "ssim")


def test_psnr_of_known_mse_constant_offset():
    ref = _scene(1)
    pred = ref + 10.0  # MSE = 100 mm^2 -> PSNR = 10 log10(1e6 / 100) = 40 dB
    m = depth_metrics_per_image(pred, ref, torch.ones_like(ref))
    assert m["mse_mm2"].item() == pytest.approx(100.0, rel=1e-5)
    assert m["mae_mm"].item() == pytest.approx(10.0, rel=1e-5)
    assert m["psnr_db"].item() == pytest.approx(40.0, abs=1e-5)
    assert m["psnr_db"].dtype == torch.float64


def test_psnr_is_not_clamped_for_large_errors():
    ref = torch.full((1, 1, 8, 8), 500.0)
    pred = ref + 5000.0  # MSE 2.5e7 -> 10 log10(1e6 / 2.5e7) = -13.979 dB
    m = depth_metrics_per_image(pred, ref, None)
    assert m["psnr_db"].item() == pytest.approx(10 * math.log10(1e6 / 2.5e7), abs=1e-9)
    assert psnr_from_mse_db(torch.tensor(0.0)).item() == math.inf


def test_checkerboard_error_mae_and_mse():
    ref = torch.full((1, 1, 6, 6), 1000.0)
    sign = (torch.arange(6)[:, None] + torch.arange(6)[None, :]) % 2 * 2 - 1
    pred = ref + 3.0 * sign
    m = depth_metrics_per_image(pred, ref, torch.ones_like(ref))
    assert m["mae_mm"].item() == pytest.approx(3.0)
    assert m["mse_mm2"].item() == pytest.approx(9.0)


def test_ssim_identical_images_is_one_even_with_mask():
    ref = _scene(3)
    mask = torch.ones_like(ref)
    mask[:, :, 5:12, 7:20] = 0
    m = depth_metrics_per_image(ref.clone(), ref, mask)
    assert torch.allclose(m["ssim"], torch.ones(3, dtype=torch.float64), atol=1e-12)


def test_ssim_constant_images_closed_form_with_garbage_in_masked_pixels():
    # constant a vs constant b: variances and covariance vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    a, b = 900.0, 700.0
    pred = torch.full((1, 1, 16, 16), a)
    ref = torch.full((1, 1, 16, 16), b)
    mask = torch.ones_like(ref)
    mask[..., 3:9, 4:10] = 0
    pred[..., 3:9, 4:10] = torch.nan
    ref[..., 3:9, 4:10] = 1e9
    m = depth_metrics_per_image(pred, ref, mask)
    assert m["ssim"].item() == pytest.approx((2 * a * b + C1) / (a * a + b * b + C1), rel=1e-12)
    assert m["mae_mm"].item() == pytest.approx(200.0)


def test_ssim_matches_torchmetrics_on_fully_valid_images():
    ref = _scene(2, 30, 41).double()
    g = torch.Generator().manual_seed(3)
    pred = ref + 15.0 * torch.randn(ref.shape, generator=g, dtype=torch.float64)
    ours = depth_metrics_per_image(pred, ref, torch.ones_like(ref))["ssim"]
    theirs = structural_similarity_index_measure(pred, ref, data_range=1000.0, reduction="none")
    assert torch.allclose(ours, theirs, rtol=0, atol=1e-10)
    assert 0.0 < ours.min() < 1.0


def test_gaussian_window_is_11_taps_normalised():
    g = gaussian_window_1d(1.5)
    assert g.numel() == 11
    assert g.sum().item() == pytest.approx(1.0)
    assert g[5] == g.max()


def test_masked_pixels_do_not_change_any_metric():
    ref = _scene(2)
    g = torch.Generator().manual_seed(5)
    pred = ref + 8.0 * torch.randn(ref.shape, generator=g)
    mask = torch.ones_like(ref)
    mask[:, :, :, :6] = 0
    mask[1, :, 10:14, 10:25] = 0
    results = []
    for garbage_pred, garbage_ref in ((0.0, 0.0), (torch.nan, 5e6), (-1e7, torch.inf)):
        p, r = pred.clone(), ref.clone()
        p[mask == 0] = garbage_pred
        r[mask == 0] = garbage_ref
        results.append(depth_metrics_per_image(p, r, mask))
    for other in results[1:]:
        for k in METRIC_KEYS:
            assert torch.allclose(results[0][k], other[k], rtol=0, atol=1e-12), k


def test_validity_rules_reference_zero_or_nonfinite_and_prediction_nonfinite():
    ref = torch.tensor([[[[1000.0, 0.0], [torch.nan, 1000.0]]]])
    pred = torch.tensor([[[[1010.0, 5.0], [7.0, torch.inf]]]])
    valid = valid_pixel_mask(ref, None, pred)
    assert valid.tolist() == [[[[True, False], [False, False]]]]
    m = depth_metrics_per_image(pred, ref, None)
    assert m["valid_px"].item() == 1
    assert m["mae_mm"].item() == pytest.approx(10.0)


def test_per_image_average_differs_from_pixel_pooled_as_expected():
    ref = torch.full((2, 1, 10, 10), 1000.0)
    pred = ref.clone()
    pred[0] += 1.0  # 100 valid pixels, error 1 mm
    pred[1] += 10.0  # 1 valid pixel, error 10 mm
    mask = torch.ones_like(ref)
    mask[1] = 0
    mask[1, 0, 4, 4] = 1
    metric = DepthMetrics()
    metric.update(pred, ref, mask, index=torch.tensor([0, 1]))
    out = metric.compute()
    assert out["mae_mm"].item() == pytest.approx((1.0 + 10.0) / 2)
    assert out["mae_mm_pooled"].item() == pytest.approx((100 * 1.0 + 10.0) / 101)
    assert out["mse_mm2"].item() == pytest.approx((1.0 + 100.0) / 2)
    assert out["psnr_db"].item() == pytest.approx((60.0 + 40.0) / 2)  # mean of per-image PSNRs
    assert metric.counts() == {"images": 2, "skipped_images": 0, "valid_px": 101}


def test_image_without_valid_pixel_is_skipped_and_counted():
    ref = torch.full((3, 1, 8, 8), 1000.0)
    pred = ref + torch.tensor([2.0, 50.0, 4.0]).view(3, 1, 1, 1)
    mask = torch.ones_like(ref)
    mask[1] = 0
    per = depth_metrics_per_image(pred, ref, mask)
    assert torch.isnan(per["mae_mm"][1]) and per["valid_px"][1] == 0
    metric = DepthMetrics()
    metric.update(pred, ref, mask, index=torch.tensor([7, 8, 9]))
    out = metric.compute()
    assert out["mae_mm"].item() == pytest.approx(3.0)
    assert metric.counts()["skipped_images"] == 1
    rows = metric.per_image_rows()
    assert [r["index"] for r in rows] == [7, 8, 9]
    assert rows[1]["valid_px"] == 0 and math.isnan(rows[1]["mae_mm"])


def test_accumulation_over_batches_equals_one_batch_and_rows_sorted():
    ref = _scene(4)
    g = torch.Generator().manual_seed(9)
    pred = ref + 6.0 * torch.randn(ref.shape, generator=g)
    mask = (torch.rand(ref.shape, generator=g) > 0.2).float()
    whole = DepthMetrics()
    whole.update(pred, ref, mask, index=torch.arange(4))
    parts = DepthMetrics()
    parts.update(pred[2:], ref[2:], mask[2:], index=torch.arange(2, 4))
    parts.update(pred[:2], ref[:2], mask[:2], index=torch.arange(0, 2))
    a, b = whole.compute(), parts.compute()
    for k in a:
        assert a[k].item() == pytest.approx(b[k].item(), rel=1e-12)
    rows = parts.per_image_rows()
    assert [r["index"] for r in rows] == [0, 1, 2, 3]
    per = depth_metrics_per_image(pred, ref, mask)
    for i, r in enumerate(rows):
        for k in METRIC_KEYS:
            assert r[k] == pytest.approx(per[k][i].item(), rel=1e-12)
    parts.reset()
    assert parts.per_image_rows() == []
    with pytest.warns(UserWarning, match="before the ``update``"):
        assert math.isnan(parts.compute()["mae_mm"].item())


def test_ssim_independent_of_batch_composition():
    ref = _scene(3)
    pred = ref + 5.0 * torch.randn(ref.shape)
    pred[2] = pred[2] * 0.1  # an outlier image must not change the others (fixed data range)
    alone = depth_metrics_per_image(pred[:1], ref[:1], None)["ssim"]
    batch = depth_metrics_per_image(pred, ref, None)["ssim"]
    assert alone.item() == pytest.approx(batch[0].item(), rel=1e-12)


def test_masked_ssim_map_uses_only_valid_neighbours():
    # left half valid at 1000/1000, right half garbage: the SSIM map at valid pixels is exactly 1
    ref = torch.full((1, 1, 12, 12), 1000.0, dtype=torch.float64)
    pred = ref.clone()
    valid = torch.zeros_like(ref, dtype=torch.bool)
    valid[..., :6] = True
    pred[..., 6:] = 3.0
    smap = masked_ssim_map(pred, ref, valid)
    assert torch.allclose(smap[valid], torch.ones(72, dtype=torch.float64))
    assert torch.isnan(smap[~valid]).all()


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match="pred_mm shape"):
        depth_metrics_per_image(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 5), None)
    with pytest.raises(ValueError, match="expected shape"):
        depth_metrics_per_image(torch.ones(1, 3, 4, 4), torch.ones(1, 3, 4, 4), None)
    with pytest.raises(ValueError, match="index has"):
        DepthMetrics().update(torch.ones(2, 1, 4, 4), torch.ones(2, 1, 4, 4), None, index=torch.tensor([1]))


_DDP_SCRIPT = r"""
import json, os, sys
import torch
import torch.distributed as dist

def run(rank, world, port, out):
    os.environ["MASTER_ADDR"] = "127.0.0.1"
    os.environ["MASTER_PORT"] = str(port)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    from tofdenoise.training.metrics import DepthMetrics
    ref = torch.full((2, 1, 8, 8), 1000.0)
    # rank 0 sees images 0, 1 (errors 1, 2 mm); rank 1 sees images 2, 3 (errors 3, 4 mm), image 3 has 1 pixel
    err = torch.tensor([1.0, 2.0]) + 2 * rank
    pred = ref + err.view(2, 1, 1, 1)
    mask = torch.ones_like(ref)
    if rank == 1:
        mask[1] = 0
        mask[1, 0, 0, 0] = 1
    m = DepthMetrics()
    m.update(pred, ref, mask, index=torch.arange(2) + 2 * rank)
    res = {k: float(v) for k, v in m.compute().items()}
    rows = m.per_image_rows()
    if rank == 0:
        with open(out, "w") as f:
            json.dump({"res": res, "rows": rows}, f)
    dist.destroy_process_group()

if __name__ == "__main__":
    run(int(sys.argv[1]), 2, int(sys.argv[2]), sys.argv[3])
"""


def test_depth_metrics_sync_across_two_ddp_processes(tmp_path):
    import json
    import socket
    import subprocess
    import sys

    script = tmp_path / "ddp_metrics.py"
    script.write_text(_DDP_SCRIPT)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "out.json"
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(rank), str(port), str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for rank in (0, 1)
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-3000:]
    data = json.loads(out.read_text())
    assert data["res"]["mae_mm"] == pytest.approx((1 + 2 + 3 + 4) / 4)
    assert data["res"]["mae_mm_pooled"] == pytest.approx((64 * (1 + 2 + 3) + 4) / (3 * 64 + 1))
    assert [r["index"] for r in data["rows"]] == [0, 1, 2, 3]
    assert [r["valid_px"] for r in data["rows"]] == [64, 64, 64, 1]


def _padded_image(i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Image ``i`` of the padded-sampler tests: its own error level and mask; image 1 has no valid pixel and
    image 2 only a few, so means, pooled MAE and counts all depend on which images are counted."""
    g = torch.Generator().manual_seed(100 + i)
    ref = 900.0 + 50.0 * torch.rand(1, 1, 12, 16, generator=g)
    pred = ref + (2.0 + 3.0 * i) * torch.randn(ref.shape, generator=g)
    mask = (torch.rand(ref.shape, generator=g) > 0.25).float()
    if i == 1:
        mask.zero_()
    if i == 2:
        mask.zero_()
        mask[..., :2, :3] = 1
    return pred, ref, mask


_DDP_PADDED_SCRIPT = r"""
import json, os, sys
import torch
import torch.distributed as dist
from torch.utils.data import DistributedSampler

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from images import padded_image

def run(rank, world, port, out, n, batch):
    os.environ["MASTER_ADDR"] = "127.0.0.1"
    os.environ["MASTER_PORT"] = str(port)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    from tofdenoise.training.metrics import DepthMetrics
    # Lightning's evaluation sampler: DistributedSampler(shuffle=False) pads to a multiple of the world size
    mine = list(DistributedSampler(range(n), num_replicas=world, rank=rank, shuffle=False))
    m = DepthMetrics()
    for k in range(0, len(mine), batch):
        ids = mine[k:k + batch]
        imgs = [padded_image(i) for i in ids]
        pred, ref, mask = (torch.cat([im[j] for im in imgs]) for j in range(3))
        m.update(pred, ref, mask, index=torch.tensor(ids))
    res = {k: float(v) for k, v in m.compute().items()}
    counts = m.counts()
    rows = m.per_image_rows()
    try:
        m.update(pred, ref, mask)
        no_index = "accepted"
    except ValueError as exc:
        no_index = str(exc)
    with open(f"{out}.{rank}", "w") as f:
        json.dump({"mine": mine, "res": res, "counts": counts, "rows": rows, "no_index": no_index}, f)
    dist.destroy_process_group()

if __name__ == "__main__":
    run(int(sys.argv[1]), 2, int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
"""


def _run_two_gloo_processes(tmp_path, script_text: str, extra: list[str]) -> list[dict]:
    import inspect
    import json
    import socket
    import subprocess
    import sys

    script = tmp_path / "ddp_metrics.py"
    script.write_text(script_text)
    (tmp_path / "images.py").write_text(
        "import torch\n\n" + inspect.getsource(_padded_image).replace("_padded_image", "padded_image")
    )
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "out.json"
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(rank), str(port), str(out), *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for rank in (0, 1)
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-3000:]
    return [json.loads((tmp_path / f"out.json.{rank}").read_text()) for rank in (0, 1)]


@pytest.mark.parametrize("n, batch", [(3, 1), (5, 2)])
def test_depth_metrics_under_ddp_count_padded_repeats_once(tmp_path, n, batch):
    """Two gloo processes, an odd number of images, Lightning's DistributedSampler (it repeats image 0 to
    pad): compute(), counts() and the rows equal the single-process results over the n unique images, on
    both ranks, to the last bit. Before the fix the repeated image was counted twice in the means and counts."""
    ranks = _run_two_gloo_processes(tmp_path, _DDP_PADDED_SCRIPT, [str(n), str(batch)])
    seen = ranks[0]["mine"] + ranks[1]["mine"]
    assert sorted(seen) == sorted(list(range(n)) + [0])  # the sampler really padded with a repeat of image 0
    single = DepthMetrics()
    for i in range(n):
        single.update(*_padded_image(i), index=torch.tensor([i]))
    want = {k: float(v) for k, v in single.compute().items()}
    want_counts = single.counts()
    assert want_counts == {
        "images": n - 1,
        "skipped_images": 1,
        "valid_px": sum(int(_padded_image(i)[2].sum()) for i in range(n)),
    }
    # hand check of the per-image mean and the pooled MAE from the single-process rows
    rows = single.per_image_rows()
    ok = [r for r in rows if r["valid_px"] > 0]
    assert want["mae_mm"] == pytest.approx(sum(r["mae_mm"] for r in ok) / (n - 1), rel=1e-12)
    assert want["mae_mm_pooled"] == pytest.approx(
        sum(r["mae_mm"] * r["valid_px"] for r in ok) / sum(r["valid_px"] for r in ok), rel=1e-12
    )
    for rank in ranks:
        assert rank["res"] == want  # bit-identical: same per-image values summed in the same (index) order
        assert rank["counts"] == want_counts
        assert [r["index"] for r in rank["rows"]] == list(range(n))
        assert json_rows_equal(rank["rows"], rows)
        # an update without index cannot be de-duplicated: refused under DDP with a clear message
        assert "index is required with 2 distributed processes" in rank["no_index"]


def json_rows_equal(a: list[dict], b: list[dict]) -> bool:
    """Per-image rows equal, NaN == NaN (a skipped image has NaN metrics)."""

    def norm(rows):
        return [{k: ("nan" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()} for r in rows]

    return norm(a) == norm(b)


def test_repeated_index_counts_once_and_rows_without_index_all_count():
    pred, ref, mask = (torch.cat(t) for t in zip(*[_padded_image(i) for i in (0, 3)]))
    once = DepthMetrics()
    once.update(pred, ref, mask, index=torch.tensor([0, 3]))
    twice = DepthMetrics()
    twice.update(pred, ref, mask, index=torch.tensor([0, 3]))
    twice.update(pred[:1], ref[:1], mask[:1], index=torch.tensor([0]))  # a padded repeat
    assert {k: float(v) for k, v in twice.compute().items()} == {k: float(v) for k, v in once.compute().items()}
    assert twice.counts() == once.counts() and len(twice.per_image_rows()) == 2
    # one process without indices: every row counts (nothing can be told apart), rows keep index None
    anon = DepthMetrics()
    anon.update(pred, ref, mask)
    anon.update(pred[:1], ref[:1], mask[:1])
    assert anon.counts()["images"] == 3
    assert [r["index"] for r in anon.per_image_rows()] == [None, None, None]
    with pytest.raises(ValueError, match="non-negative whole numbers"):
        DepthMetrics().update(pred, ref, mask, index=torch.tensor([0.5, 1.0]))


@pytest.mark.gpu
def test_metrics_on_cuda_match_cpu():
    ref = _scene(2)
    pred = ref + 7.0 * torch.randn(ref.shape)
    mask = (torch.rand(ref.shape) > 0.2).float()
    cpu = DepthMetrics()
    cpu.update(pred, ref, mask, index=torch.arange(2))
    gpu = DepthMetrics().to("cuda")
    gpu.update(pred.cuda(), ref.cuda(), mask.cuda(), index=torch.arange(2, device="cuda"))
    a, b = cpu.compute(), gpu.compute()
    for k in a:
        assert b[k].device.type == "cuda"
        assert a[k].item() == pytest.approx(b[k].item(), rel=1e-9)
    # per-image values agree to float64 round-off (CUDA reduces in another order: SSIM differed by 1.5e-15
    # on an H100)
    rows_gpu, rows_cpu = gpu.per_image_rows(), cpu.per_image_rows()
    assert len(rows_gpu) == len(rows_cpu)
    for rg, rc in zip(rows_gpu, rows_cpu):
        assert rg.keys() == rc.keys() and rg["index"] == rc["index"] and rg["valid_px"] == rc["valid_px"]
        assert all(rg[k] == pytest.approx(rc[k], rel=1e-12) for k in rg)


def test_depth_edge_mask_marks_both_sides_of_a_step_not_holes_or_the_border():
    """A 100 mm step between columns 2 and 3 marks columns 2 and 3 (8-neighbourhood); a 40 mm step does not at
    the default 50 mm; a hole (reference 0) next to a surface makes no edge, nor does the image border; a NaN
    reference is never an edge pixel."""
    from tofdenoise.training.metrics import EDGE_JUMP_MM, depth_edge_mask

    assert EDGE_JUMP_MM == 50.0
    ref = torch.full((6, 8), 1000.0)
    ref[:, 3:] = 1100.0
    ref[:, 6:] = 1140.0  # a 40 mm step: below the default jump
    ref[0, 0] = 0.0  # a hole
    ref[5, 7] = float("nan")
    edge = depth_edge_mask(ref)
    assert edge.shape == (1, 1, 6, 8) and edge.dtype == torch.bool
    expected = torch.zeros(6, 8, dtype=torch.bool)
    expected[:, 2:4] = True
    assert torch.equal(edge[0, 0], expected)
    # the 40 mm step counts at a 30 mm jump; a diagonal neighbour counts as much as a side one
    assert torch.equal(depth_edge_mask(ref, 30.0)[0, 0, :5, 5:7], torch.ones(5, 2, dtype=torch.bool))
    diagonal = torch.full((3, 3), 500.0)
    diagonal[0, 0] = 900.0
    marked = depth_edge_mask(diagonal)[0, 0]
    assert marked[0, 0] and marked[1, 1] and marked.sum() == 4  # (0,0) and its three neighbours
    with pytest.raises(ValueError, match="jump_mm must be > 0"):
        depth_edge_mask(ref, 0.0)
