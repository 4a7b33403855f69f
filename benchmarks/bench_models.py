"""Backbone and selective-scan benchmarks (CPU), side by side in one run.

    python benchmarks/bench_models.py [--quick] [--threads N] [--only scan,block,backbones,bilateral,ss2d]

1. Selective scan, forward+backward, batch 1, 4 directions x d_inner 96 (dim 384), d_state 16, L = 25600
   (160 x 160): the chunked scan with recomputing backward vs a sequential loop whose hand-written backward
   stores every state. Ratios: time chunked / sequential (target <= 1) and peak memory sequential / chunked
   (target >= 3).
2. One DVSS block (width 48 -> d_inner 96, d_state 16) at 160 x 160, forward+backward, both scan backends.
3. Every trainable backbone (default kwargs): parameters; forward and forward+backward time and peak
   memory at 320 x 320, batch 4; forward time and peak memory at 480 x 640, batch 1.
4. The classical row (``bilateral``, no parameters, not in the default ``--only``): one 480 x 640 frame
   (depth + amplitude channels) per window radius of the default tuning grid's sigma_spatial_px.
5. ``--only ss2d`` (not in the default): where an SS2D block's inference time goes at each level of a 480 x 640 DVSS
   frame (default widths): process CPU time of each stage of ``SS2D._scan_spatial``'s route (in_proj, depthwise conv
   + SiLU with its layout copy, x_proj, the dt projection through the block-diagonal matrix, the native scan,
   out_norm * SiLU(z), out_proj) and of the whole block, median of 3 after a warm-up, in this process.

Peak memory: every case runs in a fresh subprocess; peak = VmHWM at the end (the process's resident-set
high-water mark) minus the resident set just before the timed work (after imports, model and inputs are
built). This counts every CPU allocation (torch's allocator is invisible to tracemalloc), including the
autograd graph; it is an upper bound when the allocator keeps freed pages.
Time: wall clock and process CPU time (user + system, all threads), median over repetitions after one
warm-up (large cases: one run, the first). On a shared machine, CPU time is the stable measure of the
work done (wall time includes waiting for the cores); the scan's time ratio is reported for both.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

BYTES_PER_MIB = 2**20


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_bytes() -> int:
    from tofdenoise.allocator import peak_rss_bytes  # VmHWM: ru_maxrss would start at the parent's size

    return peak_rss_bytes()


def _timed(fn, reps: int) -> list[tuple[float, float]]:
    """(wall seconds, process CPU seconds) per repetition."""
    times = []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    return times


#: a kernel source that knows chunk 0 ("no checkpoints": the inference forward, 9109c5f on) names this constant
CHUNK_ZERO_MARKER = b"INFERENCE_CHUNK"


def knows_chunk_zero(source: bytes) -> bool:
    """Whether a kernel source runs ``scan_fwd`` with chunk 0 as its inference forward (no checkpoints); an older
    one needs chunk >= 1."""
    return CHUNK_ZERO_MARKER in source


class _ChunkZeroAdapter:
    """An extension built from an older kernel source: forwards every call, but turns ``scan_fwd``'s chunk 0 (today's
    "no checkpoints" for inference) into ``CHUNK`` for sources that do not know it (``chunk_zero`` False: they need
    chunk >= 1, so their inference wrote checkpoints); a source that knows it runs its own inference forward. A
    source without the fused dt projection (``ss2d_fwd_lowrank``, f99439f) gets the projection it did before: a
    batched product, then its SS2D forward; and a source without the fused output stage (``ss2d_out_gate``) torch's
    layer_norm and silu, as SS2D ran them before."""

    def __init__(self, ext, chunk: int, chunk_zero: bool = False) -> None:
        self._ext, self._chunk, self._chunk_zero = ext, chunk, chunk_zero

    def scan_fwd(self, *args):
        args = list(args)
        if args[-1] < 1 and not self._chunk_zero:
            args[-1] = self._chunk
        return self._ext.scan_fwd(*args)

    def ss2d_fwd_lowrank(self, x, dt_low, dt_weight, A, B, C, D, bias, height, width):
        if hasattr(self._ext, "ss2d_fwd_lowrank"):
            return self._ext.ss2d_fwd_lowrank(x, dt_low, dt_weight, A, B, C, D, bias, height, width)
        from tofdenoise.models.ss2d import dt_projection

        b, length, k, r = dt_low.shape
        weight = dt_weight.view(k, -1, r)
        delta = dt_projection(dt_low.reshape(b * length, k, r), weight).view(b, length, -1)
        return self.scan_fwd(x, delta, A, B, C, D, bias, True, True, height, width, 0)[0]

    def ss2d_out_gate(self, y, z, weight, bias, eps):
        if hasattr(self._ext, "ss2d_out_gate"):
            return self._ext.ss2d_out_gate(y, z, weight, bias, eps)
        import torch.nn.functional as F

        return y.copy_(F.layer_norm(y, weight.shape, weight, bias, eps) * F.silu(z))

    def __getattr__(self, name):
        return getattr(self._ext, name)


def build_scan_source(path: str):
    """The native CPU scan compiled from the C++ source ``path`` (e.g. an older commit's, for a side-by-side
    baseline) under an extension name of its own, with today's flags; None when it cannot be built."""
    import hashlib
    from pathlib import Path

    from torch.utils import cpp_extension

    from tofdenoise.models.scan import cpu as scan_cpu

    data = Path(path).read_bytes()
    digest = hashlib.sha256(data + " ".join(scan_cpu.CFLAGS + scan_cpu.LDFLAGS).encode()).hexdigest()[:12]
    scan_cpu._ninja_on_path()
    ext = cpp_extension.load(
        name=f"tofdenoise_scan_cpu_src_{digest}",
        sources=[str(path)],
        extra_cflags=scan_cpu.CFLAGS,
        extra_ldflags=scan_cpu.LDFLAGS,
        verbose=False,
    )
    return _ChunkZeroAdapter(ext, scan_cpu.CHUNK, chunk_zero=knows_chunk_zero(data))


