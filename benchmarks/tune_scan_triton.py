"""Tune the Triton selective scan's launch constants on this GPU (CUDA only).

Usage: python benchmarks/tune_scan_triton.py [--length 102400] [--dim 256]

For chunk x channels-per-program x warps, with float32 and bf16 inputs (u, delta, B, C), prints the forward and
forward+backward milliseconds and the largest relative difference from the float32 PyTorch scan, at the size of
DVSS's first stage on a 320x320 batch of 4 by default. Set the winners in ``tofdenoise.models.scan_triton``
(CHUNK, BLOCK_D_MAX, NUM_WARPS). The defaults were tuned on an H100 (docs/benchmarks.md).
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
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        print("tune_scan_triton: skipped (no CUDA device)")
        return 0
    from bench_gpu import time_cuda  # benchmarks/ is on sys.path when run as a script

    from tofdenoise.models import scan_triton as st
    from tofdenoise.models.scan import selective_scan_chunked

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
    defaults = (st.CHUNK, st.BLOCK_D_MAX, st.NUM_WARPS)
    for dtype in (torch.float32, torch.bfloat16):
        ins = [(t.to(dtype) if i in (0, 1, 3, 4) else t).clone().requires_grad_() for i, t in enumerate(base)]
        for chunk, block_d, warps in itertools.product((32, 64), (1, 2, 4), (2, 4, 8)):
            st.CHUNK, st.BLOCK_D_MAX, st.NUM_WARPS = chunk, block_d, warps

            def fwd():
                return st.selective_scan_triton(*ins, delta_softplus=True)

            y = fwd()
            got = [y, *torch.autograd.grad(y, ins, dy.to(dtype))]
            err = max(float(((a.float() - r).abs().max() / r.abs().max()).item()) for a, r in zip(got, ref))
            row = {
                "dtype": str(dtype).replace("torch.", ""),
                "chunk": chunk,
                "block_d": block_d,
                "warps": warps,
                "fwd_ms": round(time_cuda(fwd, 5), 3),
                "fwd_bwd_ms": round(time_cuda(lambda: torch.autograd.grad(fwd(), ins, dy.to(dtype)), 5), 3),
                "max_rel_err": err,
            }
            print(json.dumps(row), flush=True)
    st.CHUNK, st.BLOCK_D_MAX, st.NUM_WARPS = defaults
    return 0


if __name__ == "__main__":
    sys.exit(main())
