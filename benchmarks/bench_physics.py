"""Physics benchmarks (side by side, one run): closed-form sigma_D vs a batched generic 2x2 inverse, and the
tap-level capture simulator.

Usage: python benchmarks/bench_physics.py [--quick] [--threads N ...]

1. sigma_D on a 640x480 float32 map (CPU):
   closed   tofdenoise.physics.uncertainty.sigma_depth_mm (closed form of the 2x2 information matrix)
   sums+inv the same quantity through torch.linalg.inv: information-matrix entries I_DD, I_Da, I_aa by
            vectorised sums (information_matrix), stacked to (H, W, 2, 2), inverted, entry [0, 0]
   JtWJ+inv the textbook route: J (H, W, N, 2), J^T Sigma^-1 J by batched matmul, torch.linalg.inv
   inv only torch.linalg.inv on the (H, W, 2, 2) stack alone (lower bound of any generic-inverse route)
   fused    benchmarks/sigma_compiled.py: sigma_depth_mm_compiled (the closed form as one
            torch.compile kernel; compiled once before timing)
   Timings are medians of interleaved repeats; the ratios are generic / closed and generic / fused.
2. simulate_frames: 100 frames of 640x480, 4 taps (default calibration), frames/s and total seconds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from sigma_compiled import sigma_depth_mm_compiled  # benchmarks/ is on sys.path when run as a script

from tofdenoise.physics.calibration import default_calibration
from tofdenoise.physics.simulator import simulate_frames
from tofdenoise.physics.uncertainty import information_matrix, sigma_depth_mm, tap_jacobian, tap_variance_e2


def jtwj_sigma(depth: torch.Tensor, signal: torch.Tensor, calib) -> torch.Tensor:
    """Textbook route: J (H,W,N,2), Sigma^-1 diagonal, J^T Sigma^-1 J by batched matmul, then inverse."""
    g, r = tap_jacobian(depth, signal, calib)
    jac = torch.stack([g, r], -1)
    w = 1.0 / tap_variance_e2(depth, signal, calib)
    m = jac.transpose(-1, -2) @ (w.unsqueeze(-1) * jac)
    return torch.linalg.inv(m)[..., 0, 0].sqrt()


def generic_sigma(depth: torch.Tensor, signal: torch.Tensor, calib) -> torch.Tensor:
    """Vectorised information-matrix sums, then the batched generic inverse."""
    i_dd, i_da, i_aa = information_matrix(depth, signal, calib)
    m = torch.stack([torch.stack([i_dd, i_da], -1), torch.stack([i_da, i_aa], -1)], -2)
    return torch.linalg.inv(m)[..., 0, 0].sqrt()


def bench_sigma(threads: int, repeats: int, h: int = 480, w: int = 640) -> dict[str, float]:
    torch.set_num_threads(threads)
    calib = default_calibration()
    g = torch.Generator().manual_seed(0)
    depth = (300.0 + 2400.0 * torch.rand(h, w, generator=g)).float()
    signal = (calib.signal_min_e + (calib.signal_max_e - calib.signal_min_e) * torch.rand(h, w, generator=g)).float()
    closed = sigma_depth_mm(depth, signal, calib)
    ref = generic_sigma(depth.double(), signal.double(), calib).float()
    max_rel = float(((closed - ref).abs() / ref).max())
    i_dd, i_da, i_aa = information_matrix(depth, signal, calib)
    stack = torch.stack([torch.stack([i_dd, i_da], -1), torch.stack([i_da, i_aa], -1)], -2).contiguous()
    max_rel = max(
        max_rel, float(((closed - jtwj_sigma(depth.double(), signal.double(), calib).float()).abs() / ref).max())
    )
    fused = sigma_depth_mm_compiled(depth, signal, calib)  # compiles once (not timed)
    max_rel = max(max_rel, float(((fused - ref).abs() / ref).max()))
    t_closed, t_generic, t_jtwj, t_inv, t_fused = [], [], [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sigma_depth_mm(depth, signal, calib)
        t1 = time.perf_counter()
        generic_sigma(depth, signal, calib)
        t2 = time.perf_counter()
        jtwj_sigma(depth, signal, calib)
        t3 = time.perf_counter()
        torch.linalg.inv(stack)
        t4 = time.perf_counter()
        sigma_depth_mm_compiled(depth, signal, calib)
        t_fused.append(time.perf_counter() - t4)
        t_closed.append(t1 - t0)
        t_generic.append(t2 - t1)
        t_jtwj.append(t3 - t2)
        t_inv.append(t4 - t3)
    c, gen, jt, inv, fu = (statistics.median(t) for t in (t_closed, t_generic, t_jtwj, t_inv, t_fused))
    mpx = h * w / 1e6
    return {
        "threads": threads,
        "closed_ms": 1e3 * c,
        "generic_ms": 1e3 * gen,
        "jtwj_ms": 1e3 * jt,
        "inv_only_ms": 1e3 * inv,
        "closed_mpx_s": mpx / c,
        "generic_mpx_s": mpx / gen,
        "ratio": gen / c,
        "ratio_jtwj": jt / c,
        "ratio_vs_inv_only": inv / c,
        "max_rel_diff": max_rel,
        "fused_ms": 1e3 * fu,
        "fused_mpx_s": mpx / fu,
        "ratio_fused": gen / fu,
        "ratio_fused_jtwj": jt / fu,
    }


def bench_simulator(frames: int, threads: int, h: int = 480, w: int = 640) -> dict[str, float]:
    torch.set_num_threads(threads)
    calib = default_calibration()
    g = torch.Generator().manual_seed(0)
    depth = 300.0 + 2000.0 * torch.rand(h, w, generator=g)
    signal = calib.signal_min_e + (calib.signal_max_e - calib.signal_min_e) * torch.rand(h, w, generator=g)
    t0 = time.perf_counter()
    out = simulate_frames(depth, signal, calib, frames, generator=torch.Generator().manual_seed(1))
    dt = time.perf_counter() - t0
    assert out.depth_mm.shape == (frames, h, w)
    return {
        "threads": threads,
        "frames": frames,
        "seconds": dt,
        "frames_per_s": frames / dt,
        "seconds_per_100_frames": 100.0 * dt / frames,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few repeats, 10 simulator frames")
    parser.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=None,
        help="torch thread counts to measure (default: 1 and the current setting)",
    )
    args = parser.parse_args(argv)
    default_threads = torch.get_num_threads()
    threads = args.threads or sorted({1, default_threads})
    repeats = 5 if args.quick else 30
    frames = 10 if args.quick else 100

    print(f"torch {torch.__version__}, numpy {np.__version__}, default threads {default_threads}")
    print("\n### sigma_D on a 640x480 float32 map (CPU), median of interleaved repeats")
    print(
        f"{'threads':>7} {'closed ms':>10} {'sums+inv ms':>12} {'JtWJ+inv ms':>12} {'inv-only ms':>12} "
        f"{'closed Mpx/s':>13} {'sums+inv Mpx/s':>15} {'ratio':>7} {'ratio JtWJ':>11} {'vs inv-only':>12} "
        f"{'max rel diff':>13} {'fused ms':>9} {'fused Mpx/s':>12} {'ratio fused':>12} {'fused JtWJ':>11}"
    )
    rows = []
    for t in threads:
        r = bench_sigma(t, repeats)
        rows.append(r)
        print(
            f"{r['threads']:>7d} {r['closed_ms']:>10.2f} {r['generic_ms']:>12.2f} {r['jtwj_ms']:>12.2f} "
            f"{r['inv_only_ms']:>12.2f} {r['closed_mpx_s']:>13.1f} {r['generic_mpx_s']:>15.2f} {r['ratio']:>6.1f}x "
            f"{r['ratio_jtwj']:>10.1f}x {r['ratio_vs_inv_only']:>11.1f}x {r['max_rel_diff']:>13.1e} "
            f"{r['fused_ms']:>9.2f} {r['fused_mpx_s']:>12.1f} {r['ratio_fused']:>11.1f}x "
            f"{r['ratio_fused_jtwj']:>10.1f}x"
        )
    print(
        "ratio = (vectorised sums + batched torch.linalg.inv) / closed; ratio JtWJ = (J^T Sigma^-1 J by batched\n"
        "matmul + torch.linalg.inv) / closed; vs inv-only = torch.linalg.inv alone / closed; ratio fused /\n"
        "fused JtWJ = the same two generic routes / the fused kernel. Target >= 20x."
    )

    print(f"\n### simulate_frames: {frames} frames of 640x480, 4 taps (target: 100 frames < 30 s on 2 cores)")
    print(f"{'threads':>7} {'frames':>7} {'seconds':>8} {'frames/s':>9} {'s per 100 frames':>17}")
    for t in sorted({default_threads}):
        s = bench_simulator(frames, t)
        print(
            f"{s['threads']:>7d} {s['frames']:>7d} {s['seconds']:>8.2f} {s['frames_per_s']:>9.2f} "
            f"{s['seconds_per_100_frames']:>17.2f}"
        )
    torch.set_num_threads(default_threads)
    return 0


if __name__ == "__main__":
    sys.exit(main())