def use_scan_extension(ext) -> None:
    """Route every later native CPU scan call of this process to ``ext`` (the scan calls ``load_extension()`` on
    each use)."""
    from tofdenoise.models.scan import cpu as scan_cpu

    def load_extension():
        return ext

    scan_cpu.load_extension = load_extension
    scan_cpu.cpu_kernel_available.cache_clear()


def _run_case(case: dict) -> dict:
    import torch

    torch.manual_seed(0)
    if case.get("allocator") == "keep":  # what the tofdenoise command runs with (tofdenoise.allocator)
        from tofdenoise.allocator import keep_freed_memory

        keep_freed_memory()
    if case.get("pointwise") == "mm":  # DVSS's per-pixel products on MKL, not oneDNN (models.common.pointwise)
        from tofdenoise.models import common

        common.POINTWISE_ONEDNN = False
    if case.get("scan_source"):  # a baseline kernel from another source (bench_scan_cpu.py --baseline)
        use_scan_extension(build_scan_source(case["scan_source"]))
    kind = case["kind"]
    if kind == "scan":
        from tofdenoise.models.scan import selective_scan_chunked, selective_scan_sequential

        dim, L, N, G = case["dim"], case["L"], 16, 4
        u = torch.randn(1, dim, L, requires_grad=True)
        delta = (0.5 * torch.randn(1, dim, L) - 4.0).requires_grad_()
        A = (-torch.arange(1, N + 1.0).repeat(dim, 1)).requires_grad_()
        B = torch.randn(1, G, N, L, requires_grad=True)
        C = torch.randn(1, G, N, L, requires_grad=True)
        D = torch.ones(dim, requires_grad=True)
        bias = torch.zeros(dim, requires_grad=True)
        impl = selective_scan_chunked if case["impl"] == "chunked" else selective_scan_sequential

        def fn():
            y = impl(u, delta, A, B, C, D, bias, True)
            y.sum().backward()

    elif kind == "block":
        from tofdenoise.models.dvss import DVSSBlock

        block = DVSSBlock(case["dim"], d_state=16, expand=2.0, scan_backend=case["backend"])
        x = torch.randn(1, case["dim"], case["size"], case["size"], requires_grad=True)

        def fn():
            block(x).square().mean().backward()

    elif kind == "backbone":
        from tofdenoise.models import build_backbone, count_parameters

        model = build_backbone(case["name"], **case.get("kwargs", {}))
        # depth (+ amplitude for a backbone that needs it: rcf's default in_channels is 2)
        x = torch.randn(case["batch"], getattr(model, "in_channels", 1), case["H"], case["W"])
        if case["mode"] == "fwd":
            model.eval()

            def fn():
                with torch.no_grad():
                    model(x)

        else:
            model.train()

            def fn():
                model.zero_grad(set_to_none=True)
                out = model(x)  # a deep-supervised backbone (rcf) returns its step predictions in training
                steps = out if isinstance(out, (list, tuple)) else [out]
                sum(o.square().mean() for o in steps).backward()

    elif kind == "bilateral":
        from tofdenoise.models import build_backbone

        model = build_backbone(
            "bilateral",
            in_channels=2,
            sigma_spatial_px=case["sigma_spatial_px"],
            sigma_depth_mm=80.0,
            amplitude_power=case["amplitude_power"],
        )
        depth = 10.0 + torch.rand(1, 1, case["H"], case["W"])
        x = torch.cat([depth, torch.rand(1, 1, case["H"], case["W"])], dim=1)

        def fn():
            with torch.no_grad():
                model(x)

    else:
        raise ValueError(f"unknown case kind {kind!r}")
    base = _rss_bytes()
    first = _timed(fn, 1)
    reps = case.get("reps", 3)
    times = first if first[0][0] > case.get("single_run_above_s", 5.0) or reps <= 1 else _timed(fn, reps)
    out = {
        "time_s": statistics.median(t for t, _ in times),
        "cpu_s": statistics.median(c for _, c in times),
        "peak_mib": (_peak_bytes() - base) / BYTES_PER_MIB,
    }
    if kind == "backbone":
        out["params"] = count_parameters(model)
    return out


