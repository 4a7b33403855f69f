"""The restore path through PyTorch and through onnxruntime, side by side (one 480 x 640 frame).

    python benchmarks/bench_onnx.py [--quick] [--threads N] [--backbones unet,dvss] [--repeats 5]
        [--precisions fp32,fp16] [--exporters torchscript,dynamo] [--device cpu|cuda|tensorrt]

For each backbone (default kwargs, weights as initialised plus a small perturbation, so the network's output is
not the zero-initialised residual): ``DepthRestorer.restore_mm`` in float32 (no tiling; DVSS on its native CPU scan
kernel) against the exported graph (``tofdenoise.inference.export``, the whole path: hole fill, centring, network,
offset; DVSS through the export scan of ``models/scan/export.py``) in onnxruntime's CPU provider, fp32 and fp16.
Frames/s = 1 / median wall time of a frame with 10 % holes, after one warm-up; the max |difference| to PyTorch
over valid pixels is printed with it, and the peak resident memory of the process while the route ran (Linux:
the high-water mark ``VmHWM``, reset before each route through ``/proc/self/clear_refs``; it includes what the
process already held, printed as the RSS at the start). ``--quick``: 240 x 320 frames. The default list is the
U-Net and DVSS, the pair the issue asks for (DVSS takes about 25 s per 480 x 640 frame through onnxruntime on a
2-core CPU, so ``make bench`` spends a few minutes here; ``--backbones unet`` skips it). ``--exporters`` picks the
``torch.onnx.export`` routes (default: the TorchScript one; ``dynamo`` exports DVSS's scans as ONNX ``Scan`` nodes
instead of ``Loop`` nodes). ``--device cuda``: PyTorch on the GPU (DVSS on its Triton scan) against onnxruntime's
CUDA execution provider (``tensorrt``: its TensorRT provider); both routes take the frame from host memory and
give it back there, so a frame's time includes the two copies.
"""

from __future__ import annotations

import argparse
import gc
import statistics
import tempfile
import time
import warnings
from pathlib import Path


def _reset_peak_rss() -> None:
    """Reset the process's resident-memory high-water mark to its current RSS (Linux >= 4.0; else a no-op)."""
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


def _release_memory() -> None:
    """Collect garbage and hand freed heap pages back to the system (glibc), so that a route's RSS at start is
    not what an earlier route left behind."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _memory(start_mib: float) -> str:
    return f"{_rss_mib('VmHWM'):.0f} | {start_mib:.0f}"


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--backbones", default="unet,dvss")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--precisions", default="fp32,fp16", help="onnxruntime routes to run (fp32, fp16 or both)")
    p.add_argument("--exporters", default="torchscript", help="export routes: torchscript, dynamo or both")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda", "tensorrt"), help="where both routes run")
    args = p.parse_args()
    warnings.filterwarnings("ignore")
    import numpy as np
    import onnxruntime as ort
    import torch

    from tofdenoise.inference.export import export_graph, restore_graph
    from tofdenoise.inference.onnx_runner import execution_providers, open_session
    from tofdenoise.training.module import DepthRestorer

    providers = execution_providers(args.device, ort.get_available_providers())  # a missing provider: an error here
    dev = torch.device("cpu" if args.device == "cpu" else "cuda")
    torch.backends.cudnn.allow_tf32 = False  # float32 convolutions in float32, as onnxruntime's (open_session)

    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    h, w = (240, 320) if args.quick else (480, 640)
    gen = torch.Generator().manual_seed(0)
    depth = 800.0 + 600.0 * torch.rand(1, 1, h, w, generator=gen)
    depth[torch.rand(depth.shape, generator=gen) < 0.1] = 0.0
    valid = (depth > 0).numpy()
    where = torch.cuda.get_device_name() if dev.type == "cuda" else "CPU"
    print(
        f"frame {h} x {w}, 10 % holes, {where}, torch {torch.__version__} threads {threads}, "
        f"onnxruntime {ort.__version__} ({providers[0]}) intra-op {threads}"
    )
    print("| backbone | route | frames/s | ms/frame | max abs diff vs PyTorch (mm) | peak RSS (MiB) | RSS at start |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name in args.backbones.split(","):
        torch.manual_seed(0)
        model = DepthRestorer(backbone=name).eval().to(dev)
        with torch.no_grad():
            for prm in model.backbone.parameters():
                prm.add_(0.01 * torch.randn_like(prm))

        def torch_frame(frame=depth):  # host -> device -> restored -> host, as onnxruntime's session.run does
            return model.restore_mm({"noisy": frame.to(dev)}, tile=None).cpu()

        with torch.no_grad():  # a small frame first: DVSS builds its native scan kernel outside the measurement
            torch_frame(depth[..., :32, :32])
        _release_memory()
        start = _rss_mib("VmRSS")
        _reset_peak_rss()
        with torch.no_grad():
            ref = torch_frame().numpy()
            t = _median_time(torch_frame, args.repeats)
        row = f"| {name} | PyTorch fp32 ({dev.type}) | {1 / t:.3g} | {1000 * t:.0f} | 0 | {_memory(start)} |"
        print(row, flush=True)
        routes = [(p, e) for e in args.exporters.split(",") for p in args.precisions.split(",")]
        for precision, exporter in routes:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "m.onnx"
                t0 = time.perf_counter()
                export_graph(restore_graph(model.cpu(), fp16=precision == "fp16"), path, dynamo=exporter == "dynamo")
                model.to(dev)
                export_s = time.perf_counter() - t0
                options = ort.SessionOptions()
                options.intra_op_num_threads = threads
                sess = open_session(path, options, args.device)  # an error if the provider does not start
                feeds = {"depth_mm": depth.numpy()}
                _release_memory()
                start = _rss_mib("VmRSS")
                _reset_peak_rss()
                out = sess.run(None, feeds)[0]
                t = _median_time(lambda: sess.run(None, feeds), args.repeats)
                memory = _memory(start)
                sess = None  # the session's memory goes before the next route
            diff = float(np.abs(out - ref)[valid].max())
            route = f"onnxruntime {precision}" + (
                f" ({exporter}, export {export_s:.0f} s)" if exporter != "torchscript" else ""
            )
            print(f"| {name} | {route} | {1 / t:.3g} | {1000 * t:.0f} | {diff:.4f} | {memory} |", flush=True)


if __name__ == "__main__":
    main()
