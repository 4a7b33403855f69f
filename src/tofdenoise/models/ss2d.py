"""SS2D: the 2-D selective-scan module (the paper's VSSB, after VMamba / MambaIR)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .common import eager_inference, pointwise
from .scan import cross_merge, cross_scan, resolve_scan_backend, selective_scan
from .scan.cpu import LOWRANK_MAX_RANK, ss2d_forward_lowrank, ss2d_out_gate, ss2d_scan_cpu

__all__ = ["SS2D", "cross_scan", "cross_merge", "dt_projection", "DT_PROJECTION_FORMS"]

#: the forms of the dt projection: "bmm" (one product batched over the directions), "split" (the same product with
#: the positions cut into up to 64 batches, so that the weight gradient's reduction over all positions is spread
#: over many products and summed after), "sum" (dt_rank broadcast multiply-adds, no matrix product), "blockdiag" (one
#: plain product of the (M, k r) steps with the (k r, k d) block-diagonal weight: k times the arithmetic, but the
#: weight gradient is one plain ``mm`` over all positions, the kind that took 0.06-0.08 ms on an H200 where the
#: batched one took 5.2 ms)
DT_PROJECTION_FORMS = ("bmm", "split", "sum", "blockdiag")
#: the form used on CUDA tensors (the CPU always takes "bmm": its training numbers stay bit for bit those of the
#: records). On an H200 the "bmm" form's weight gradient at the first level is a bf16 GEMM of 5.2 ms, twice a DVSS
#: step (docs/benchmarks.md, 2026-11-28); ``benchmarks/bench_gpu_scan.py --only dt_forms`` times every form
DT_PROJECTION_CUDA = "bmm"
#: training on the native CPU kernel: the dt projection fused into the scan's forward and backward
#: (``tofdenoise::ss2d_scan_lowrank``) -- no (b, L, 4 d) tensor of steps, of their gradient, or the batched products
#: and copy around them. False takes the batched product and ``tofdenoise::ss2d_scan`` (the route of the records up
#: to 2026-11-28: the same forward bit for bit, gradients of dt_low and the dt weights equal to rounding);
#: ``benchmarks/bench_scan_cpu.py`` times the two side by side
FUSE_DT_TRAINING = True


def _dt_projection_split(lhs: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """lhs (k, M, r) @ rhs (k, r, d) as (k, s, M / s, r) @ (k, 1, r, d) (s = gcd(M, 64)): the forward is the same
    row by row; autograd's gradient of the broadcast weight is s products over M / s positions each, then a sum."""
    k, m, r = lhs.shape
    s = math.gcd(m, 64)
    out = torch.matmul(lhs.reshape(k, s, m // s, r), rhs.unsqueeze(1))
    return out.reshape(k, m, rhs.size(-1))


def _dt_projection_sum(dt_low: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """sum_i dt_low[m, j, i] * weight[j, :, i] as dt_rank broadcast multiply-adds, (M, k, d)."""
    out = dt_low[..., 0:1] * weight[:, :, 0]
    for i in range(1, weight.size(-1)):
        out = out + dt_low[..., i : i + 1] * weight[:, :, i]
    return out


def _dt_projection_blockdiag(dt_low: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """dt_low (M, k, r) @ the block-diagonal (k r, k d) matrix whose j-th block is weight[j]^T, as (M, k, d)."""
    m, k, r = dt_low.shape
    blocks = torch.block_diag(*weight.transpose(1, 2).unbind(0))  # (k r, k d)
    return (dt_low.reshape(m, k * r) @ blocks).view(m, k, weight.size(1))


def dt_projection(dt_low: torch.Tensor, weight: torch.Tensor, form: str | None = None) -> torch.Tensor:
    """The per-direction dt projection of SS2D: dt_low (M, k, r) (any strides) and weight (k, d, r) give
    (M, k, d) contiguous, ``out[m, j] = weight[j] @ dt_low[m, j]`` -- one matrix product batched over the k
    directions (no (k r, k d) block-diagonal matrix).

    Where no gradient is recorded the product is written straight into the (M, k, d) layout the scan reads (a
    batched product with a strided output); with autograd it is computed direction-major and copied, since an
    ``out=`` product records no gradient, and so it is under autocast, which does not cast ``out=`` products.
    The two give the same numbers (tests/models/test_ss2d.py); the copy is the largest one of a DVSS frame
    (docs/benchmarks.md, "Where a DVSS frame's time goes"). ``form`` (default: :data:`DT_PROJECTION_CUDA` on
    CUDA, "bmm" elsewhere) picks one of :data:`DT_PROJECTION_FORMS`; they agree to rounding.
    """
    form = form or (DT_PROJECTION_CUDA if dt_low.is_cuda else "bmm")
    if form not in DT_PROJECTION_FORMS:
        raise ValueError(f"dt_projection: form must be one of {', '.join(DT_PROJECTION_FORMS)}, got {form!r}")
    lhs = dt_low.transpose(0, 1)  # (k, M, r)
    rhs = weight.transpose(1, 2)  # (k, r, d)
    if form == "sum":
        return _dt_projection_sum(dt_low, weight).contiguous()
    if form == "blockdiag":
        return _dt_projection_blockdiag(dt_low, weight)
    if form == "split":
        return _dt_projection_split(lhs, rhs).transpose(0, 1).contiguous()
    records_grad = torch.is_grad_enabled() and (dt_low.requires_grad or weight.requires_grad)
    if records_grad or torch.compiler.is_compiling() or torch.is_autocast_enabled(dt_low.device.type):
        return torch.bmm(lhs, rhs).transpose(0, 1).contiguous()
    out = dt_low.new_empty(dt_low.size(0), weight.size(0), weight.size(1))
    torch.bmm(lhs, rhs, out=out.transpose(0, 1))
    return out


class SS2D(nn.Module):
    """2-D selective scan block on channels-last input (B, H, W, C) -> (B, H, W, C).

    in_proj (C -> 2 d_inner, no bias) splits x / z; x -> depthwise 3x3 conv + SiLU -> 4-direction cross
    scan; per direction x_proj gives (dt, B, C), dt_proj (with bias) + softplus gives delta;
    A = -exp(A_log) with A_log = log(1..N); skip D = 1; the four scans are merged, layer-normalised,
    gated by SiLU(z) and projected back (out_proj, no bias).
    """

    directions = 4

    def __init__(
        self,
        dim: int,
        d_state: int = 16,
        expand: float = 2.0,
        d_conv: int = 3,
        dt_rank: int | None = None,
        dt_min: float = 0.001,
        dt_max: float = 0.1,
        dt_init_floor: float = 1e-4,
        scan_backend: str = "auto",
    ) -> None:
        super().__init__()
        k = self.directions
        self.d_inner = d_inner = int(round(expand * dim))
        self.d_state = d_state
        self.dt_rank = dt_rank = dt_rank if dt_rank is not None else math.ceil(dim / 16)
        self.scan_backend = scan_backend
        self.in_proj = nn.Linear(dim, 2 * d_inner, bias=False)
        self.conv = nn.Conv2d(d_inner, d_inner, d_conv, padding=d_conv // 2, groups=d_inner, bias=True)
        self.x_proj_weight = nn.Parameter(torch.empty(k, dt_rank + 2 * d_state, d_inner))
        bound = d_inner**-0.5
        nn.init.uniform_(self.x_proj_weight, -bound, bound)
        # dt projection: weight ~ U(+-dt_rank^-0.5); bias = softplus^-1(dt), dt log-uniform in [dt_min, dt_max].
        self.dt_projs_weight = nn.Parameter(torch.empty(k, d_inner, dt_rank).uniform_(-(dt_rank**-0.5), dt_rank**-0.5))
        dt = torch.exp(torch.rand(k, d_inner) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min))
        dt = dt.clamp(min=dt_init_floor)
        self.dt_projs_bias = nn.Parameter(dt + torch.log(-torch.expm1(-dt)))
        a_log = torch.log(torch.arange(1, d_state + 1, dtype=torch.float32)).repeat(k * d_inner, 1)
        self.A_logs = nn.Parameter(a_log)
        self.Ds = nn.Parameter(torch.ones(k * d_inner))
        # As in VMamba / MambaIR: A_log and D are usually excluded from weight decay (optimiser hint).
        self.A_logs._no_weight_decay = True  # type: ignore[attr-defined]
        self.Ds._no_weight_decay = True  # type: ignore[attr-defined]
        self.out_norm = nn.LayerNorm(d_inner)
        self.out_proj = nn.Linear(d_inner, dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out_proj(self.gated(x))

    def gated(self, x: torch.Tensor) -> torch.Tensor:
        """The block before out_proj: ``out_norm(scan) * SiLU(z)``, (B, H, W, C) -> (B, H, W, d_inner)."""
        b, h, w, _ = x.shape
        if self._native_inference(x):
            return self._gated_native_inference(x, h, w)
        xz = self.in_proj(x)
        xi, z = xz.chunk(2, dim=-1)
        kernel = self._spatial_scan(xz)
        if kernel:
            # channels-last depthwise conv: xi is read once into NHWC, and the output's (b, h, w, d_inner)
            # view is what the kernel reads (no cross_scan copies)
            xi = xi.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
            xi = F.silu(self.conv(xi)).permute(0, 2, 3, 1)
            y = self._scan_spatial(xi.contiguous(), h, w, kernel)
        else:
            xi = F.silu(self.conv(xi.permute(0, 3, 1, 2).contiguous()))
            y = self._scan_cross(xi, h, w)
        return self.out_norm(y) * F.silu(z)

    def _native_inference(self, x: torch.Tensor) -> bool:
        """True where :meth:`gated` takes the native kernel's inference path: an eager forward without a gradient
        (:func:`~tofdenoise.models.common.eager_inference`), the CPU kernel's route for float32 input, no autocast,
        and the dt projection fusable (:meth:`_fuse_dt_projection`)."""
        return (
            x.dtype == torch.float32
            and eager_inference()
            and not torch.is_autocast_enabled(x.device.type)
            and self._spatial_scan(x) == "cpu"
            and self._fuse_dt_projection(x)
        )

    def _gated_native_inference(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """:meth:`gated` for inference on the native kernel, the same numbers to rounding with fewer passes over
        memory: in_proj as two products (xi and z each contiguous: no copy of xi for the convolution), SiLU in
        place, the dt projection in the scan (:func:`ss2d_forward_lowrank`) and LayerNorm * SiLU(z) in one pass
        (:func:`ss2d_out_gate`)."""
        b, di = x.shape[0], self.d_inner
        xn = x.permute(0, 3, 1, 2)  # NCHW view of channels-last memory
        weight = self.in_proj.weight
        xi = pointwise(xn, weight[:di])  # channels-last
        z = pointwise(xn, weight[di:]).permute(0, 2, 3, 1).reshape(b * h * w, di)
        xi = F.silu(self.conv(xi), inplace=True).permute(0, 2, 3, 1).contiguous()
        y = self._scan_spatial(xi, h, w, "cpu").view(b * h * w, di)
        norm = self.out_norm
        return ss2d_out_gate(y, z, norm.weight, norm.bias, norm.eps).view(b, h, w, di)

    def _spatial_scan(self, x: torch.Tensor) -> str | None:
        """The kernel that reads the four directions in place for this call, or None (the cross_scan route). The
        route is :func:`~tofdenoise.models.scan.resolve_scan_backend`'s (``ss2d=True``): ``"triton"`` (any float
        dtype, so bf16 activations under autocast are read as they are), or ``"cpu"`` for float32 tensors (the
        native kernel's SS2D route is float32); any other route runs on the cross_scan copies."""
        route = resolve_scan_backend(self.scan_backend, x, ss2d=True)
        if route == "triton" or (route == "cpu" and x.dtype == torch.float32):
            return route
        return None

    def _scan_params(self):
        return (
            -torch.exp(self.A_logs.float()),
            self.Ds.float(),
            self.dt_projs_bias.reshape(-1).float(),
        )

    def _scan_cross(self, xi: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """Reference route: cross_scan copies, per-direction projections, one selective_scan call over the
        4 d_inner channels, cross_merge. xi (b, d_inner, h, w) -> (b, h, w, d_inner)."""
        b = xi.shape[0]
        k, n, r, di = self.directions, self.d_state, self.dt_rank, self.d_inner
        xs = cross_scan(xi)  # (b, 4, di, L)
        length = h * w
        x_dbl = torch.einsum("bkdl,kcd->bkcl", xs, self.x_proj_weight)
        dts, Bs, Cs = torch.split(x_dbl, [r, n, n], dim=2)
        dts = torch.einsum("bkrl,kdr->bkdl", dts, self.dt_projs_weight)
        A, D, bias = self._scan_params()
        y = selective_scan(
            xs.reshape(b, k * di, length),
            dts.reshape(b, k * di, length),
            A,
            Bs.contiguous(),
            Cs.contiguous(),
            D,
            delta_bias=bias,
            delta_softplus=True,
            backend=self.scan_backend,
        ).view(b, k, di, length)
        return cross_merge(y, h, w).permute(0, 2, 3, 1)

    def _scan_spatial(self, xs: torch.Tensor, h: int, w: int, kernel: str = "cpu") -> torch.Tensor:
        """Kernel route (``kernel``: "cpu" or "triton") on channels-last activations xs (b, h, w, d_inner),
        the same math as :meth:`_scan_cross`: x_proj and dt_proj are per-position linear maps, applied once in
        row-major order as matrix products (the 4 directions' x_proj weights stacked into one matrix, the dt
        projections as one product batched over the directions); the kernel reads direction k's step l at position
        pi_k(l) and sums the 4 directions' outputs in place of cross_merge."""
        b = xs.shape[0]
        k, n, r, di = self.directions, self.d_state, self.dt_rank, self.d_inner
        length = h * w
        fused = kernel == "cpu" and self._fuse_dt_projection(xs)
        x_weight = self.x_proj_weight.reshape(k * (r + 2 * n), di)
        if fused and eager_inference():  # the per-pixel product on oneDNN (see models.common.pointwise)
            x_dbl = pointwise(xs.view(b, h, w, di).permute(0, 3, 1, 2), x_weight).permute(0, 2, 3, 1)
        else:
            x_dbl = xs.view(b, length, di) @ x_weight.t()
        x_dbl = x_dbl.reshape(b, length, k, r + 2 * n)
        xs = xs.view(b, length, di)
        A, D, bias = self._scan_params()
        # split, not three slices: its backward concatenates the three gradients into one tensor, where slicing's
        # zero-fills a whole x_dbl per slice and adds them up (the same values)
        dt_low, B, C = x_dbl.split((r, n, n), dim=-1)
        if fused:
            # inference: the kernel projects the low-rank steps itself (no (b, L, 4 d) steps tensor)
            y = ss2d_forward_lowrank(xs, dt_low, self.dt_projs_weight.float(), A, B, C, D, bias, h, w)
            return y.view(b, h, w, di)
        if kernel == "cpu" and self._fuse_dt_training(xs):
            # training: the same in the kernel's forward and backward (the custom operator's autograd)
            y, _ = torch.ops.tofdenoise.ss2d_scan_lowrank(xs, dt_low, self.dt_projs_weight, A, B, C, D, bias, h, w)
            return y.view(b, h, w, di)
        dts = dt_projection(dt_low.reshape(b * length, k, r), self.dt_projs_weight).view(b, length, k * di)
        if kernel == "triton":
            from .scan.triton import ss2d_scan_triton as scan
        else:
            scan = ss2d_scan_cpu

        y = scan(xs, dts, A, B, C, D, bias, h, w)
        return y.view(b, h, w, di)

    def _records_grad(self, xs: torch.Tensor) -> bool:
        """Whether autograd records this scan (a gradient for the activations or the projections' weights)."""
        return torch.is_grad_enabled() and (
            xs.requires_grad or any(p.requires_grad for p in (self.x_proj_weight, self.dt_projs_weight))
        )

    def _fuse_dt_training(self, xs: torch.Tensor) -> bool:
        """True where the native kernel's training route takes the dt projection into its forward and backward
        (:data:`FUSE_DT_TRAINING`): a gradient recorded (the operator keeps the backward's checkpoints), float32
        activations and weights, dt_rank within the kernel's bound (traced by torch.compile too: the operator has a
        fake implementation)."""
        return (
            FUSE_DT_TRAINING
            and self._records_grad(xs)
            and xs.dtype == torch.float32
            and self.dt_projs_weight.dtype == torch.float32
            and self.dt_rank <= LOWRANK_MAX_RANK
        )

    def _fuse_dt_projection(self, xs: torch.Tensor) -> bool:
        """True where the native kernel computes the dt projection itself: no gradient recorded (inference, or
        validation under ``no_grad``), not traced by torch.compile (which sees the ``tofdenoise::ss2d_scan``
        operator), float32, dt_rank within the kernel's bound."""
        return (
            not self._records_grad(xs)
            and not torch.compiler.is_compiling()
            and xs.dtype == torch.float32
            and self.dt_rank <= LOWRANK_MAX_RANK
        )