def run_isolated(case: dict, threads: int | None, timeout_s: float, mem_cap_gib: float = 0.0) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--case", json.dumps(case)]
    if threads:
        cmd += ["--threads", str(threads)]
    if mem_cap_gib:
        cmd += ["--mem-cap-gib", str(mem_cap_gib)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout_s:.0f} s"}
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit code {proc.returncode}"]
    return {"error": tail[0][:160]}


def _fmt(res: dict, key: str, spec: str) -> str:
    width = int("".join(ch for ch in spec.split(".")[0] if ch.isdigit()) or 0)
    if "error" in res:
        if res["error"] == "skipped":
            return "-".rjust(width)
        return ("OOM" if "memory" in res["error"].lower() else "err").rjust(width)
    return format(res[key], spec)


def bench_scan(args) -> None:
    L = 2500 if args.quick else 25600
    dim = 384
    rounds = 2 if args.quick else 3
    print(
        f"\n### Selective scan, forward+backward: batch 1, 4 directions x d_inner 96 (dim {dim}), d_state 16, L = {L}"
    )
    print(f"# {rounds} rounds, each running both implementations in fresh subprocesses (alternating order)")
    runs: dict[str, list[dict]] = {"sequential": [], "chunked": []}
    ratios: dict[str, list[float]] = {"cpu": [], "wall": [], "mem": []}
    for r in range(rounds):
        order = ("sequential", "chunked") if r % 2 == 0 else ("chunked", "sequential")
        got = {
            impl: run_isolated(
                {"kind": "scan", "impl": impl, "dim": dim, "L": L, "reps": 1}, args.threads, args.timeout
            )
            for impl in order
        }
        for impl, res in got.items():
            runs[impl].append(res)
        if all("error" not in v for v in got.values()):
            seq, chk = got["sequential"], got["chunked"]
            ratios["cpu"].append(chk["cpu_s"] / seq["cpu_s"])
            ratios["wall"].append(chk["time_s"] / seq["time_s"])
            ratios["mem"].append(seq["peak_mib"] / max(chk["peak_mib"], 1e-9))
    print(f"{'implementation':<34}{'cpu_s':>9}{'wall_s':>9}{'peak_MiB':>10}   (medians over rounds)")
    labels = {"sequential": "sequential loop, stores all states", "chunked": "chunked, recomputing backward"}
    for impl, lst in runs.items():
        ok = [v for v in lst if "error" not in v]
        if not ok:
            print(f"{labels[impl]:<34}{'err':>9}{'err':>9}{'err':>10}  {lst[0].get('error', '')}")
            continue
        med = {k: statistics.median(v[k] for v in ok) for k in ("cpu_s", "time_s", "peak_mib")}
        print(f"{labels[impl]:<34}{med['cpu_s']:9.3f}{med['time_s']:9.3f}{med['peak_mib']:10.1f}")

    def show(values: list[float]) -> str:
        return f"{statistics.median(values):.2f} (per round: {', '.join(f'{v:.2f}' for v in values)})"

    if ratios["cpu"]:
        print(f"time ratio chunked/sequential, CPU time = {show(ratios['cpu'])}; target <= 1.00")
        print(f"time ratio chunked/sequential, wall time = {show(ratios['wall'])}")
        print(f"peak-memory ratio sequential/chunked = {show(ratios['mem'])}; target >= 3")


