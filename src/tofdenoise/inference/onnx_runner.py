"""Run an exported restore graph (``tofdenoise export``) with onnxruntime: no torch weights are loaded.

:class:`OnnxRestorer` reads the graph's metadata (``tofdenoise.inference.export``: backbone, signal channel,
precision, source checkpoint) and restores one frame as ``restore_frame`` does for a checkpoint: invalid input
pixels are 0 in the output unless ``fill_holes``. Used by ``tofdenoise denoise --onnx``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["OnnxRestorer", "OnnxModelError"]


class OnnxModelError(ValueError):
    """The ``--onnx`` file is missing, unreadable or not a tofdenoise restore graph (the message names it)."""


class OnnxRestorer:
    """An onnxruntime session over a restore graph; ``restore_frame(depth_mm, valid, amplitude, fill_holes)``."""

    def __init__(self, path: str | os.PathLike[str], threads: int | None = None) -> None:
        self.path = Path(path).expanduser()
        if not self.path.is_file():
            raise OnnxModelError(f"ONNX model {self.path} does not exist")
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise OnnxModelError("--onnx needs the onnxruntime package (pip install onnxruntime)") from exc
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = int(threads)
        options.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for any unreadable file
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise OnnxModelError(f"ONNX model {self.path} could not be loaded by onnxruntime ({first})") from None
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        if "tofdenoise_backbone" not in self.metadata:
            raise OnnxModelError(
                f"ONNX model {self.path} is not a tofdenoise restore graph (no tofdenoise_* metadata); "
                "write one with tofdenoise export CKPT --onnx FILE"
            )
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.use_signal_channel = self.metadata.get("tofdenoise_use_signal_channel") == "true"
        self.backbone = self.metadata["tofdenoise_backbone"]

    def restore_mm(self, depth_mm: np.ndarray, amplitude: np.ndarray | None = None) -> np.ndarray:
        """The graph's output (B, 1, H, W) float32 mm at every pixel for a (B, 1, H, W) float32 depth."""
        feeds = {"depth_mm": np.ascontiguousarray(depth_mm, dtype=np.float32)}
        if "amplitude" in self.inputs:
            if amplitude is None:
                raise ValueError(
                    f"ONNX model {self.path} uses the amplitude (signal) channel: give the frame's amplitude "
                    "(tofdenoise denoise --amplitude DIR_OR_PATTERN)"
                )
            feeds["amplitude"] = np.ascontiguousarray(amplitude, dtype=np.float32)
        return self.session.run(["restored_mm"], feeds)[0]

    def restore_frame(
        self, depth_mm: np.ndarray, valid: np.ndarray, amplitude: np.ndarray | None = None, fill_holes: bool = False
    ) -> np.ndarray:
        """Restored depth [mm] float32 (H, W); 0 at invalid input pixels unless ``fill_holes``."""
        depth = np.where(valid, depth_mm, 0.0).astype(np.float32)[None, None]
        amp = None if amplitude is None else np.asarray(amplitude, dtype=np.float32)[None, None]
        out = self.restore_mm(depth, amp)[0, 0].astype(np.float32)
        return out if fill_holes else np.where(valid, out, np.float32(0.0))
