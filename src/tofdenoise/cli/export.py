"""``tofdenoise export``: a checkpoint's whole restore path as one ONNX graph (``tofdenoise.inference.export``).

    tofdenoise export CKPT --onnx model.onnx [--fp16] [--exporter torchscript|dynamo] [--no-check]

The graph takes ``depth_mm`` (1, 1, H, W) float32 (0/NaN = invalid; any H, W) and, for a checkpoint with the
signal channel, ``amplitude``; it returns ``restored_mm``. After writing, the graph is run with onnxruntime on a
small frame with holes and compared with the checkpoint in PyTorch (``--no-check`` skips it). Exit status 2 for
a bad checkpoint, a backbone that cannot be exported, or an ``--onnx`` that is not safe to write: a name without the
``.onnx`` suffix, the checkpoint itself, or an existing file that is not an earlier export of ours (a run's
``checkpoints/last.ckpt`` or an image is never replaced; an earlier export is).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from tofdenoise.output_guard import OutputPathError

__all__ = ["build_parser", "main", "parity_check"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise export",
        description="Export a DepthRestorer checkpoint's restore path (hole fill, centring, network, offset) "
        "to ONNX with dynamic height and width.",
    )
    p.add_argument("ckpt", type=Path, metavar="CKPT", help="checkpoint of tofdenoise train / tofdenoise fit")
    p.add_argument(
        "--onnx",
        required=True,
        type=Path,
        help="output .onnx file (written atomically; an existing file is replaced only when it is an earlier export)",
    )
    p.add_argument("--fp16", action="store_true", help="the network in float16 (conditioning and offset stay fp32)")
    p.add_argument(
        "--exporter",
        default="torchscript",
        help="torch.onnx.export route: the TorchScript tracer (default; fast, deprecated in torch 2.13) or "
        "torch.export (dynamo; slower to export, the same graph's numbers)",
    )
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime vs PyTorch check")
    return p


def parity_check(ckpt: Path, onnx_path: Path, height: int = 45, width: int = 67) -> float:
    """Max |onnxruntime - PyTorch| in mm over the valid pixels of a procedural frame with 10 % holes."""
    import numpy as np
    import torch

    from tofdenoise.inference.denoise import load_restorer
    from tofdenoise.inference.onnx_runner import OnnxRestorer

    gen = torch.Generator().manual_seed(1)
    depth = 800.0 + 400.0 * torch.rand(1, 1, height, width, generator=gen)
    depth[torch.rand(depth.shape, generator=gen) < 0.1] = 0.0
    amplitude = 1000.0 * torch.rand(1, 1, height, width, generator=gen)
    model = load_restorer(ckpt, torch.device("cpu"))
    with torch.no_grad():
        ref = model.restore_mm({"noisy": depth, "amplitude": amplitude}, tile=None).numpy()
    out = OnnxRestorer(onnx_path).restore_mm(depth.numpy(), amplitude.numpy())
    valid = depth.numpy() > 0
    return float(np.abs(out - ref)[valid].max())


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``tofdenoise export``. The arguments are checked before torch is imported."""
    args = build_parser().parse_args(argv)
    if not Path(args.ckpt).expanduser().is_file():
        print(f"tofdenoise export: error: checkpoint file not found: {Path(args.ckpt).expanduser()}", file=sys.stderr)
        return 2
    from tofdenoise.inference.denoise import CheckpointError
    from tofdenoise.inference.export import ExportError, check_onnx_output, export_onnx

    try:
        check_onnx_output(args.onnx, [args.ckpt])
        meta = export_onnx(args.ckpt, args.onnx, fp16=args.fp16, exporter=args.exporter)
    except (CheckpointError, ExportError, OutputPathError, OSError) as exc:
        print(f"tofdenoise export: error: {exc}", file=sys.stderr)
        return 2
    line = (
        f"tofdenoise export: {meta['tofdenoise_backbone']} ({meta['tofdenoise_precision']}, "
        f"{meta['tofdenoise_exporter']} exporter) -> {args.onnx}"
    )
    if not args.no_check:
        line += f"; onnxruntime vs PyTorch max |diff| {parity_check(args.ckpt, args.onnx):.4g} mm on valid pixels"
    print(line, file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
