"""GPU benchmarks (CUDA only; prints a skip line without a GPU), every comparison side by side in one run.

Usage: python benchmarks/bench_gpu.py [--quick] [--json FILE]

1. Selective scan, forward+backward, at the size of the first DVSS stage on a 320x320 training crop
   (batch 4, 4 directions x d_inner 64, d_state 16, L = 102400): the chunked PyTorch scan vs the Triton kernels
   (and mamba-ssm when importable); time, peak memory and the largest relative difference to the PyTorch scan.
2. sigma_D on a 640x480 float32 map: the batched 2x2 torch.linalg.inv route, the eager closed form
   (sigma_depth_mm) and the fused compiled kernel (sigma_depth_mm_compiled), with ratios.
3. The SS2D block (the DVSS first stage's size: batch 4, 320x320, dim 32 -> d_inner 64, d_state 16), float32 and
   bf16 autocast, forward and forward+backward, side by side: the cross_scan route (layout copies + the plain
   Triton scan) vs the fused route (the Triton kernels read the four directions in place); peak memory, and the
   fused forward's effective bandwidth (bytes of x, delta, B, C read once and y written once, per second)
   against the H100's 3.35 TB/s.
4. Training steps (forward+backward+AdamW) of every paper backbone at batch 4, 320x320: float32 vs bf16 autocast,
   ms per step and peak memory; full-resolution 480x640 inference (batch 1, bf16 autocast) ms per frame. DVSS
   twice: on its default SS2D route (the fused kernels) and on the cross_scan route, side by side (on an H200,
   2026-11-25, the fused block was slower under bf16: docs/benchmarks.md).
Timings: CUDA events around warm, synchronised repeats; medians.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

import torch


def time_cuda(fn: Callable[[], Any], repeats: int, warmup: int = 2) -> float:
    """Median milliseconds of ``fn`` on the current CUDA stream."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)


def time_ms(fn: Callable[[], Any], repeats: int, dry: bool = False) -> float:
    """:func:`time_cuda`'s median; ``dry`` (a rehearsal on the CPU): the wall milliseconds of one call."""
    if dry:
        t = time.perf_counter()
        fn()
        return (time.perf_counter() - t) * 1e3
    return time_cuda(fn, repeats)


def _peak_mib(fn: Callable[[], Any]) -> float:
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2**20


