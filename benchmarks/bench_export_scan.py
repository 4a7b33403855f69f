"""The ONNX export scan alone in onnxruntime against PyTorch's native CPU scan kernel, per state budget (CPU).

    python benchmarks/bench_export_scan.py [--quick] [--threads N] [--length L] [--state-elems 65536,262144,...]

One selective scan of the shape of the default DVSS's first level (batch 1, dim 4 x 64 = 256 channels of the four
directions, N = 16, 4 groups of B/C, ``--length`` positions; 480 x 640 is L = 307200, the default 19200 is a
quarter of a 240 x 320 frame's level): the native kernel (``selective_scan(..., backend="cpu")``) against the
export scan (``models/scan/export.py``) exported alone and run by onnxruntime's CPU provider, once per state budget
``state_elems`` (elements per loop step; the lanes are ``state_elems // (dim x N)``). Time = the second of two runs;
ns per state element = time / (dim x N x L), the unit that makes levels and frame sizes comparable; peak RSS is the
process's high-water mark, reset before each route (Linux). ``--quick``: L = 4800 and two budgets.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

DIM, N, GROUPS = 256, 16, 4


def _reset_peak_rss() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_rss_mib() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _second_run(fn) -> float:
    fn()
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--length", type=int, default=19200)
    p.add_argument("--state-elems", default="65536,262144,1048576")
    args = p.parse_args()
    warnings.filterwarnings("ignore")
    import numpy as np
    import onnx
    import onnxruntime as ort
    import torch

    from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs
    from tofdenoise.models.scan import selective_scan
    from tofdenoise.models.scan.export import export_scan_lanes, selective_scan_export

    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    length = 4800 if args.quick else args.length
    budgets = [65536, 262144] if args.quick else [int(v) for v in args.state_elems.split(",")]
    gen = torch.Generator().manual_seed(0)
    A = -torch.arange(1, N + 1, dtype=torch.float32).repeat(DIM, 1)  # A_log = log(1..N), as initialised
    D, bias = torch.ones(DIM), 0.5 * torch.randn(DIM, generator=gen) - 3.0
    u, delta = (torch.randn(1, DIM, length, generator=gen) for _ in range(2))
    B, C = (torch.randn(1, GROUPS, N, length, generator=gen) for _ in range(2))
    elems = DIM * N * length
    print(f"scan dim {DIM}, N {N}, groups {GROUPS}, L {length}; torch/onnxruntime threads {threads}")
    print("| route | state elems per step | lanes | time (s) | ns per state element | peak RSS (MiB) |")
    print("|---|---:|---:|---:|---:|---:|")
    _reset_peak_rss()
    with torch.no_grad():
        ref = selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu")
        t = _second_run(lambda: selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu"))
    print(f"| PyTorch native kernel | - | - | {t:.2f} | {t / elems * 1e9:.2f} | {_peak_rss_mib():.0f} |", flush=True)
    for budget in budgets:

        class Scan(torch.nn.Module):
            def forward(self, u, delta, B, C, budget=budget):
                return selective_scan_export(u, delta, A, B, C, D, bias, True, state_elems=budget)

        names = ["u", "delta", "B", "C"]
        small = (u[..., :37], delta[..., :37], B[..., :37], C[..., :37])
        path = Path(f"/tmp/bench_export_scan_{budget}.onnx")
        torch.onnx.export(
            Scan(),
            small,
            str(path),
            dynamo=False,
            input_names=names,
            dynamic_axes={"u": {2: "L"}, "delta": {2: "L"}, "B": {3: "L"}, "C": {3: "L"}},
            opset_version=18,
        )
        proto = onnx.load(str(path))
        path.unlink()
        sequences_to_scan_outputs(proto.graph)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        sess = ort.InferenceSession(proto.SerializeToString(), options, providers=["CPUExecutionProvider"])
        feeds = dict(zip(names, (x.numpy() for x in (u, delta, B, C))))
        _reset_peak_rss()
        out = sess.run(None, feeds)[0]
        t = _second_run(lambda: sess.run(None, feeds))
        diff = float(np.abs(out - ref.numpy()).max())
        lanes = export_scan_lanes(DIM * N, length, budget)
        print(
            f"| onnxruntime export scan (max diff {diff:.1e}) | {budget} | {lanes} | {t:.2f} | "
            f"{t / elems * 1e9:.2f} | {_peak_rss_mib():.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
