"""SS2D's dt projection: the strided-output product (no gradient recorded) equals the autograd form bit for bit,
and both equal the per-direction matrix products."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.ss2d import DT_PROJECTION_FORMS, SS2D, dt_projection


def _per_direction(dt_low: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """out[m, j] = weight[j] @ dt_low[m, j], written out direction by direction in float64."""
    return torch.stack([dt_low[:, j].double() @ weight[j].double().t() for j in range(weight.size(0))], dim=1)


@pytest.mark.parametrize("m,k,r,d", [(1, 4, 1, 3), (37, 4, 2, 64), (150, 4, 5, 20), (9, 2, 3, 7)])
def test_dt_projection_without_gradient_equals_the_autograd_form(m, k, r, d):
    torch.manual_seed(0)
    # dt_low as SS2D hands it over: a strided slice of the x_proj output (r of r + 2 N columns)
    x_dbl = torch.randn(m, k, r + 6)
    weight = torch.randn(k, d, r)
    with torch.no_grad():
        fast = dt_projection(x_dbl[..., :r], weight)
    slow = dt_projection(x_dbl[..., :r], weight.clone().requires_grad_())
    assert fast.shape == slow.shape == (m, k, d)
    assert fast.is_contiguous() and slow.is_contiguous()
    assert torch.equal(fast, slow.detach())
    torch.testing.assert_close(fast.double(), _per_direction(x_dbl[..., :r], weight), rtol=1e-5, atol=1e-5)


def test_dt_projection_gradients_are_the_per_direction_products():
    torch.manual_seed(1)
    dt_low = torch.randn(23, 4, 3, requires_grad=True)
    weight = torch.randn(4, 11, 3, requires_grad=True)
    g = torch.randn(23, 4, 11)
    (dt_projection(dt_low, weight) * g).sum().backward()
    # d/d dt_low[m, j] = weight[j]^T g[m, j]; d/d weight[j] = sum_m g[m, j] dt_low[m, j]^T
    want_dlow = torch.einsum("mjd,jdr->mjr", g.double(), weight.detach().double())
    want_dw = torch.einsum("mjd,mjr->jdr", g.double(), dt_low.detach().double())
    torch.testing.assert_close(dt_low.grad.double(), want_dlow, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(weight.grad.double(), want_dw, rtol=1e-5, atol=1e-5)


def test_ss2d_block_gives_the_same_output_with_and_without_autograd():
    """Inference (no_grad: the kernel's inference path -- the dt projection in the kernel, its exp2, the fused output
    stage) and training (autograd: product, copy, the operator) run one block to the same numbers, to rounding."""
    torch.manual_seed(2)
    block = SS2D(12, d_state=4)
    x = torch.randn(2, 7, 9, 12)
    with torch.no_grad():
        y_inference = block(x)
    y_training = block(x.clone().requires_grad_())
    torch.testing.assert_close(y_inference, y_training.detach(), rtol=2e-6, atol=2e-6)


def test_dt_projection_under_bf16_autocast_without_gradient():
    """Inference under autocast (as ``denoise`` and the GPU profiles run DVSS): x_proj's output is bf16 and the
    weight float32; autocast does not cast ``out=`` products, so the projection takes autocast's product and gives
    what the autograd form gives under the same autocast."""
    torch.manual_seed(3)
    weight = torch.randn(4, 11, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        x_dbl = torch.randn(23, 4, 3 + 8) @ torch.eye(11)  # bf16 under autocast, as SS2D's x_proj output
        assert x_dbl.dtype == torch.bfloat16
        with torch.no_grad():
            fast = dt_projection(x_dbl[..., :3], weight)
        slow = dt_projection(x_dbl[..., :3], weight.clone().requires_grad_())
    assert fast.shape == (23, 4, 11) and fast.is_contiguous()
    assert torch.equal(fast, slow.detach())


@pytest.mark.parametrize("form", DT_PROJECTION_FORMS)
@pytest.mark.parametrize("m", [128, 23])  # 23: no split (gcd 1)
def test_dt_projection_forms_give_the_products_and_their_gradients(form, m):
    """Every form of the projection gives the per-direction products and the same gradients (the split form's
    weight gradient is a sum over batches of positions: equal to rounding)."""
    torch.manual_seed(4)
    x_dbl = torch.randn(m, 4, 3 + 6, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(4, 11, 3, dtype=torch.float64, requires_grad=True)
    g = torch.randn(m, 4, 11, dtype=torch.float64)
    out = dt_projection(x_dbl[..., :3], weight, form=form)
    assert out.shape == (m, 4, 11) and out.is_contiguous()
    torch.testing.assert_close(out, _per_direction(x_dbl[..., :3], weight), rtol=1e-12, atol=1e-12)
    got = torch.autograd.grad((out * g).sum(), [x_dbl, weight])
    ref = torch.autograd.grad((dt_projection(x_dbl[..., :3], weight, form="bmm") * g).sum(), [x_dbl, weight])
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="form must be one of"):
        dt_projection(x_dbl[..., :3], weight, form="nope")


def _fills(fn, shape) -> int:
    """How many zero-fills of a tensor of ``shape`` ``fn`` runs."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True) as prof:
        fn()
    return sum(1 for e in prof.events() if e.name in ("aten::fill_", "aten::zero_") and list(shape) in e.input_shapes)