def bench_scan(quick: bool) -> list[dict[str, Any]]:
    from tofdenoise.models.scan import available_scan_backends, selective_scan

    batch, dim, length, groups, n = (2, 64, 4096, 4, 16) if quick else (4, 256, 320 * 320, 4, 16)
    g = torch.Generator(device="cuda").manual_seed(0)
    u = torch.randn(batch, dim, length, device="cuda", generator=g)
    delta = 0.5 * torch.randn(batch, dim, length, device="cuda", generator=g)
    A = -torch.exp(0.5 * torch.randn(dim, n, device="cuda", generator=g))
    B = torch.randn(batch, groups, n, length, device="cuda", generator=g)
    C = torch.randn(batch, groups, n, length, device="cuda", generator=g)
    D = torch.randn(dim, device="cuda", generator=g)
    bias = torch.randn(dim, device="cuda", generator=g)
    inputs = [t.requires_grad_() for t in (u, delta, A, B, C, D, bias)]
    grad_out = torch.randn(batch, dim, length, device="cuda", generator=g)

    def run(backend: str):
        y = selective_scan(*inputs, True, backend=backend)
        grads = torch.autograd.grad(y, inputs, grad_out)
        return y, grads

    ref_y, ref_g = run("torch")
    rows = []
    backends = ["torch"] + [b for b in available_scan_backends("cuda", verify=True) if b != "torch"]
    for backend in backends:
        y, grads = run(backend)
        err_y = float(((y - ref_y).abs().max() / ref_y.abs().max()).item())
        err_g = max(float(((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()) for a, b in zip(grads, ref_g))
        ms = time_cuda(lambda: run(backend), repeats=3 if quick else 10)
        mib = _peak_mib(lambda: run(backend))
        rows.append(
            {
                "backend": backend,
                "ms_fwd_bwd": ms,
                "peak_mib": mib,
                "max_rel_err_y": err_y,
                "max_rel_err_grads": err_g,
                "shape": [batch, dim, length, groups, n],
            }
        )
    return rows


H100_BYTES_PER_S = 3.35e12  # H100 SXM HBM3


def bench_ss2d(quick: bool) -> list[dict[str, Any]]:
    from tofdenoise.models.ss2d import SS2D

    batch, size, dim = (2, 96, 32) if quick else (4, 320, 32)
    torch.manual_seed(0)
    block = SS2D(dim, scan_backend="triton").cuda()
    x = torch.randn(batch, size, size, dim, device="cuda", requires_grad=True)
    fused = block._spatial_scan(x)
    rows = []
    for precision in ("fp32", "bf16"):
        for route in ("cross", "fused"):
            if route == "fused" and fused != "triton":
                rows.append({"precision": precision, "route": route, "error": "Triton not verified on this device"})
                continue
            block._spatial_scan = (lambda t: "triton") if route == "fused" else (lambda t: None)

            def fwd():
                with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bf16"):
                    return block(x)

            def fwd_bwd():
                fwd().float().square().mean().backward()

            row = {
                "precision": precision,
                "route": route,
                "shape": [batch, size, size, dim],
                "ms_fwd": time_cuda(lambda: fwd(), repeats=3 if quick else 10),
                "ms_fwd_bwd": time_cuda(fwd_bwd, repeats=3 if quick else 10),
                "peak_mib_fwd_bwd": _peak_mib(fwd_bwd),
            }
            rows.append(row)
        del block._spatial_scan  # back to the class's own dispatch
    # the fused scan alone: bytes it must move at least once, per second of its forward
    from tofdenoise.models.scan.triton import ss2d_scan_triton

    di, n, length = block.d_inner, block.d_state, size * size
    g = torch.Generator(device="cuda").manual_seed(0)
    for dtype in (torch.float32, torch.bfloat16):
        xs = torch.randn(batch, length, di, device="cuda", generator=g).to(dtype)
        dts = (0.5 * torch.randn(batch, length, 4 * di, device="cuda", generator=g)).to(dtype)
        x_dbl = torch.randn(batch, length, 4, 2 + 2 * n, device="cuda", generator=g).to(dtype)
        A, D, bias = block._scan_params()
        args = (xs, dts, A, x_dbl[..., 2 : 2 + n], x_dbl[..., 2 + n :], D, bias, size, size)
        with torch.no_grad():
            ms = time_cuda(lambda: ss2d_scan_triton(*args), repeats=3 if quick else 10)
        item = xs.element_size()
        moved = batch * length * (di + 4 * di + 8 * n) * item + batch * length * di * item
        rows.append(
            {
                "kernel": "ss2d_scan_triton forward",
                "dtype": str(dtype).replace("torch.", ""),
                "ms": ms,
                "min_bytes": moved,
                "effective_bytes_per_s": moved / (ms / 1e3),
                "fraction_of_h100": moved / (ms / 1e3) / H100_BYTES_PER_S,
            }
        )
    return rows


def bench_sigma(quick: bool) -> dict[str, Any]:
    from bench_physics import generic_sigma  # benchmarks/ is on sys.path when run as a script
    from sigma_compiled import sigma_depth_mm_compiled  # benchmarks/ is on sys.path when run as a script

    from tofdenoise.physics.calibration import default_calibration
    from tofdenoise.physics.uncertainty import sigma_depth_mm

    calib = default_calibration()
    g = torch.Generator(device="cuda").manual_seed(0)
    h, w = 480, 640
    depth = 300.0 + 2400.0 * torch.rand(h, w, device="cuda", generator=g)
    signal = calib.signal_min_e + (calib.signal_max_e - calib.signal_min_e) * torch.rand(
        h, w, device="cuda", generator=g
    )

    def generic():  # the sums+inv route of bench_physics, on the GPU
        return generic_sigma(depth, signal, calib)

    ref = sigma_depth_mm(depth.double(), signal.double(), calib)
    eager = sigma_depth_mm(depth, signal, calib)
    t0 = time.perf_counter()
    fused = sigma_depth_mm_compiled(depth, signal, calib)
    torch.cuda.synchronize()
    compile_s = time.perf_counter() - t0
    reps = 20 if quick else 100
    out = {
        "compile_s": compile_s,
        "generic_ms": time_cuda(generic, reps),
        "eager_ms": time_cuda(lambda: sigma_depth_mm(depth, signal, calib), reps),
        "fused_ms": time_cuda(lambda: sigma_depth_mm_compiled(depth, signal, calib), reps),
        "max_rel_err_eager": float(((eager.double() - ref) / ref).abs().max()),
        "max_rel_err_fused": float(((fused.double() - ref) / ref).abs().max()),
        "max_rel_err_generic": float(((generic().double() - ref) / ref).abs().max()),
    }
    out["ratio_generic_over_eager"] = out["generic_ms"] / out["eager_ms"]
    out["ratio_generic_over_fused"] = out["generic_ms"] / out["fused_ms"]
    out["fused_mpx_s"] = h * w / 1e3 / out["fused_ms"]
    return out


@contextlib.contextmanager
def ss2d_route(route: str):
    """DVSS's SS2D layers on ``route``: "fused" (the default: the kernels read the four directions in place) or
    "cross" (cross_scan copies, then the plain scan; the same numbers)."""
    from tofdenoise.models.ss2d import SS2D

    if route not in ("fused", "cross"):
        raise ValueError(f"ss2d_route: fused or cross, got {route!r}")
    original = SS2D._spatial_scan
    if route == "cross":
        SS2D._spatial_scan = lambda self, x: None
    try:
        yield
    finally:
        SS2D._spatial_scan = original


def _bench_backbone(name: str, kwargs: dict[str, Any], size: int, quick: bool) -> dict[str, Any]:
    from tofdenoise.models.registry import build_backbone

    row: dict[str, Any] = {"backbone": name, "crop": size}
    net = build_backbone(name, in_channels=1, **kwargs).cuda()
    row["params_m"] = sum(p.numel() for p in net.parameters()) / 1e6
    opt = torch.optim.AdamW(net.parameters(), lr=2e-4)
    x = torch.randn(4, 1, size, size, device="cuda")
    target = torch.randn(4, 1, size, size, device="cuda")
    for precision in ("fp32", "bf16"):

        def step():
            opt.zero_grad(set_to_none=True)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bf16"):
                y = net(x)
            loss = (y.float() - target).abs().mean()
            loss.backward()
            opt.step()

        row[f"{precision}_ms_step"] = time_cuda(step, repeats=3 if quick else 10)
        row[f"{precision}_peak_mib"] = _peak_mib(step)
    net.eval()
    frame = torch.randn(1, 1, 480, 640, device="cuda")
    with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16):
        row["infer_480x640_bf16_ms"] = time_cuda(lambda: net(frame), repeats=3 if quick else 10)
        if name.startswith("dvss"):  # the same frame with the blocks on channels-last memory (the CPU's default)
            from tofdenoise.models import dvss as dvss_module

            torch.nn.init.normal_(net.head.weight, std=0.1)  # the zero-initialised head would hide any difference
            default_layout = net(frame).float()
            devices = dvss_module.CHANNELS_LAST_INFERENCE_DEVICES
            dvss_module.CHANNELS_LAST_INFERENCE_DEVICES = (*devices, "cuda")
            try:
                row["infer_480x640_bf16_channels_last_ms"] = time_cuda(lambda: net(frame), repeats=3 if quick else 10)
                row["channels_last_max_diff"] = float((net(frame).float() - default_layout).abs().max())
            except Exception as exc:  # the row's other figures stand
                row["channels_last_error"] = f"{type(exc).__name__}: {exc}"
            finally:
                dvss_module.CHANNELS_LAST_INFERENCE_DEVICES = devices
    return row


def bench_backbones(quick: bool) -> list[dict[str, Any]]:
    size = 128 if quick else 320
    rows = []
    dvss = {"width": 32, "enc_blocks": [1, 1, 2], "bottleneck_blocks": 2}  # configs/backbone/dvss.yaml
    for name, kwargs, route in (
        ("unet", {}, None),
        ("restormer", {}, None),
        ("dvss", dvss, "fused"),
        ("dvss", dvss, "cross"),
    ):
        try:
            with ss2d_route(route or "fused"):
                rows.append({**_bench_backbone(name, kwargs, size, quick), **({"ss2d_route": route} if route else {})})
        except Exception as exc:  # report and go on with the next backbone
            rows.append({"backbone": name, "crop": size, "error": f"{type(exc).__name__}: {exc}"})
            traceback.print_exc()
        torch.cuda.empty_cache()
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    p.add_argument("--json", default=None, help="also write the results to this JSON file")
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_gpu: skipped (no CUDA device)")
        return 0
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    print(f"torch {torch.__version__}, device {torch.cuda.get_device_name()}")
    results: dict[str, Any] = {"device": torch.cuda.get_device_name(), "torch": torch.__version__}
    sections = (("sigma", bench_sigma), ("scan", bench_scan), ("ss2d", bench_ss2d), ("backbones", bench_backbones))
    for name, fn in sections:
        try:
            results[name] = fn(args.quick)
        except Exception as exc:
            results[name] = {"error": f"{type(exc).__name__}: {exc}"}
            traceback.print_exc()
        print(f"\n### {name}\n{json.dumps(results[name], indent=1)}", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
