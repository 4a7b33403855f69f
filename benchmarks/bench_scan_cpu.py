"""Native CPU selective scan (issue 11): the kernel against the chunked PyTorch scan and the CPU's roofline,
the DVSS training step against the U-Net's, and full-resolution DVSS inference memory -- side by side.

    python benchmarks/bench_scan_cpu.py [--quick] [--threads 2] [--rounds 3]

1. Selective scan forward and forward+backward at the DVSS level-0 size of a 64x64 batch-4 training step
   (batch 4, 4 directions x 64 channels = 256 channels in 4 groups, L = 4096, N = 16, softplus + bias + D):
   ``selective_scan(backend="cpu")`` vs ``backend="torch"`` (chunked), rounds alternating the order; and
   the SS2D route (``ss2d_scan_cpu``: channels-last input, the 4 directions read in place, merged output).
   Throughput in state updates per second (batch x channels x L x N per forward) against the roofline: the
   measured peak of the kernel's own exp + 3 multiply-add loop (same compiler flags, same threads).
2. Training step (DepthRestorer input normalisation + backbone + L_full + backward + AdamW), 64x64 crops,
   batch 4, one pre-loaded batch: U-Net vs DVSS (native scan) vs DVSS on the pure-PyTorch route, steps
   interleaved round by round so that load from other processes hits all alike; ratio DVSS / U-Net. Once with
   freed memory kept (what ``tofdenoise train`` runs with) and once with glibc's default allocator, each in a
   fresh process (``--step-allocator``).
3. Full-resolution inference, 480x640 batch 1 (``--quick``: 240x320), U-Net and DVSS, each in a fresh subprocess
   with glibc's allocator as it starts and with freed memory kept (``tofdenoise.allocator``, what the ``tofdenoise``
   command runs with): time and peak resident memory above the pre-run baseline (bench_models' method).

``--baseline REV`` also builds the kernel source of git revision REV under an extension name of its own and puts it
next to today's in every part: the SS2D route's forward at DVSS level 0 of a 480x640 frame (batch 1, 64 channels,
L = 307200; ``--quick``: 240x320) and forward+backward at the training size, the training step, and the inference
frame (the baseline in its own subprocess).

Times are wall clock (medians over rounds); on a shared machine the ratios, measured side by side, are the
figures to compare. The scan rows also give process CPU time, steadier when other jobs share the cores.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))


CPU_TIMES: dict[int, float] = {}  # id(fn) -> process CPU seconds of its best wall-clock repetition


def _time(fn, reps: int = 1) -> float:
    """Best wall-clock seconds over ``reps`` runs (its process CPU time is kept in CPU_TIMES)."""
    best = float("inf")
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall = time.perf_counter() - t0
        if wall < best:
            best, CPU_TIMES[id(fn)] = wall, time.process_time() - c0
    return best


def roofline_updates_per_s(seconds: float = 1.0) -> tuple[float, float]:
    """Measured peak of the native kernel's exp + 3 multiply-add loop (the scan's floor per state update), using
    torch's threads: (updates per second, seconds spent)."""
    import torch

    from tofdenoise.models.scan.cpu import load_extension

    ext = load_extension()
    if ext is None:
        raise RuntimeError("roofline: the native CPU kernel is not available")
    tasks = 8 * torch.get_num_threads()
    repeats = 2000
    ext.roofline_loop(tasks, 10)  # warm-up
    while True:
        t0 = time.perf_counter()
        ext.roofline_loop(tasks, repeats)
        dt = time.perf_counter() - t0
        if dt > 0.2 * seconds or repeats > 10**8:
            break
        repeats *= 4
    return tasks * 256 * repeats / dt, dt


def scan_inputs(batch: int, groups: int, dg: int, length: int, n: int):
    import torch

    g = torch.Generator().manual_seed(0)
    dim = groups * dg
    u = torch.randn(batch, dim, length, generator=g)
    delta = 0.5 * torch.randn(batch, dim, length, generator=g) - 4.0
    A = -torch.arange(1, n + 1.0).repeat(dim, 1)
    B = torch.randn(batch, groups, n, length, generator=g)
    C = torch.randn(batch, groups, n, length, generator=g)
    D = torch.ones(dim)
    bias = 0.1 * torch.randn(dim, generator=g)
    return [t.requires_grad_() for t in (u, delta, A, B, C, D, bias)]


