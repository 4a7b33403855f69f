"""Tune the Triton selective scan's launch constants on this GPU (CUDA only).

Usage: python benchmarks/tune_scan_triton.py [--length 102400] [--dim 256] [--ss2d]

For settings of chunk x channels-per-program x warps x programs per multiprocessor (the sequence split into
segments, ``SEGMENT_PROGRAMS_PER_SM``), with float32 and bf16 inputs (u, delta, B, C), prints the forward and
forward+backward milliseconds and the largest relative difference from the float32 PyTorch scan, at the size of
DVSS's first stage on a 320x320 batch of 4 by default. Set the winners in ``tofdenoise.models.scan.triton``
(CHUNK, BLOCK_D_MAX / SS2D_BLOCK_D_MAX, NUM_WARPS, SEGMENT_PROGRAMS_PER_SM); docs/benchmarks.md has the sweeps.
``--ss2d`` tunes the SS2D route instead (channels-last, four directions read in place; ``SS2D_BLOCK_D_MAX``) at
the same size: --dim is then 4 x d_inner and --length H x W of a square image.
"""

from __future__ import annotations

import argparse
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
    p.add_argument(
        "--settings",
        default=None,
        help="space-separated chunk,block_d,warps,programs_per_sm settings (default: SETTINGS)",
    )
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        print("tune_scan_triton: skipped (no CUDA device)")
        return 0
    if args.ss2d:
        tune_ss2d(args)
        return 0

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
        [(c, b, w, p) for c, b, w, p in parse_settings(args.settings) if b <= 4],
        lambda dtype: [(t.to(dtype) if i in (0, 1, 3, 4) else t).clone().requires_grad_() for i, t in enumerate(base)],
        lambda ins: st.selective_scan_triton(*ins, delta_softplus=True),
        ref,
        dy,
    )
    return 0


#: (positions per chunk, channels per program, warps, programs per multiprocessor) tried by default
SETTINGS = (
    (32, 4, 4, 8),
    (32, 4, 4, 2),
    (32, 4, 4, 32),
    (16, 4, 4, 8),
    (16, 8, 4, 8),
    (32, 2, 4, 8),
    (32, 8, 8, 8),
    (32, 4, 8, 8),
    (64, 4, 8, 8),
    (16, 4, 2, 16),
)


def parse_settings(text: str | None) -> tuple[tuple[int, int, int, int], ...]:
    """``"32,4,4,8 16,4,4,8"`` -> settings (chunk, channels per program, warps, programs per multiprocessor)."""
    if not text:
        return SETTINGS
    out = []
    for item in text.split():
        parts = tuple(int(v) for v in item.split(","))
        if len(parts) != 4:
            raise SystemExit(f"tune_scan_triton: --settings item {item!r} is not chunk,block_d,warps,programs_per_sm")
        out.append(parts)
    return tuple(out)


def _sweep(block_name: str, settings, make_inputs, call, ref, dy, label=None, dtypes=None) -> list[dict]:
    """Time ``call(ins)`` forward and forward+backward for each setting (chunk, channels per program -- the module
    constant ``block_name`` --, warps, programs per multiprocessor), float32 and bf16 inputs (or ``dtypes``), with
    the largest relative difference from ``ref``; one JSON line per setting, returned as rows; the module's
    constants are restored afterwards."""
    from bench_gpu import time_cuda  # benchmarks/ is on sys.path when run as a script

    from tofdenoise.models.scan import triton as st

    names = ("CHUNK", block_name, "NUM_WARPS", "SEGMENT_PROGRAMS_PER_SM")
    defaults = {name: getattr(st, name) for name in names}
    rows = []
    try:
        for dtype in dtypes or (torch.float32, torch.bfloat16):
            ins = make_inputs(dtype)
            for setting in settings:
                for name, value in zip(names, setting):
                    setattr(st, name, value)
                y = call(ins)
                got = [y, *torch.autograd.grad(y, ins, dy.to(dtype))]
                err = max(float(((a.float() - r).abs().max() / r.abs().max()).item()) for a, r in zip(got, ref))
                row = {
                    **(label or {}),
                    "dtype": str(dtype).replace("torch.", ""),
                    "chunk": setting[0],
                    "block_d": setting[1],
                    "warps": setting[2],
                    "programs_per_sm": setting[3],
                    "fwd_ms": round(time_cuda(lambda: call(ins), 5), 3),
                    "fwd_bwd_ms": round(time_cuda(lambda: torch.autograd.grad(call(ins), ins, dy.to(dtype)), 5), 3),
                    "max_rel_err": err,
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    finally:
        for name, value in defaults.items():
            setattr(st, name, value)
    return rows


def tune_ss2d(args, dtypes=None) -> list[dict]:
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
    return _sweep(
        "SS2D_BLOCK_D_MAX",
        parse_settings(args.settings),
        lambda dtype: [
            (t.to(dtype) if i != 2 else t).clone().requires_grad_() for i, t in enumerate((x, dts, A, x_dbl))
        ],
        lambda ins: call(st.ss2d_scan_triton, ins),
        ref,
        dy,
        {"route": "ss2d"},
        dtypes,
    )


if __name__ == "__main__":
    sys.exit(main())
