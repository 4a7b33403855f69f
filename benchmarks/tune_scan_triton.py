"""Tune the Triton selective scan's launch constants on this GPU (CUDA only).

Usage: python benchmarks/tune_scan_triton.py [--length 102400] [--dim 256] [--ss2d]

For chunk x channels-per-program x warps, with float32 and bf16 inputs (u, delta, B, C), prints the forward and
forward+backward milliseconds and the largest relative difference from the float32 PyTorch scan, at the size of
DVSS's first stage on a 320x320 batch of 4 by default. Set the winners in ``tofdenoise.models.scan.triton``
(CHUNK, BLOCK_D_MAX, NUM_WARPS). The defaults were tuned on an H100 (docs/benchmarks.md).
``--ss2d`` tunes the SS2D route instead (channels-last, four directions read in place; ``SS2D_BLOCK_D_MAX``) at
the same size: --dim is then 4 x d_inner and --length H x W of a square image.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys

import torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--dim", type=int, default=256)
    p.add_argument("--length", type=int, default=320 * 320)
    p.add_argument("--groups", type=int, default=4)
    p.add_argument("--d-state", type=int, default=16)
    p.add_argument("--ss2d", action="store_true", help="tune the SS2D route (SS2D_BLOCK_D_MAX) instead")
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        print("tune_scan_triton: skipped (no CUDA device)")
        return 0
    if args.ss2d:
        return tune_ss2d(args)

    from tofdenoise.models.scan import selective_scan_chunked
    from tofdenoise.models.scan import triton as st

    b, dim, length, groups, n = args.batch, args.dim, args.length, args.groups, args.d_state
    g = torch.Generator(device="cuda").manual_seed(0)

    def randn(*shape):
        return torch.randn(*shape, device="cuda", generator=g)

    base = [
        randn(b, dim, length),
        0.5 * randn(b, dim, length),
        -torch.exp(0.5 * randn(dim, n)),
        randn(b, groups, n, length),
        randn(b, groups, n, length),
        randn(dim),
        randn(dim),
    ]
    dy = randn(b, dim, length)
    ref_in = [t.clone().requires_grad_() for t in base]
    ref_y = selective_scan_chunked(*ref_in, True)
    ref = [ref_y.detach(), *torch.autograd.grad(ref_y, ref_in, dy)]
    _sweep(
        "BLOCK_D_MAX",
        (1, 2, 4),
        lambda dtype: [(t.to(dtype) if i in (0, 1, 3, 4) else t).clone().requires_grad_() for i, t in enumerate(base)],
        lambda ins: st.selective_scan_triton(*ins, delta_softplus=True),
        ref,
        dy,
    )
    return 0


def _sweep(block_name: str, blocks, make_inputs, call, ref, dy, label: dict | None = None) -> None:
    """Time ``call(ins)`` forward and forward+backward for chunk x channels-per-program (the module constant
    ``block_name``) x warps, float32 and bf16 inputs, with the largest relative difference from ``ref``; one JSON
    line per setting; the module's constants are restored afterwards."""
    from bench_gpu import time_cuda  # benchmarks/ is on sys.path when run as a script

    from tofdenoise.models.scan import triton as st

    defaults = (st.CHUNK, getattr(st, block_name), st.NUM_WARPS)
    try:
        for dtype in (torch.float32, torch.bfloat16):
            ins = make_inputs(dtype)
            for chunk, block_d, warps in itertools.product((32, 64), blocks, (2, 4, 8)):
                st.CHUNK, st.NUM_WARPS = chunk, warps
                setattr(st, block_name, block_d)
                y = call(ins)
                got = [y, *torch.autograd.grad(y, ins, dy.to(dtype))]
                err = max(float(((a.float() - r).abs().max() / r.abs().max()).item()) for a, r in zip(got, ref))
                row = {
                    **(label or {}),
                    "dtype": str(dtype).replace("torch.", ""),
                    "chunk": chunk,
                    "block_d": block_d,
                    "warps": warps,
                    "fwd_ms": round(time_cuda(lambda: call(ins), 5), 3),
                    "fwd_bwd_ms": round(time_cuda(lambda: torch.autograd.grad(call(ins), ins, dy.to(dtype)), 5), 3),
                    "max_rel_err": err,
                }
                print(json.dumps(row), flush=True)
    finally:
        st.CHUNK, st.NUM_WARPS = defaults[0], defaults[2]
        setattr(st, block_name, defaults[1])


def tune_ss2d(args) -> int:
    from tofdenoise.models.scan import ss2d_scan_reference
    from tofdenoise.models.scan import triton as st

    side = int(round(args.length**0.5))
    b, di, n, length = args.batch, args.dim // 4, args.d_state, side * side
    g = torch.Generator(device="cuda").manual_seed(0)

    def randn(*shape):
        return torch.randn(*shape, device="cuda", generator=g)

    x, dts, x_dbl = randn(b, length, di), 0.5 * randn(b, length, 4 * di), randn(b, length, 4, 2 + 2 * n)
    A, D, bias = -torch.exp(0.5 * randn(4 * di, n)), randn(4 * di), randn(4 * di)
    dy = randn(b, length, di)

    def call(fn, ins):
        xd = ins[3]
        return fn(ins[0], ins[1], ins[2], xd[..., 2 : 2 + n], xd[..., 2 + n :], D, bias, side, side)

    ref_in = [t.clone().requires_grad_() for t in (x, dts, A, x_dbl)]
    ref_y = call(ss2d_scan_reference, ref_in)
    ref = [ref_y.detach(), *torch.autograd.grad(ref_y, ref_in, dy)]
    _sweep(
        "SS2D_BLOCK_D_MAX",
        (2, 4, 8, 16, 32),
        lambda dtype: [
            (t.to(dtype) if i != 2 else t).clone().requires_grad_() for i, t in enumerate((x, dts, A, x_dbl))
        ],
        lambda ins: call(st.ss2d_scan_triton, ins),
        ref,
        dy,
        {"route": "ss2d"},
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
