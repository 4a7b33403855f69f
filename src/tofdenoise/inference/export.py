"""The whole restore path of a checkpoint as one ONNX graph (``tofdenoise export CKPT --onnx model.onnx``).

:class:`RestoreGraph` is ``DepthRestorer.restore_mm`` written for export: the hole fill (the checkpoint's fill with
a fixed number of levels, :func:`tofdenoise.models.conditioning.fill_invalid_mm`), the centring on the smooth local
offset, the network, and the offset added back in float32. Inputs ``depth_mm`` (B, 1, H, W) float32 (0, negative,
NaN = invalid) and, for a checkpoint with the signal channel, ``amplitude`` (B, 1, H, W); output ``restored_mm``
(B, 1, H, W) at every pixel (the caller masks input holes, as ``tofdenoise denoise`` does). Height and width are
dynamic. ``fp16`` runs the network in float16 between the float32 conditioning and the float32 offset.

Exporter: the TorchScript-based ``torch.onnx.export(..., dynamo=False)`` by default. Both were tried on the tiny
U-Net (2-core CPU, shared): both give graphs that run at any size with onnxruntime within 2.5e-4 mm of PyTorch,
but the dynamo exporter (``torch.export`` with ``Dim.DYNAMIC`` height and width) took 89 s against 5 s, its
symbolic shape reasoning going through the 16 nested ``(side + 1) // 2`` of the hole fill's pyramid. The
tracer records shape arithmetic (``x.shape``, the pads to whole blocks, the bilinear sizes) as graph
operations, so the graph stays dynamic; what it cannot follow are Python branches on a shape, so the example
frame has odd prime sides (:func:`_example`) and the code paths that branch on a size (a backbone padding to its
stride) take the general branch.

The TorchScript-based exporter is deprecated in torch 2.13 (it still works and is what the tests check first). The
dynamo exporter is the other route, for every backbone (``export_onnx(..., exporter="dynamo")``, ``tofdenoise
export --exporter dynamo``): slower to export (37 s against 5 s for the tiny DVSS of the tests), the same numbers.

DVSS's scans go through ``models/scan/export.py``. For the TorchScript exporter they are ``torch.jit.script``
loops that it keeps as ONNX ``Loop`` nodes (dynamic trip count, memory bounded in the sequence length); after
export their per-step outputs are rewritten from ONNX sequences into the loops' scan outputs
(:mod:`tofdenoise.inference.onnx_loops`). For the dynamo exporter, which would unroll scripted loops at the
example's size, they are ``scan`` operators that become ONNX ``Scan`` nodes. ``scan_form`` picks the scan's form:
one loop step per chunk of positions behind a run-time exponent guard (an ONNX ``If``) or one per position.

The graph's metadata (``metadata_props``) names the backbone, ``use_signal_channel``, ``depth_scale_mm``, the
fill levels, the precision, the checkpoint's sha256 and the depths it was trained on (``tofdenoise_training_depth_mm``,
``nearest,farthest`` in mm, when the checkpoint records them); ``tofdenoise denoise --onnx`` reads them.
"""

from __future__ import annotations

import copy
import json
import os
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from tofdenoise.atomic import atomic_write
from tofdenoise.inference.denoise import load_restorer
from tofdenoise.models.conditioning import InputConditioning
from tofdenoise.training.init_weights import file_sha256
from tofdenoise.training.module import final_prediction

__all__ = [
    "RestoreGraph",
    "ExportError",
    "check_onnx_output",
    "export_onnx",
    "is_onnx_export",
    "EXPORTERS",
    "FILL_LEVELS",
    "ONNX_OPSET",
]

#: ``torch.onnx.export`` routes: the TorchScript-based tracer (default; deprecated in torch 2.13) and torch.export
EXPORTERS = ("torchscript", "dynamo")

#: pull-push levels of the exported hole fill: exact for frames up to 2**16 pixels a side
FILL_LEVELS = 16
ONNX_OPSET = 18


class ExportError(ValueError):
    """A checkpoint or setting that cannot be exported (the message names the file or the field)."""