BASELINE: dict = {}  # "source": path of the baseline kernel source, "ext": its extension (--baseline)


def baseline_source(rev: str) -> str:
    """The kernel source of git revision ``rev`` written to a temporary file (kept for the subprocesses)."""
    import subprocess
    import tempfile

    rel = "src/tofdenoise/models/scan/csrc/selective_scan_cpu.cpp"
    text = subprocess.run(
        ["git", "show", f"{rev}:{rel}"], cwd=HERE.parent, capture_output=True, text=True, check=True
    ).stdout
    fd, path = tempfile.mkstemp(prefix="selective_scan_cpu_baseline_", suffix=".cpp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    return path


def ss2d_inputs(batch: int, side_h: int, side_w: int, dg: int, n: int = 16, r: int = 2):
    """SS2D-route inputs as SS2D hands them over: x (b, L, dg), raw steps (b, L, 4 dg), B / C slices of an x_proj
    output (b, L, 4, r + 2N), A = -(1..N), D = 1, a small bias."""
    import torch

    g = torch.Generator().manual_seed(0)
    length = side_h * side_w
    x = torch.randn(batch, length, dg, generator=g)
    dts = 0.5 * torch.randn(batch, length, 4 * dg, generator=g) - 3.0
    x_dbl = torch.randn(batch, length, 4, r + 2 * n, generator=g)
    A = -torch.arange(1, n + 1.0).repeat(4 * dg, 1)
    D, bias = torch.ones(4 * dg), 0.1 * torch.randn(4 * dg, generator=g)
    return x, dts, A, x_dbl[..., r : r + n], x_dbl[..., r + n :], D, bias


def bench_baseline_scan(args) -> None:
    """Today's kernel vs the baseline's on the SS2D route, process CPU time and wall, interleaved."""
    import torch

    from tofdenoise.models.scan import cpu as scan_cpu

    cur, base = scan_cpu.load_extension(), BASELINE["ext"]
    fh, fw = (240, 320) if args.quick else (480, 640)
    cases = [
        (f"forward, inference: 1 x {fh}x{fw}, 64 channels (DVSS level 0 of a frame)", (1, fh, fw, 64), False),
        ("forward+backward: 4 x 64x64, 64 channels (DVSS level 0 of a training step)", (4, 64, 64, 64), True),
    ]
    print(
        f"\n### SS2D route, today's kernel vs baseline {args.baseline}; {args.rounds + 2} rounds, order alternating; "
        f"threads {torch.get_num_threads()}"
    )
    print("| case | baseline CPU (ms) | today CPU (ms) | CPU ratio | baseline wall (ms) | today wall (ms) | ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for label, (b, h, w, dg), backward in cases:
        x, dts, A, B, C, D, bias = ss2d_inputs(b, h, w, dg)
        dy = torch.randn(b, h * w, dg, generator=torch.Generator().manual_seed(1))
        args_ = (x, dts, A, B, C, D, bias, True, True, h, w)

        def run(ext, args_=args_, backward=backward, dy=dy):
            y, ck = ext.scan_fwd(*args_, scan_cpu.CHUNK if backward else 0)
            if backward:
                ext.scan_bwd(*args_, scan_cpu.CHUNK, ck, dy)

        cpu_t: dict[str, list[float]] = {"base": [], "cur": []}
        wall_t: dict[str, list[float]] = {"base": [], "cur": []}
        run(cur), run(base)
        for r in range(args.rounds + 2):
            for key, ext in (("base", base), ("cur", cur)) if r % 2 == 0 else (("cur", cur), ("base", base)):
                t0, c0 = time.perf_counter(), time.process_time()
                run(ext)
                wall_t[key].append(time.perf_counter() - t0)
                cpu_t[key].append(time.process_time() - c0)
        med = {k: statistics.median(v) for k, v in (*cpu_t.items(), *(("w" + k, v) for k, v in wall_t.items()))}
        print(
            f"| {label} | {med['base'] * 1e3:.1f} | {med['cur'] * 1e3:.1f} | {med['base'] / med['cur']:.2f} | "
            f"{med['wbase'] * 1e3:.1f} | {med['wcur'] * 1e3:.1f} | {med['wbase'] / med['wcur']:.2f} |"
        )


def bench_scan(args) -> None:
    import torch

    from tofdenoise.models import selective_scan
    from tofdenoise.models.scan import cpu as scan_cpu

    batch, groups, dg, length, n = (4, 4, 64, 1024 if args.quick else 4096, 16)
    dim = groups * dg
    tensors = scan_inputs(batch, groups, dg, length, n)
    updates = batch * dim * length * n
    print(
        f"\n### Selective scan at DVSS level 0: batch {batch}, {groups} directions x {dg} channels, L = {length}, "
        f"N = {n}; {args.rounds} rounds, order alternating; threads {torch.get_num_threads()}"
    )

    def fwd(backend):
        with torch.no_grad():
            selective_scan(*tensors, True, backend=backend)

    dy = torch.randn(batch, dim, length, generator=torch.Generator().manual_seed(1))  # a dense upstream gradient

    def fwdbwd(backend):
        for t in tensors:
            t.grad = None
        selective_scan(*tensors, True, backend=backend).backward(dy)

    # SS2D route: channels-last x (b, L, dg), raw steps (b, L, 4 dg), B/C (b, L, 4, N), 4 directions over H x W
    side = int(round(length**0.5))
    u, delta, A, B, C, D, bias = (t.detach() for t in tensors)
    xs = u[:, :dg].transpose(1, 2).contiguous().requires_grad_()
    dts = delta.transpose(1, 2).contiguous().requires_grad_()
    Bs, Cs = (t.permute(0, 3, 1, 2).contiguous().requires_grad_() for t in (B, C))
    Ar, Dr, br = (t.clone().requires_grad_() for t in (A, D, bias))

    dy_cl = dy[:, :dg].transpose(1, 2).contiguous()

    def ss2d_fwdbwd():
        scan_cpu.ss2d_scan_cpu(xs, dts, Ar, Bs, Cs, Dr, br, side, side).backward(dy_cl)

    fwd("cpu")
    fwdbwd("cpu")
    rows: dict[str, list[float]] = {k: [] for k in ("cpu_f", "torch_f", "cpu_fb", "torch_fb", "ss2d_fb", "roof")}
    cpu_s: dict[str, list[float]] = {"cpu_fb": [], "torch_fb": []}
    for r in range(args.rounds):
        order = ("cpu", "torch") if r % 2 == 0 else ("torch", "cpu")
        for backend in order:
            rows[f"{backend}_f"].append(_time(lambda: fwd(backend), 2 if backend == "cpu" else 1))
            run = lambda: fwdbwd(backend)  # noqa: E731
            rows[f"{backend}_fb"].append(_time(run, 2 if backend == "cpu" else 1))
            cpu_s[f"{backend}_fb"].append(CPU_TIMES[id(run)])
        rows["ss2d_fb"].append(_time(ss2d_fwdbwd, 2))
        rows["roof"].append(roofline_updates_per_s(seconds=0.5)[0])
    med = {k: statistics.median(v) for k, v in rows.items()}
    roof = med["roof"]
    print("| route | forward (ms) | forward+backward (ms) | forward updates/s | fraction of roofline |")
    print("|---|---:|---:|---:|---:|")
    print(
        f'| native kernel (`backend="cpu"`) | {med["cpu_f"] * 1e3:.1f} | {med["cpu_fb"] * 1e3:.1f} | '
        f"{updates / med['cpu_f'] / 1e9:.2f} G | {updates / med['cpu_f'] / roof:.2f} |"
    )
    print(
        f'| chunked PyTorch (`backend="torch"`) | {med["torch_f"] * 1e3:.1f} | {med["torch_fb"] * 1e3:.1f} | '
        f"{updates / med['torch_f'] / 1e9:.3f} G | {updates / med['torch_f'] / roof:.3f} |"
    )
    print(
        f"| SS2D route (`ss2d_scan_cpu`, {side}x{side}, directions read in place) | - | "
        f"{med['ss2d_fb'] * 1e3:.1f} | - | - |"
    )
    print(
        f"roofline (exp + 3 FMA loop, same flags and threads): {roof / 1e9:.2f} G updates/s; "
        f"forward+backward at the roofline's pace would take ~3 forward passes = {3 * updates / roof * 1e3:.1f} ms"
    )
    ratios_f = [t / c for t, c in zip(rows["torch_f"], rows["cpu_f"])]
    ratios_fb = [t / c for t, c in zip(rows["torch_fb"], rows["cpu_fb"])]
    ratios_ss2d = [t / c for t, c in zip(rows["torch_fb"], rows["ss2d_fb"])]
    print(
        f"speed-up native / chunked: forward {statistics.median(ratios_f):.1f}x, forward+backward "
        f"{statistics.median(ratios_fb):.1f}x (per round: {', '.join(f'{v:.1f}' for v in ratios_fb)}) through the "
        f"(batch, dim, L) API; forward+backward on the SS2D route (the one DVSS runs) "
        f"{statistics.median(ratios_ss2d):.1f}x (per round: {', '.join(f'{v:.1f}' for v in ratios_ss2d)}); "
        f"target >= 8x"
    )
    ratios_cpu = [t / c for t, c in zip(cpu_s["torch_fb"], cpu_s["cpu_fb"])]
    print(
        f"forward+backward in process CPU time: native {statistics.median(cpu_s['cpu_fb']) * 1e3:.1f} ms, chunked "
        f"{statistics.median(cpu_s['torch_fb']) * 1e3:.1f} ms, ratio {statistics.median(ratios_cpu):.1f}x (the stable "
        f"measure on a shared machine with 1 thread; with more threads it counts OpenMP spin-waiting too)"
    )


def bench_step(args) -> None:
    """The training step under each C allocator setting, each in a fresh process of this script (mallopt is
    process-wide): freed memory kept, as ``tofdenoise train`` runs (tofdenoise.allocator), and glibc's default."""
    import subprocess

    if args.step_allocator != "both":
        return bench_step_here(args)
    for allocator in ("keep", "default"):
        cmd = [sys.executable, str(Path(__file__).resolve()), "--only", "step", "--step-allocator", allocator]
        cmd += ["--threads", str(args.threads), "--rounds", str(args.rounds)]
        cmd += ["--quick"] if args.quick else []
        cmd += ["--baseline", args.baseline] if args.baseline else []
        out = subprocess.run(cmd, capture_output=True, text=True, check=False)
        lines = [line for line in out.stdout.splitlines() if not line.startswith("# ")]
        print("\n".join(lines))
        if out.returncode != 0:
            print(f"step part ({allocator}) failed: {out.stderr.strip().splitlines()[-1:]}")
    return None


def bench_step_here(args) -> None:
    import torch
    from bench_training import backbone_kwargs, make_data, time_steps

    from tofdenoise.allocator import keep_freed_memory
    from tofdenoise.training.module import DepthRestorer

    kept = args.step_allocator == "keep" and keep_freed_memory()
    crop, batch = 64, 4
    print(
        f"\n### Training step, {crop}x{crop} crops, batch {batch}, L_full + AdamW, pre-loaded batch; "
        f"{args.rounds} rounds of interleaved steps; threads {torch.get_num_threads()}; "
        + ("freed memory kept (as `tofdenoise train` runs)" if kept else "glibc's default allocator")
    )
    import tempfile

    torch.manual_seed(0)  # the same batch in every run
    with tempfile.TemporaryDirectory() as cache:
        dm = make_data(crop, batch, 0, cache)
        fixed = next(iter(dm.train_dataloader()))
    from bench_models import use_scan_extension

    from tofdenoise.models import ss2d
    from tofdenoise.models.scan import cpu as scan_cpu

    today = scan_cpu.load_extension()
    # (backbone, backbone kwargs, kernel, dt projection fused into the kernel in training: ss2d.FUSE_DT_TRAINING)
    configs = [
        ("unet", {}, today, True),
        ("dvss", {}, today, True),
        ("dvss", {}, today, False),
        ("dvss", {"scan_backend": "torch"}, today, True),
    ]
    if args.quick:
        configs = configs[:3]
    if BASELINE:  # an older kernel source knows no fused training route
        configs.insert(3, ("dvss", {}, BASELINE["ext"], False))
    runs = []
    for name, extra, ext, fuse in configs:
        torch.manual_seed(0)
        model = DepthRestorer(backbone=name, backbone_kwargs={**backbone_kwargs(name), **extra}, loss="full")
        model.train()
        opt = torch.optim.AdamW(model.backbone.parameters(), lr=2e-4)
        use_scan_extension(ext)
        ss2d.FUSE_DT_TRAINING = fuse
        time_steps(model, opt, lambda: fixed, 1)  # warm-up (and the kernel build)
        label = name if not extra else f"{name} (PyTorch scan route)"
        if name == "dvss" and not fuse:
            label = f"{name} (dt projection as a batched product, FUSE_DT_TRAINING=False)"
        if ext is not today:
            label = f"{name} (baseline kernel {args.baseline}, dt projection as a product)"
        runs.append((label, model, opt, [], ext, [], fuse))
    for _ in range(args.rounds):
        for label, model, opt, times, ext, cpu, fuse in runs:
            use_scan_extension(ext)
            ss2d.FUSE_DT_TRAINING = fuse
            steps = 1 if "PyTorch" in label else 2
            c0 = time.process_time()
            times.append(min(time_steps(model, opt, lambda: fixed, steps)))
            cpu.append((time.process_time() - c0) / steps)
    use_scan_extension(today)
    ss2d.FUSE_DT_TRAINING = True
    base = statistics.median(runs[0][3])
    print("| backbone | step (s), median | / U-Net (per round) | process CPU per step (s) | CPU / U-Net (per round) |")
    print("|---|---:|---:|---:|---:|")
    for label, _, _, times, _, cpu, _ in runs:
        per_round = [t / u for t, u in zip(times, runs[0][3])]
        cpu_round = [c / u for c, u in zip(cpu, runs[0][5])]
        print(
            f"| {label} | {statistics.median(times):.3f} | {statistics.median(per_round):.2f} "
            f"({', '.join(f'{v:.2f}' for v in per_round)}) | {statistics.median(cpu):.3f} | "
            f"{statistics.median(cpu_round):.2f} ({', '.join(f'{v:.2f}' for v in cpu_round)}) |"
        )
    print(
        f"DVSS / U-Net ({'freed memory kept' if kept else 'glibc default'}) = "
        f"{statistics.median(runs[1][3]) / base:.2f} wall, "
        f"{statistics.median(runs[1][5]) / statistics.median(runs[0][5]):.2f} process CPU; target <= 3"
    )
    fused_ratio = statistics.median([f / p for f, p in zip(runs[1][3], runs[2][3])])
    print(f"DVSS step, dt projection fused into the kernel / as a batched product = {fused_ratio:.2f} (per round)")


def bench_inference(args) -> None:
    from bench_models import run_isolated

    h, w = (240, 320) if args.quick else (480, 640)
    print(
        f"\n### Inference {h}x{w}, batch 1, fresh subprocess per row (peak RSS above baseline): glibc's allocator "
        "as it starts, and with freed memory kept (tofdenoise.allocator, what the tofdenoise command runs with)"
    )
    print("| backbone, scan route | allocator | time (s) | peak memory (MiB) |")
    print("|---|---|---:|---:|")
    rows = [
        ("U-Net", "unet", {}, None, "default"),
        ("U-Net", "unet", {}, None, "keep"),
        ("DVSS, native kernel (auto)", "dvss", {}, None, "default"),
        ("DVSS, native kernel (auto)", "dvss", {}, None, "keep"),
        ("DVSS, per-pixel products on MKL (`POINTWISE_ONEDNN=False`)", "dvss", {}, None, "keep-mm"),
    ]
    if BASELINE:
        rows.append((f"DVSS, native kernel, baseline {args.baseline}", "dvss", {}, BASELINE["source"], "default"))
    if not args.quick and not args.no_torch_route:
        rows.append(("DVSS, PyTorch (`scan_backend=torch`)", "dvss", {"scan_backend": "torch"}, None, "default"))
    times: dict[tuple[str, str], float] = {}
    for label, name, kwargs, source, allocator in rows:
        case = {
            "kind": "backbone",
            "name": name,
            "mode": "fwd",
            "H": h,
            "W": w,
            "batch": 1,
            "reps": args.frame_reps,
            "single_run_above_s": 1e9,  # frame_reps > 1: the first frame is a warm-up
            "kwargs": kwargs,
            "scan_source": source,
            "allocator": allocator.removesuffix("-mm"),
            "pointwise": "mm" if allocator.endswith("-mm") else "onednn",
        }
        res = run_isolated(case, args.threads, timeout_s=1800, mem_cap_gib=12)
        kept = "freed memory kept" if allocator.startswith("keep") else "glibc default"
        if "error" in res:
            print(f"| {label} | {kept} | {res['error']} | - |")
        else:
            print(f"| {label} | {kept} | {res['time_s']:.2f} | {res['peak_mib']:.0f} |")
            if source is None and not kwargs:
                times[(name, allocator)] = res["time_s"]
    for allocator in ("default", "keep"):
        if ("dvss", allocator) in times and ("unet", allocator) in times:
            print(f"DVSS / U-Net ({allocator}) = {times[('dvss', allocator)] / times[('unet', allocator)]:.2f}")
    mm = times.get(("dvss", "keep-mm"))
    if mm is not None and ("dvss", "keep") in times:
        print(f"DVSS per-pixel products: oneDNN / MKL = {times[('dvss', 'keep')] / mm:.2f} (the default is oneDNN)")
    for name in ("unet", "dvss"):
        if (name, "default") in times and (name, "keep") in times:
            print(f"{name}: kept / default = {times[(name, 'keep')] / times[(name, 'default')]:.2f}")
    print("targets: DVSS frame <= 1.5 s (480x640); peak under 4096 MiB")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="L = 1024 scan, no PyTorch-route step, 240x320 inference")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2, the issue's setting)")
    p.add_argument("--rounds", type=int, default=None, help="interleaved rounds (default 3, --quick 2)")
    p.add_argument("--only", default="scan,step,inference", help="comma list of: scan, step, inference")
    p.add_argument("--baseline", default="", help="git revision whose kernel source runs next to today's")
    p.add_argument("--frame-reps", type=int, default=1, help="inference frames per route (median; after a warm-up)")
    p.add_argument("--no-torch-route", action="store_true", help="skip the (slow) PyTorch-route inference frame")
    p.add_argument(
        "--step-allocator",
        choices=("both", "keep", "default"),
        default="both",
        help="the training step with freed memory kept (as `tofdenoise train` runs), glibc's default, or both "
        "(default; each in a fresh process)",
    )
    args = p.parse_args(argv)
    args.rounds = args.rounds or (2 if args.quick else 3)
    import torch

    torch.set_num_threads(args.threads)
    from tofdenoise.models.scan.cpu import cpu_kernel_available

    print(
        f"# bench_scan_cpu: torch {torch.__version__}, threads {torch.get_num_threads()}, cpu count "
        f"{os.cpu_count()}, load average {os.getloadavg()[0]:.1f} (other processes share the machine)"
    )
    if not cpu_kernel_available():
        print("native CPU scan not available (build failed or disabled): nothing to compare")
        return 1
    if args.baseline:
        from bench_models import build_scan_source

        BASELINE["source"] = baseline_source(args.baseline)
        BASELINE["ext"] = build_scan_source(BASELINE["source"])
    parts = {"scan": bench_scan, "step": bench_step, "inference": bench_inference}
    if args.baseline and "scan" in args.only.split(","):
        bench_baseline_scan(args)
    for part in args.only.split(","):
        if part not in parts:
            p.error(f"--only: unknown part {part!r}; valid: {', '.join(parts)}")
        parts[part](args)
        sys.stdout.flush()
    print(f"# load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