def bench_block(args) -> None:
    size = 48 if args.quick else 160
    print(f"\n### One DVSS block (width 48, d_inner 96, d_state 16) at {size}x{size}, batch 1, forward+backward")
    print(f"{'scan backend':<34}{'cpu_s':>9}{'wall_s':>9}{'peak_MiB':>10}")
    for backend in ("torch", "sequential"):
        r = run_isolated(
            {"kind": "block", "backend": backend, "dim": 48, "size": size, "reps": 3}, args.threads, args.timeout
        )
        name = "chunked (default)" if backend == "torch" else "sequential (stores all states)"
        print(f"{name:<34}{_fmt(r, 'cpu_s', '9.3f')}{_fmt(r, 'time_s', '9.3f')}{_fmt(r, 'peak_mib', '10.1f')}")


def bench_backbones(args) -> None:
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src"))
    from tofdenoise.models import trainable_backbones

    if args.quick:
        (h, w, b), (h2, w2) = (64, 64, 2), (96, 128)
    else:
        (h, w, b), (h2, w2) = (320, 320, 4), (480, 640)
    names = args.backbones.split(",") if args.backbones else trainable_backbones()
    print(f"\n### Backbones (default kwargs): fwd / fwd+bwd at {h}x{w} batch {b}; fwd at {h2}x{w2} batch 1")
    print(f"# memory cap per case {args.mem_cap_gib:g} GiB (address space): OOM = needs more than that")
    head = (
        f"{'backbone':<18}{'params':>10}{'fwd_s':>9}{'fwd_MiB':>9}{'fwdbwd_s':>10}{'fwdbwd_MiB':>11}"
        f"{f'fwd{h2}x{w2}_s':>14}{'MiB':>8}"
    )
    print(head)
    errors = []
    rows = [(name, {}, True) for name in names]
    if "dvss" in names:  # activation checkpointing: the DVSS setting that fits in memory for training
        rows.insert(names.index("dvss") + 1, ("dvss", {"checkpoint": True}, False))
    for name, kwargs, full in rows:
        label = name + ("+ckpt" if kwargs.get("checkpoint") else "")
        common = {"kind": "backbone", "name": name, "kwargs": kwargs, "reps": 2, "single_run_above_s": 3.0}
        run = lambda case: run_isolated(case, args.threads, args.timeout, args.mem_cap_gib)  # noqa: E731
        f = run({**common, "mode": "fwd", "H": h, "W": w, "batch": b}) if full else {"error": "skipped"}
        fb = run({**common, "mode": "fwdbwd", "H": h, "W": w, "batch": b})
        big = run({**common, "mode": "fwd", "H": h2, "W": w2, "batch": 1}) if full else {"error": "skipped"}
        params = f.get("params", fb.get("params", 0))
        print(
            f"{label:<18}{params:>10,}{_fmt(f, 'time_s', '9.2f')}{_fmt(f, 'peak_mib', '9.0f')}"
            f"{_fmt(fb, 'time_s', '10.2f')}{_fmt(fb, 'peak_mib', '11.0f')}"
            f"{_fmt(big, 'time_s', '14.2f')}{_fmt(big, 'peak_mib', '8.0f')}",
            flush=True,
        )
        errors += [
            f"{label} {m}: {r['error']}"
            for m, r in (("fwd", f), ("fwdbwd", fb), ("fwd-large", big))
            if "error" in r and r["error"] != "skipped"
        ]
    for e in errors:
        print(f"# {e}")