class RestoreGraph(nn.Module):
    """``DepthRestorer.restore_mm`` without tiling, with no data-dependent branch: (depth[, amplitude]) -> mm."""

    def __init__(
        self, net: nn.Module, conditioning: InputConditioning, fp16: bool = False, levels: int = FILL_LEVELS
    ) -> None:
        super().__init__()
        if conditioning.centering not in ("gaussian", "local", "none"):
            raise ExportError(
                f"conditioning.centering {conditioning.centering!r} cannot be exported (its per-image median has no "
                "ONNX operator); export a checkpoint trained with centering 'gaussian', 'local' or 'none'"
            )
        self.net = net.half() if fp16 else net
        self.conditioning, self.fp16, self.levels = conditioning, bool(fp16), int(levels)

    @property
    def use_signal_channel(self) -> bool:
        return self.conditioning.use_signal_channel

    def forward(self, depth_mm: Tensor, amplitude: Tensor | None = None) -> Tensor:
        x, offset = self.conditioning(depth_mm, amplitude, fill_levels=self.levels)
        y = final_prediction(self.net(x.half() if self.fp16 else x))
        return y.float() * self.conditioning.depth_scale_mm + offset


def restore_graph(model: Any, fp16: bool = False) -> RestoreGraph:
    """The :class:`RestoreGraph` of a loaded ``DepthRestorer`` (its evaluation network: the EMA copy when on)."""

    net = copy.deepcopy(model.eval_net).eval()
    for module in net.modules():
        if hasattr(module, "scan_backend"):  # SS2D (DVSS): the scan written for export (models/scan/export.py)
            module.scan_backend = "export"
    return RestoreGraph(net, model.conditioning, fp16=fp16).eval()


def _example(graph: RestoreGraph, height: int = 61, width: int = 83) -> tuple[Tensor, ...]:
    """Example inputs of odd, prime sides: torch.export follows the branches this size takes (a backbone pads to a
    multiple of its stride only when needed) and would specialise the graph to multiples of 2 or 4 otherwise."""
    gen = torch.Generator().manual_seed(0)
    depth = 500.0 + 1000.0 * torch.rand(1, 1, height, width, generator=gen)
    depth[torch.rand(depth.shape, generator=gen) < 0.1] = 0.0
    if graph.use_signal_channel:
        return depth, torch.rand(1, 1, height, width, generator=gen) * 1000.0
    return (depth,)


def export_graph(
    graph: RestoreGraph, path: str | os.PathLike[str], dynamo: bool = False, scan_form: str | None = None
) -> None:
    """Write ``graph`` as ONNX to ``path`` (not atomic: :func:`export_onnx` writes through a temporary file).
    ``scan_form``: the form of DVSS's export scans (``models/scan/export.py``: ``"chunked"`` or ``"steps"``;
    ``None``: its default, ``EXPORT_SCAN_FORM``)."""
    from tofdenoise.models.scan.export import export_scan_form

    inputs = _example(graph)
    names = ["depth_mm"] + (["amplitude"] if graph.use_signal_channel else [])
    common = {"input_names": names, "output_names": ["restored_mm"], "opset_version": ONNX_OPSET, "dynamo": dynamo}
    if dynamo:  # torch.export: symbolic height and width
        common["dynamic_shapes"] = tuple({2: torch.export.Dim.DYNAMIC, 3: torch.export.Dim.DYNAMIC} for _ in inputs)
    else:  # the tracer: sizes recorded as graph operations, the axes named dynamic
        common["dynamic_axes"] = {n: {2: "height", 3: "width"} for n in [*names, "restored_mm"]}

    with torch.no_grad(), warnings.catch_warnings(), export_scan_form(scan_form):
        # expected: the shape checks the tracer keeps as constants (the general branch, _example) and the
        # exporter's note that it does not fold strided slices
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message="Constant folding")
        torch.onnx.export(graph, inputs, str(path), **common)
    if not dynamo:
        _loops_with_scan_outputs(path)


def _loops_with_scan_outputs(path: str | os.PathLike[str]) -> None:
    """The per-step outputs of the export scan's loops (DVSS) as ``Loop`` scan outputs, not ONNX sequences
    (:mod:`tofdenoise.inference.onnx_loops`); a graph without such loops is left as written."""
    import onnx

    from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs

    proto = onnx.load(str(path))
    if sequences_to_scan_outputs(proto.graph):
        onnx.save(proto, str(path))


