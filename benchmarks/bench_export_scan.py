"""The ONNX export scan alone in onnxruntime against PyTorch's native CPU scan kernel, per form and state budget (CPU).

    python benchmarks/bench_export_scan.py [--quick] [--threads N] [--length L] [--repeats R]
        [--forms steps,chunked] [--state-elems 65536,262144,...] [--exporter torchscript|dynamo] [--delta-scale S]
        [--provider cpu|cuda]

One selective scan of the shape of the default DVSS's first level (batch 1, dim 4 x 64 = 256 channels of the four
directions, N = 16, 4 groups of B/C, ``--length`` positions; 480 x 640 is L = 307200, the default 19200 is a
quarter of a 240 x 320 frame's level): the native kernel (``selective_scan(..., backend="cpu")``) against the
export scan (``models/scan/export.py``) exported alone and run by onnxruntime's CPU provider, once per form
(``steps``: one loop step per position of a lane; ``chunked``: one per chunk of 16 positions, behind its exponent
guard) and state budget ``state_elems`` (state elements per loop step; the lanes are ``state_elems // (dim x N)``).
The routes are timed interleaved: after one warm-up run each, ``--repeats`` rounds run every route once in turn, and
the median of a route's rounds is printed, so a change of the machine's load reaches every route alike. ns per state
element = time / (dim x N x L), the unit that makes levels and frame sizes comparable; RSS rise is how far the
process's resident memory rose above its level at the start of the route's warm-up run (Linux: ``VmHWM`` reset
before it, less ``VmRSS``). ``--delta-scale`` multiplies delta before
the softplus's bias (a large value fails the chunked form's guard: its rows then time the fallback). ``--quick``:
L = 4800, budget 2^18, 3 rounds.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

DIM, N, GROUPS = 256, 16, 4


def _reset_peak_rss() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _rss_mib(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak since the last reset) of this process in MiB; NaN off Linux."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _peak_above_start(fn) -> tuple[object, float]:
    """``fn()`` and how far the process's resident memory rose above its level at the start while it ran (MiB)."""
    _reset_peak_rss()
    start = _rss_mib("VmRSS")
    out = fn()
    return out, _rss_mib("VmHWM") - start


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--length", type=int, default=19200)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--forms", default="steps,chunked")
    p.add_argument("--state-elems", default="65536,262144,1048576")
    p.add_argument("--exporter", choices=("torchscript", "dynamo"), default="torchscript")
    p.add_argument("--delta-scale", type=float, default=1.0)
    p.add_argument("--chunk", type=int, default=None, help="positions per chunk of the chunked form")
    p.add_argument(
        "--provider",
        choices=("cpu", "cuda"),
        default="cpu",
        help="onnxruntime's execution provider for the export scan (cuda: its inputs are copied to the GPU in each "
        "timed run; the PyTorch row stays the native CPU kernel, the reference of every max diff)",
    )
    args = p.parse_args()
    warnings.filterwarnings("ignore")
    import numpy as np
    import onnx
    import onnxruntime as ort
    import torch

    from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs
    from tofdenoise.models.scan import selective_scan
    from tofdenoise.models.scan.export import (
        EXPORT_SCAN_CHUNK,
        export_chunk_lanes,
        export_scan_lanes,
        selective_scan_export,
    )

    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    length = 4800 if args.quick else args.length
    repeats = 3 if args.quick else args.repeats
    budgets = [262144] if args.quick else [int(v) for v in args.state_elems.split(",")]
    forms = args.forms.split(",")
    chunk = args.chunk or EXPORT_SCAN_CHUNK
    gen = torch.Generator().manual_seed(0)
    A = -torch.arange(1, N + 1, dtype=torch.float32).repeat(DIM, 1)  # A_log = log(1..N), as initialised
    D, bias = torch.ones(DIM), 0.5 * torch.randn(DIM, generator=gen) - 3.0
    u, delta = (torch.randn(1, DIM, length, generator=gen) for _ in range(2))
    delta = delta * args.delta_scale
    B, C = (torch.randn(1, GROUPS, N, length, generator=gen) for _ in range(2))
    elems = DIM * N * length
    names = ["u", "delta", "B", "C"]
    feeds = dict(zip(names, (x.numpy() for x in (u, delta, B, C))))
    print(
        f"scan dim {DIM}, N {N}, groups {GROUPS}, L {length}; torch/onnxruntime threads {threads}; {args.exporter}; "
        f"onnxruntime provider {args.provider}"
    )

    def export(form: str, budget: int):
        class Scan(torch.nn.Module):
            def forward(self, u, delta, B, C):
                return selective_scan_export(
                    u, delta, A, B, C, D, bias, True, state_elems=budget, form=form, chunk=chunk
                )

        small = (u[..., :37], delta[..., :37], B[..., :37], C[..., :37])
        if args.exporter == "dynamo":
            n = torch.export.Dim("L")
            with torch.no_grad():
                program = torch.onnx.export(
                    Scan().eval(), small, dynamo=True, dynamic_shapes=({2: n}, {2: n}, {3: n}, {3: n}),
                    input_names=names, opset_version=18, verbose=False,
                )  # fmt: skip
            return program.model_proto
        path = Path(f"/tmp/bench_export_scan_{form}_{budget}.onnx")
        torch.onnx.export(
            Scan(), small, str(path), dynamo=False, input_names=names, opset_version=18,
            dynamic_axes={"u": {2: "L"}, "delta": {2: "L"}, "B": {3: "L"}, "C": {3: "L"}},
        )  # fmt: skip
        proto = onnx.load(str(path))
        path.unlink()
        sequences_to_scan_outputs(proto.graph)
        return proto

    with torch.no_grad():
        ref = selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu").numpy()
    routes = {"PyTorch native kernel": (lambda: selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu"), "-")}
    info = {}
    for form in forms:
        for budget in budgets:
            options = ort.SessionOptions()
            options.intra_op_num_threads = threads
            proto = export(form, budget)
            providers = ["CUDAExecutionProvider"] if args.provider == "cuda" else ["CPUExecutionProvider"]
            if args.provider == "cuda" and "CUDAExecutionProvider" not in ort.get_available_providers():
                raise SystemExit("bench_export_scan: --provider cuda: this onnxruntime has no CUDAExecutionProvider")
            sess = ort.InferenceSession(proto.SerializeToString(), options, providers=providers)
            if sess.get_providers()[0] != providers[0]:
                raise SystemExit(f"bench_export_scan: onnxruntime did not start {providers[0]}: {sess.get_providers()}")
            name = f"onnxruntime ({args.provider}) export scan, {form}"
            key = f"{name} @ {budget}"
            routes[key] = (lambda sess=sess: sess.run(None, feeds), budget)
            out, rss = _peak_above_start(lambda sess=sess: sess.run(None, feeds)[0])
            diff = float(np.abs(out - ref).max())
            if form == "chunked":
                lanes = export_chunk_lanes(DIM * N, length, budget, chunk)
            else:
                lanes = export_scan_lanes(DIM * N, length, budget)
            info[key] = (budget, lanes, diff, rss)
    with torch.no_grad():
        info["PyTorch native kernel"] = ("-", "-", 0.0, _peak_above_start(routes["PyTorch native kernel"][0])[1])
    times: dict[str, list[float]] = {key: [] for key in routes}
    with torch.no_grad():
        for _ in range(repeats):
            for key, (fn, _) in routes.items():
                times[key].append(_timed(fn))
    print(
        "| route | state elems per step | lanes | median time (s) | ns per state element | max diff | RSS rise (MiB) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for key in routes:
        budget, lanes, diff, rss = info[key]
        t = statistics.median(times[key])
        label = key.split(" @ ")[0]
        print(f"| {label} | {budget} | {lanes} | {t:.3f} | {t / elems * 1e9:.2f} | {diff:.1e} | {rss:.0f} |")


if __name__ == "__main__":
    main()