def bench_ss2d_stages(args) -> None:
    import torch

    from tofdenoise.models.scan.cpu import cpu_kernel_available

    if args.threads:
        torch.set_num_threads(args.threads)
    if not cpu_kernel_available():
        print("\n### SS2D stages: the native CPU scan is not available; skipped")
        return
    h0, w0 = (120, 160) if args.quick else (480, 640)
    print(
        f"\n### SS2D stages at each level of a {h0}x{w0} DVSS frame (width 32), inference, batch 1: process CPU "
        f"time (ms), median of 3; threads {torch.get_num_threads()}, load average {os.getloadavg()[0]:.1f}"
    )
    names = [
        "in_proj",
        "conv3x3+SiLU",
        "x_proj",
        "dt_proj (block_diag)",
        "scan",
        "out_norm*SiLU(z)",
        "out_proj",
        "whole SS2D",
    ]
    print("| level (dim, H x W, dt_rank) | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for level in range(4):
        dim, h, w = 32 * 2**level, h0 // 2**level, w0 // 2**level
        row, r = _ss2d_stage_times(dim, h, w)
        print(f"| {level} ({dim}, {h}x{w}, {r}) | " + " | ".join(f"{v:.0f}" for v in row) + " |", flush=True)


def _ss2d_stage_times(dim: int, h: int, w: int) -> tuple[list[float], int]:
    """CPU ms of each stage of an SS2D block (default settings, width ``dim``) on a (1, h, w, dim) input; dt_rank."""
    import torch
    import torch.nn.functional as F

    from tofdenoise.models.scan.cpu import ss2d_scan_cpu
    from tofdenoise.models.ss2d import SS2D

    def cpu_ms(fn) -> float:
        fn()
        times = []
        for _ in range(3):
            c0 = time.process_time()
            fn()
            times.append(time.process_time() - c0)
        return statistics.median(times) * 1e3

    torch.manual_seed(0)
    m = SS2D(dim).eval()
    x = torch.randn(1, h, w, dim)
    k, n, r, di, length = m.directions, m.d_state, m.dt_rank, m.d_inner, h * w
    w_x = m.x_proj_weight.reshape(k * (r + 2 * n), di).t()
    with torch.no_grad():
        xz = m.in_proj(x)
        xi, z = xz.chunk(2, dim=-1)

        def conv():
            a = xi.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
            return F.silu(m.conv(a)).permute(0, 2, 3, 1).contiguous()

        xs = conv().view(1, length, di)
        x_dbl = (xs @ w_x).view(1, length, k, r + 2 * n)
        dt_block = torch.block_diag(*m.dt_projs_weight.transpose(1, 2))
        dts = x_dbl[..., :r].reshape(1, length, k * r) @ dt_block
        A, D, bias = m._scan_params()
        scan_args = (xs, dts, A, x_dbl[..., r : r + n], x_dbl[..., r + n :], D, bias, h, w)
        y = ss2d_scan_cpu(*scan_args).view(1, h, w, di)
        yz = m.out_norm(y) * F.silu(z)
        stages = [
            lambda: m.in_proj(x),
            conv,
            lambda: xs @ w_x,
            lambda: x_dbl[..., :r].reshape(1, length, k * r) @ dt_block,
            lambda: ss2d_scan_cpu(*scan_args),
            lambda: m.out_norm(y) * F.silu(z),
            lambda: m.out_proj(yz),
            lambda: m(x),
        ]
        return [cpu_ms(fn) for fn in stages], r


def bench_bilateral(args) -> None:
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src"))
    from tofdenoise.models.bilateral import default_radius_px

    h, w = (96, 128) if args.quick else (480, 640)
    print(f"\n### Classical row: joint bilateral filter, one {h}x{w} frame (no parameters, forward only)")
    print(f"{'sigma_s_px':>10}{'radius':>8}{'gamma':>7}{'time_s':>9}{'cpu_s':>8}{'MiB':>7}")
    for ss in (1.0, 1.5, 2.0, 3.0):
        for gamma in (0.0, 1.0):
            res = run_isolated(
                {"kind": "bilateral", "sigma_spatial_px": ss, "amplitude_power": gamma, "H": h, "W": w, "reps": 3},
                args.threads,
                args.timeout,
                args.mem_cap_gib,
            )
            print(
                f"{ss:>10g}{default_radius_px(ss):>8}{gamma:>7g}{_fmt(res, 'time_s', '9.3f')}"
                f"{_fmt(res, 'cpu_s', '8.3f')}{_fmt(res, 'peak_mib', '7.0f')}",
                flush=True,
            )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes: a fast smoke run")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads per case (default: torch's)")
    p.add_argument(
        "--only", default="scan,block,backbones", help="comma list of: scan, block, backbones, bilateral, ss2d"
    )
    p.add_argument("--backbones", default="", help="comma list of backbone names (default: all registered)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed per case")
    p.add_argument(
        "--mem-cap-gib",
        type=float,
        default=12.0,
        help="address-space cap per backbone case (fails with OOM instead of exhausting the machine)",
    )
    p.add_argument("--case", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.case and args.mem_cap_gib:
        cap = int(args.mem_cap_gib * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    if args.case:
        print("RESULT " + json.dumps(_run_case(json.loads(args.case))), flush=True)
        return 0
    print(
        f"# bench_models: torch {torch.__version__}, threads per case {args.threads or torch.get_num_threads()}, "
        f"{'quick' if args.quick else 'full'} sizes; every case in its own subprocess",
        flush=True,
    )
    parts = {
        "scan": bench_scan,
        "block": bench_block,
        "backbones": bench_backbones,
        "bilateral": bench_bilateral,
        "ss2d": bench_ss2d_stages,
    }
    for part in args.only.split(","):
        if part not in parts:
            p.error(f"--only: unknown part {part!r}; valid: {', '.join(parts)}")
        parts[part](args)
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