def is_onnx_export(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` is an ONNX graph written by :func:`export_onnx` (its metadata names a tofdenoise backbone).
    Only the model's protobuf is parsed (no external data, no onnxruntime session); anything else, a PNG, a
    checkpoint, a graph of another tool, is False."""
    import onnx

    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception:  # noqa: BLE001 - protobuf raises its own errors for bytes that are no ONNX model
        return False
    return any(entry.key == "tofdenoise_backbone" for entry in proto.metadata_props)


def check_onnx_output(out: str | os.PathLike[str], inputs: list[str | os.PathLike[str]] = ()) -> Path:
    """``out`` as the ``--onnx`` output once it is safe to write: an ``.onnx`` file name that replaces none of
    ``inputs`` (``tofdenoise.output_guard``) and, when it exists, an earlier export of ours (:func:`is_onnx_export`),
    never another file (``OutputPathError``, naming the path and what was expected)."""
    from tofdenoise.output_guard import OutputPathError, check_output_file

    out = check_output_file(out, (".onnx",), inputs, "--onnx", shadow=False)
    if out.exists() and not is_onnx_export(out):
        raise OutputPathError(
            f"--onnx {out} exists and is not an ONNX export of tofdenoise (no tofdenoise_* metadata); refusing to "
            "replace it: choose another file name, or remove it first"
        )
    return out


def export_onnx(
    ckpt: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fp16: bool = False,
    exporter: str = "torchscript",
    scan_form: str | None = None,
) -> dict[str, str]:
    """Export checkpoint ``ckpt`` to ``out`` (atomically) with ``exporter`` (:data:`EXPORTERS`) and return the
    metadata written into the graph. ``scan_form``: as in :func:`export_graph`."""
    import onnx

    from tofdenoise.models.scan.export import EXPORT_SCAN_FORM, EXPORT_SCAN_FORMS

    if exporter not in EXPORTERS:
        raise ExportError(f"exporter {exporter!r}; expected one of {', '.join(EXPORTERS)}")
    if scan_form is not None and scan_form not in EXPORT_SCAN_FORMS:
        raise ExportError(f"scan form {scan_form!r}; expected one of {', '.join(EXPORT_SCAN_FORMS)}")

    model = load_restorer(ckpt, torch.device("cpu"))
    if not getattr(model, "trainable", True):
        raise ExportError(f"checkpoint {ckpt}: backbone {model.hparams.backbone!r} is a classical filter, not exported")
    graph = restore_graph(model, fp16=fp16)
    meta = {
        "tofdenoise_backbone": str(model.hparams.backbone),
        "tofdenoise_backbone_kwargs": json.dumps(dict(model.hparams.backbone_kwargs or {}), sort_keys=True),
        "tofdenoise_use_signal_channel": str(model.conditioning.use_signal_channel).lower(),
        "tofdenoise_depth_scale_mm": repr(model.conditioning.depth_scale_mm),
        "tofdenoise_input_centering": model.conditioning.centering,
        "tofdenoise_input_fill": model.conditioning.fill,
        "tofdenoise_fill_levels": str(FILL_LEVELS),
        "tofdenoise_precision": "fp16" if fp16 else "fp32",
        "tofdenoise_exporter": exporter,
        "tofdenoise_export_scan": scan_form or EXPORT_SCAN_FORM,
        "tofdenoise_checkpoint": str(Path(ckpt).resolve()),
        "tofdenoise_checkpoint_sha256": file_sha256(ckpt),
    }
    trained = model.training_depth_range_mm
    if trained is not None:  # the depths the network was trained on (training/depth_range.py), "nearest,farthest"
        meta["tofdenoise_training_depth_mm"] = f"{trained[0]!r},{trained[1]!r}"

    def write(tmp: Path) -> None:
        raw = tmp.with_name(tmp.name + ".export.onnx")
        try:
            export_graph(graph, raw, dynamo=exporter == "dynamo", scan_form=scan_form)
            proto = onnx.load(str(raw))  # external data (if any) folded back: one self-contained file
        finally:
            for leftover in raw.parent.glob(raw.name + "*"):
                leftover.unlink()
        for key, value in meta.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, str(tmp))

    atomic_write(out, write, suffix=".onnx")
    return meta
