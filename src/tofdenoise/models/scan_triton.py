"""Optional fused selective-scan paths for CUDA: a Triton kernel pair (forward + recomputing backward) and
mamba-ssm's ``selective_scan_fn`` when its compiled extension imports. Both are chosen automatically by
``tofdenoise.models.selective_scan`` on CUDA tensors, with the pure-PyTorch chunked scan as the fallback.

Triton kernels (same recurrence as ``scan.py``: h_t = exp(delta_t A) h_{t-1} + delta_t u_t B_t,
y_t = C_t . h_t + D u_t, with delta_t = softplus(delta_raw_t + delta_bias) computed inside the kernels):
- one program per (batch, block of BLOCK_D channels of one group) walks the sequence in chunks of CHUNK
  positions; each chunk is loaded as coalesced (BLOCK_D, CHUNK) / (N, CHUNK) tiles and its states are one
  ``tl.associative_scan`` of the affine maps h -> a h + b over a (BLOCK_D, N, CHUNK) tile, continued from the
  state carried in from the previous chunk. The forward writes y and the state entering every chunk
  (memory L * dim * N / CHUNK);
- the backward walks the chunks in reverse: it recomputes the chunk's states from its checkpoint, gets the
  adjoint g_t = dy_t C_t + a_{t+1} g_{t+1} by a reverse associative scan seeded with the next chunk's adjoint,
  and uses a_t h_{t-1} = h_t - b_t, so no shifted state is needed. dB and dC (shared by the channels of a
  group) are accumulated with atomic adds; dA is summed over the batch with atomic adds.

delta_bias, softplus and the D skip term are applied inside the kernels (their gradients too), and bf16/fp16
u, delta, B, C are read as they are, so SS2D under autocast pays for no conversion copies; everything is
computed in float32. Speed and agreement with the PyTorch scan on an H100: docs/benchmarks.md ("GPU",
``benchmarks/bench_gpu.py``). The ``auto`` dispatch uses the Triton kernels only after :func:`triton_verified` has
checked them against the PyTorch scan on the device (once per process), so
a toolchain problem falls back to the PyTorch scan with a warning instead of wrong results.
"""

from __future__ import annotations

import functools
import warnings

import torch

__all__ = [
    "triton_available",
    "triton_verified",
    "mamba_ssm_available",
    "selective_scan_triton",
    "selective_scan_mamba",
]

#: positions per chunk (one associative scan over a (BLOCK_D, N, CHUNK) tile; a state checkpoint per chunk)
CHUNK = 32
#: channels per program: the fastest setting on an H100 at the DVSS training size, float32 and bf16 inputs
#: (``benchmarks/tune_scan_triton.py``; the sweep is in docs/benchmarks.md, "GPU")
BLOCK_D_MAX = 2
NUM_WARPS = 4


@functools.lru_cache(maxsize=1)
def _mamba_fn():
    try:  # the compiled extension (selective_scan_cuda) can fail to import even when the package is there
        from mamba_ssm.ops.selective_scan_interface import selective_scan_fn
    except Exception:  # noqa: BLE001 - any import-time failure means "not available"
        return None
    return selective_scan_fn


def mamba_ssm_available() -> bool:
    """True when CUDA is available and mamba-ssm's compiled selective scan imports."""
    return torch.cuda.is_available() and _mamba_fn() is not None


try:  # kernels at module level: Triton resolves the names a kernel calls (_combine) from its module's globals
    import triton
    import triton.language as tl
except Exception:  # noqa: BLE001 - no Triton (CPU-only install): the PyTorch scan is used
    triton = tl = None