def test_ss2d_training_backward_zero_fills_no_whole_x_proj_output():
    """The x_proj output's gradient is assembled once from its three parts (dt, B, C), not from a zero-filled
    tensor per part; the native kernel's checkpoints get no zero-filled gradient either."""
    torch.manual_seed(0)
    block = SS2D(8, d_state=4)
    x = torch.randn(2, 6, 5, 8)
    (2 * block(x)).sum().backward()  # warm-up (builds the kernel)
    shape = (2, 30, 4, block.dt_rank + 2 * block.d_state)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True) as prof:
        (2 * block(x)).sum().backward()
    fills = [
        list(e.input_shapes[0]) for e in prof.events() if e.name in ("aten::fill_", "aten::zero_") and e.input_shapes
    ]
    assert list(shape) not in fills
    assert not [f for f in fills if len(f) == 6]  # (b, blocks, 4, chunks, N, lanes): the checkpoints


def test_ss2d_training_takes_the_fused_dt_projection_and_matches_the_product_route(monkeypatch):
    """Training on the native kernel takes ``tofdenoise::ss2d_scan_lowrank`` (the dt projection inside the scan's
    forward and backward: no batched product); with ``FUSE_DT_TRAINING`` off it takes the product and
    ``tofdenoise::ss2d_scan``. The two give the same output bit for bit and the same parameter gradients to
    rounding."""
    from tofdenoise.models import ss2d as ss2d_mod
    from tofdenoise.models.scan.cpu import cpu_kernel_available

    if not cpu_kernel_available():
        pytest.skip("native CPU scan not available")
    torch.manual_seed(3)
    block = SS2D(20, d_state=16)  # d_inner 40: a full and a partial block of lanes; dt_rank 2
    x = torch.randn(2, 7, 5, 20)
    runs = {}
    for fused in (True, False):
        monkeypatch.setattr(ss2d_mod, "FUSE_DT_TRAINING", fused)
        block.zero_grad()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            y = block(x)
            (y * torch.linspace(-1, 1, y.numel()).view_as(y)).sum().backward()
        names = {e.name for e in prof.events()}
        assert ("tofdenoise::ss2d_scan_lowrank" in names) is fused
        assert ("aten::bmm" in names) is not fused
        runs[fused] = (y.detach(), {n: p.grad.clone() for n, p in block.named_parameters()})
    assert torch.equal(runs[True][0], runs[False][0])
    for name, grad in runs[False][1].items():
        err = ((runs[True][1][name] - grad).abs().max() / grad.abs().max().clamp_min(1e-30)).item()
        assert err < 1e-5, name