if triton is not None:

    @triton.jit
    def _combine(a1, b1, a2, b2):
        # (a1, b1) then (a2, b2) for h -> a h + b: h -> a2 (a1 h + b1) + b2
        return a1 * a2, a2 * b1 + b2

    @triton.jit
    def _softplus(x):
        # log(1 + e^x) without overflow, and e^x where 1 + e^x rounds to 1 (float32)
        return tl.where(x > 20.0, x, tl.where(x < -15.0, tl.exp(x), tl.log(1.0 + tl.exp(x))))

    @triton.jit
    def _delta_eff(raw_ptr, bias_ptr, offs, d, mask, HAS_BIAS: tl.constexpr, SOFTPLUS: tl.constexpr):
        """(delta after bias and softplus, the pre-softplus value) of a (BLOCK_D, T) tile, in float32."""
        x = tl.load(raw_ptr + offs, mask=mask, other=0.0).to(tl.float32)
        if HAS_BIAS:
            x = x + tl.load(bias_ptr + d).to(tl.float32)[:, None]
        if SOFTPLUS:
            dt = _softplus(x)
        else:
            dt = x
        return dt, x

    @triton.jit
    def _program_tiles(
        A_ptr, L, DIM, N, DIM_PER_GROUP, G, NCHUNK, CHUNK_T: tl.constexpr, BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr
    ):
        """This program's channels d, states n (and mask), chunk positions tt, its A block and the base offsets
        of its u/delta/y rows, its group's B/C rows and its state checkpoints."""
        pid_b = tl.program_id(0).to(tl.int64)  # 64-bit offsets: batch * dim * L can exceed 2**31
        pid_d = tl.program_id(1)
        d = (pid_d * BLOCK_D + tl.arange(0, BLOCK_D)).to(tl.int64)
        n = tl.arange(0, BLOCK_N)
        tt = tl.arange(0, CHUNK_T)
        nmask = n < N
        grp = ((pid_d * BLOCK_D) // DIM_PER_GROUP).to(tl.int64)
        A = tl.load(A_ptr + d[:, None] * N + n[None, :], mask=nmask[None, :], other=0.0)  # (D, N)
        row = pid_b * DIM * L + d * L  # (D,)
        bc = pid_b * G * N * L + grp * N * L + n * L  # (N,)
        ck = (pid_b * DIM + d)[:, None] * (NCHUNK * BLOCK_N) + n[None, :]
        return d, n, tt, nmask, A, row, bc, ck

    @triton.jit
    def _chunk_states(
        u_ptr,
        delta_ptr,
        bias_ptr,
        B_ptr,
        C_ptr,
        A,
        h0,
        d,
        row,
        bc,
        t,
        tmask,
        nmask,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        """Load one chunk's tiles and scan it from the entering state h0: (delta, pre-softplus delta, u, B, C,
        b = delta u B, states h_t), all float32; the states are (BLOCK_D, BLOCK_N, CHUNK_T)."""
        offs = row[:, None] + t[None, :]
        bmask = nmask[:, None] & tmask[None, :]
        dt, x = _delta_eff(delta_ptr, bias_ptr, offs, d, tmask[None, :], HAS_BIAS, SOFTPLUS)  # (D, T)
        ut = tl.load(u_ptr + offs, mask=tmask[None, :], other=0.0).to(tl.float32)
        Bt = tl.load(B_ptr + bc[:, None] + t[None, :], mask=bmask, other=0.0).to(tl.float32)  # (N, T)
        Ct = tl.load(C_ptr + bc[:, None] + t[None, :], mask=bmask, other=0.0).to(tl.float32)
        a = tl.exp(dt[:, None, :] * A[:, :, None])  # (D, N, T)
        b = (dt * ut)[:, None, :] * Bt[None, :, :]
        a_acc, b_acc = tl.associative_scan((a, b), axis=2, combine_fn=_combine)
        return dt, x, ut, Bt, Ct, b, a_acc * h0[:, :, None] + b_acc

    @triton.jit
    def fwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        y_ptr,
        ckpt_ptr,
        L,
        DIM,
        N,
        DIM_PER_GROUP,
        G,
        NCHUNK,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        d, n, tt, nmask, A, row, bc, ck = _program_tiles(
            A_ptr, L, DIM, N, DIM_PER_GROUP, G, NCHUNK, CHUNK_T, BLOCK_D, BLOCK_N
        )
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        for c in range(0, NCHUNK):
            tl.store(ckpt_ptr + ck + c * BLOCK_N, h)  # the state entering chunk c
            t = c * CHUNK_T + tt
            tmask = t < L
            _, _, ut, _, Ct, _, hs = _chunk_states(
                u_ptr, delta_ptr, bias_ptr, B_ptr, C_ptr, A, h, d, row, bc, t, tmask, nmask, HAS_BIAS, SOFTPLUS
            )
            yt = tl.sum(hs * Ct[None, :, :], axis=1)
            if HAS_D:
                yt += Dv[:, None] * ut
            tl.store(y_ptr + row[:, None] + t[None, :], yt, mask=tmask[None, :])
            h = tl.sum(tl.where((tt == CHUNK_T - 1)[None, None, :], hs, 0.0), axis=2)  # state after the chunk

    @triton.jit
    def bwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        dy_ptr,
        ckpt_ptr,
        du_ptr,
        ddelta_ptr,
        dA_ptr,
        dB_ptr,
        dC_ptr,
        dD_ptr,
        dbias_ptr,
        L,
        DIM,
        N,
        DIM_PER_GROUP,
        G,
        NCHUNK,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        d, n, tt, nmask, A, row, bc, ck = _program_tiles(
            A_ptr, L, DIM, N, DIM_PER_GROUP, G, NCHUNK, CHUNK_T, BLOCK_D, BLOCK_N
        )
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        g_next = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)  # adjoint of the state after the chunk
        dA_acc = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        dD_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        dbias_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        for ci in range(0, NCHUNK):
            c = NCHUNK - 1 - ci
            h0 = tl.load(ckpt_ptr + ck + c * BLOCK_N)
            t = c * CHUNK_T + tt
            tmask = t < L
            t1mask = (t + 1) < L
            bmask = nmask[:, None] & tmask[None, :]
            offs = row[:, None] + t[None, :]
            # recompute the chunk's states from its checkpoint
            dt, x, ut, Bt, Ct, b, hs = _chunk_states(
                u_ptr, delta_ptr, bias_ptr, B_ptr, C_ptr, A, h0, d, row, bc, t, tmask, nmask, HAS_BIAS, SOFTPLUS
            )
            dt1, _ = _delta_eff(delta_ptr, bias_ptr, offs + 1, d, t1mask[None, :], HAS_BIAS, SOFTPLUS)
            dyt = tl.load(dy_ptr + offs, mask=tmask[None, :], other=0.0).to(tl.float32)
            # adjoint g_t = dy_t C_t + a_{t+1} g_{t+1}: a reverse scan, seeded with the next chunk's g
            a1 = tl.where(t1mask[None, None, :], tl.exp(dt1[:, None, :] * A[:, :, None]), 0.0)
            src = dyt[:, None, :] * Ct[None, :, :]
            ga, gb = tl.associative_scan((a1, src), axis=2, combine_fn=_combine, reverse=True)
            gs = gb + ga * g_next[:, :, None]
            # a_t h_{t-1} = h_t - b_t (no division, no shifted state)
            q = gs * (hs - b)
            sr = tl.sum(gs * Bt[None, :, :], axis=1)  # (D, T)
            tl.atomic_add(dC_ptr + bc[:, None] + t[None, :], tl.sum(dyt[:, None, :] * hs, axis=0), mask=bmask)
            tl.atomic_add(dB_ptr + bc[:, None] + t[None, :], tl.sum(gs * (dt * ut)[:, None, :], axis=0), mask=bmask)
            g_dt = tl.sum(q * A[:, :, None], axis=1) + ut * sr  # d loss / d delta (after softplus)
            if SOFTPLUS:
                g_dt = g_dt / (1.0 + tl.exp(-x))  # softplus' = sigmoid
            g_dt = tl.where(tmask[None, :], g_dt, 0.0)
            tl.store(ddelta_ptr + offs, g_dt, mask=tmask[None, :])
            du = dt * sr
            if HAS_D:
                du += Dv[:, None] * dyt
                dD_acc += tl.sum(dyt * ut, axis=1)
            tl.store(du_ptr + offs, du, mask=tmask[None, :])
            dbias_acc += tl.sum(g_dt, axis=1)
            dA_acc += tl.sum(q * dt[:, None, :], axis=2)
            g_next = tl.sum(tl.where((tt == 0)[None, None, :], gs, 0.0), axis=2)
        tl.atomic_add(dA_ptr + d[:, None] * N + n[None, :], dA_acc, mask=nmask[None, :])
        if HAS_D:
            tl.atomic_add(dD_ptr + d, dD_acc)
        if HAS_BIAS:
            tl.atomic_add(dbias_ptr + d, dbias_acc)


def _triton_kernels():
    """(triton, forward kernel, backward kernel), or None without Triton."""
    if triton is None:
        return None
    return triton, fwd_kernel, bwd_kernel


def triton_available() -> bool:
    """True when CUDA is available and Triton imports."""
    return torch.cuda.is_available() and _triton_kernels() is not None


@functools.cache
def triton_verified(device_index: int = 0) -> bool:
    """Triton is importable *and* its kernels reproduce the PyTorch scan (forward and all gradients, 1e-3
    relative) on a small random problem on this device. Run once per device by the ``auto`` dispatch, so a
    kernel or toolchain problem falls back to the PyTorch scan with a warning instead of wrong results."""
    if not triton_available():
        return False
    from .scan import selective_scan_chunked

    try:
        dev = torch.device("cuda", device_index)
        gen = torch.Generator(device="cpu").manual_seed(0)
        batch, dim, length, groups, n = 2, 64, 130, 2, 16
        shapes = [
            (batch, dim, length),
            (batch, dim, length),
            (dim, n),
            (batch, groups, n, length),
            (batch, groups, n, length),
            (dim,),
            (dim,),
        ]
        base = [torch.randn(s, generator=gen) for s in shapes]
        base[2] = -torch.exp(0.5 * base[2])
        results = []
        with torch.enable_grad():  # the first call may happen under no_grad (inference)
            for fn in (selective_scan_triton, selective_scan_chunked):
                ins = [t.to(dev).requires_grad_() for t in base]
                y = fn(*ins, delta_softplus=True)
                grads = torch.autograd.grad(y.square().sum(), ins)
                results.append([y.detach(), *grads])
        for a, b in zip(*results):
            if not torch.isfinite(a).all() or (a - b).abs().max() > 1e-3 * b.abs().max().clamp_min(1e-6):
                raise RuntimeError("Triton selective scan disagrees with the PyTorch scan")
    except Exception as exc:  # noqa: BLE001 - any failure means: do not use this path
        warnings.warn(f"Triton selective scan disabled ({exc}); using the PyTorch scan", RuntimeWarning, stacklevel=2)
        return False
    return True


def _block_d(dim_per_group: int) -> int:
    """Largest power of two <= BLOCK_D_MAX dividing the channels per group (a block never straddles two
    groups)."""
    b = BLOCK_D_MAX
    while dim_per_group % b:
        b //= 2
    return b


class _TritonScanFn(torch.autograd.Function):
    """u, delta, B, C in their own float dtype (bf16 under autocast: no conversion copies), A / D / delta_bias
    float32; bias, softplus and the D skip term are applied inside the kernels. Computation in float32."""

    @staticmethod
    def forward(ctx, u, delta, A, B, C, D, delta_bias, delta_softplus):
        triton, fwd_kernel, _ = _triton_kernels()
        batch, dim, length = u.shape
        groups, n = B.shape[1], A.shape[1]
        dpg = dim // groups
        block_d = _block_d(dpg)
        block_n = triton.next_power_of_2(n)
        nchunk = triton.cdiv(length, CHUNK)
        y = torch.empty(u.shape, device=u.device, dtype=u.dtype)
        ckpt = torch.empty(batch, dim, nchunk, block_n, device=u.device, dtype=torch.float32)
        dummy = A  # any float32 tensor: never read when HAS_D / HAS_BIAS is off
        grid = (batch, dim // block_d)
        fwd_kernel[grid](
            u,
            delta,
            A,
            B,
            C,
            dummy if D is None else D,
            dummy if delta_bias is None else delta_bias,
            y,
            ckpt,
            length,
            dim,
            n,
            dpg,
            groups,
            nchunk,
            CHUNK_T=CHUNK,
            BLOCK_D=block_d,
            BLOCK_N=block_n,
            HAS_D=D is not None,
            HAS_BIAS=delta_bias is not None,
            SOFTPLUS=bool(delta_softplus),
            num_warps=NUM_WARPS,
        )
        ctx.save_for_backward(u, delta, A, B, C, D, delta_bias, ckpt)
        ctx.meta = (block_d, block_n, nchunk, CHUNK, NUM_WARPS, bool(delta_softplus))
        return y

    @staticmethod
    def backward(ctx, dy):
        _, _, bwd_kernel = _triton_kernels()
        u, delta, A, B, C, D, delta_bias, ckpt = ctx.saved_tensors
        block_d, block_n, nchunk, chunk, num_warps, softplus = ctx.meta
        batch, dim, length = u.shape
        groups, n = B.shape[1], A.shape[1]
        dy = dy.contiguous()
        du = torch.empty_like(u)
        ddelta = torch.empty_like(delta)
        dA = torch.zeros_like(A)
        dB = torch.zeros(B.shape, device=B.device, dtype=torch.float32)  # atomics accumulate in float32
        dC = torch.zeros(C.shape, device=C.device, dtype=torch.float32)
        dD = torch.zeros(dim, device=u.device, dtype=torch.float32)
        dbias = torch.zeros(dim, device=u.device, dtype=torch.float32)
        dummy = A
        grid = (batch, dim // block_d)
        bwd_kernel[grid](
            u,
            delta,
            A,
            B,
            C,
            dummy if D is None else D,
            dummy if delta_bias is None else delta_bias,
            dy,
            ckpt,
            du,
            ddelta,
            dA,
            dB,
            dC,
            dD,
            dbias,
            length,
            dim,
            n,
            dim // groups,
            groups,
            nchunk,
            CHUNK_T=chunk,
            BLOCK_D=block_d,
            BLOCK_N=block_n,
            HAS_D=D is not None,
            HAS_BIAS=delta_bias is not None,
            SOFTPLUS=softplus,
            num_warps=num_warps,
        )
        return (
            du,
            ddelta,
            dA,
            dB.to(B.dtype),
            dC.to(C.dtype),
            None if D is None else dD.to(D.dtype),
            None if delta_bias is None else dbias.to(delta_bias.dtype),
            None,
        )


def selective_scan_triton(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Triton selective scan (CUDA, float32 compute); same signature and result as ``selective_scan``. The
    result has u's dtype; bf16/fp16 u, delta, B, C are read as they are (no conversion copies)."""
    from .scan import _check_shapes

    if not triton_available():
        raise RuntimeError("selective_scan_triton: Triton with a CUDA device is not available")
    B, C, _ = _check_shapes(u, delta, A, B, C, D, delta_bias)
    f32 = torch.float32
    return _TritonScanFn.apply(
        u.contiguous(),
        delta.contiguous(),
        A.to(f32).contiguous(),
        B.contiguous(),
        C.contiguous(),
        None if D is None else D.to(f32).contiguous(),
        None if delta_bias is None else delta_bias.to(f32).contiguous(),
        bool(delta_softplus),
    )


def selective_scan_mamba(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """mamba-ssm's CUDA ``selective_scan_fn`` (raises RuntimeError when it cannot be imported)."""
    fn = _mamba_fn()
    if fn is None or not torch.cuda.is_available():
        raise RuntimeError("selective_scan_mamba: mamba_ssm's compiled selective scan is not importable")
    return fn(u, delta, A, B, C, D, z=None, delta_bias=delta_bias, delta_softplus=delta_softplus)
