"""Run an exported restore graph (``tofdenoise export``) with onnxruntime: no torch weights are loaded.

:class:`OnnxRestorer` reads the graph's metadata (``tofdenoise.inference.export``: backbone, signal channel,
precision, source checkpoint) and restores one frame as ``restore_frame`` does for a checkpoint: invalid input
pixels are 0 in the output unless ``fill_holes``. Used by ``tofdenoise denoise --onnx`` and
``benchmarks/bench_onnx.py``. The session runs on onnxruntime's CPU execution provider, or on its CUDA (or
TensorRT) provider when the installed onnxruntime has one (the ``onnxruntime-gpu`` package):
:func:`execution_providers` maps ``--device`` to the providers' list, and :func:`open_session` starts a session
on them (used by :class:`OnnxRestorer` and the benchmark alike).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["OnnxRestorer", "OnnxModelError", "execution_providers", "open_session", "session_providers"]

# what each device asks onnxruntime for, best first; onnxruntime falls back along the list node by node
_PROVIDERS = {
    "cpu": ["CPUExecutionProvider"],
    "cuda": ["CUDAExecutionProvider", "CPUExecutionProvider"],
    "tensorrt": ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"],
}


class OnnxModelError(ValueError):
    """The ``--onnx`` file is missing, unreadable or not a tofdenoise restore graph (the message names it)."""


def execution_providers(device: str, available: Sequence[str]) -> list[str]:
    """onnxruntime's providers for ``device`` (``auto``, ``cpu``, ``cuda`` or ``tensorrt``), given the providers
    the installed onnxruntime ``available`` has: ``auto`` is CUDA when it has it, else the CPU; a device whose
    provider it lacks is a ``ValueError`` naming the package that has it."""
    if device == "auto":
        device = "cuda" if "CUDAExecutionProvider" in available else "cpu"
    if device not in _PROVIDERS:
        raise ValueError(f"onnxruntime device must be auto, cpu, cuda or tensorrt, got {device!r}")
    wanted = _PROVIDERS[device]
    if wanted[0] not in available:
        raise ValueError(
            f"--device {device}: the installed onnxruntime has no {wanted[0]} (it has {', '.join(available)}); "
            "install onnxruntime-gpu for CUDA and TensorRT"
        )
    return [name for name in wanted if name in available]


def session_providers(providers: Sequence[str]) -> list[str | tuple[str, dict[str, str]]]:
    """``providers`` (from :func:`execution_providers`) with their options, as ``onnxruntime.InferenceSession(
    providers=...)`` takes them: the CUDA provider without TF32 (``use_tf32 0``), so that a float32 graph computes in
    float32 as PyTorch does (with TF32, DVSS at 480 x 640 differed from PyTorch by 0.020 mm, without it by 0.0001 mm;
    measured on an H200, docs/benchmarks.md)."""
    return [(name, {"use_tf32": "0"}) if name == "CUDAExecutionProvider" else name for name in providers]


def open_session(path: str | os.PathLike[str], options: Any, device: str) -> Any:
    """An ``onnxruntime.InferenceSession`` of the graph at ``path`` on ``device``'s providers (CUDA and cuDNN loaded
    from the nvidia-* wheels first, onnxruntime >= 1.21). onnxruntime falls back to the CPU with only a log line
    when the CUDA provider does not start: that is an :class:`OnnxModelError` for an explicit device, a warning for
    ``auto``. onnxruntime's own errors (an unreadable file) pass through."""
    import onnxruntime as ort

    providers = execution_providers(device, ort.get_available_providers())
    if providers[0] != "CPUExecutionProvider" and hasattr(ort, "preload_dlls"):
        ort.preload_dlls()
    session = ort.InferenceSession(str(path), options, providers=session_providers(providers))
    running = session.get_providers()[0]
    if running != providers[0]:
        why = f"onnxruntime could not start its {providers[0]} (its CUDA or cuDNN libraries did not load)"
        if device != "auto":
            raise OnnxModelError(
                f"ONNX model {path}: {why} and fell back to {running}; run with --device cpu or fix the CUDA install"
            )
        warnings.warn(f"ONNX model {path}: {why}; running on {running}", RuntimeWarning, stacklevel=2)
    return session


def _depth_range(text: str | None) -> tuple[float, float] | None:
    """The ``tofdenoise_training_depth_mm`` metadata ("nearest,farthest" mm) as numbers; None when absent or bad."""
    try:
        low, high = (float(v) for v in str(text).split(","))
    except ValueError:
        return None
    return (low, high) if 0 < low < high else None


class OnnxRestorer:
    """An onnxruntime session over a restore graph; ``restore_frame(depth_mm, valid, amplitude, fill_holes)``.
    ``device``: see :func:`execution_providers`; ``self.device`` is the one the session runs on."""

    def __init__(self, path: str | os.PathLike[str], threads: int | None = None, device: str = "cpu") -> None:
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
            self.session = open_session(self.path, options, device)
        except (OnnxModelError, ValueError):  # a provider that did not start, a device without one
            raise
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for any unreadable file
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise OnnxModelError(f"ONNX model {self.path} could not be loaded by onnxruntime ({first})") from None
        self.device = "cpu" if self.session.get_providers()[0] == "CPUExecutionProvider" else "cuda"
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        if "tofdenoise_backbone" not in self.metadata:
            raise OnnxModelError(
                f"ONNX model {self.path} is not a tofdenoise restore graph (no tofdenoise_* metadata); "
                "write one with tofdenoise export CKPT --onnx FILE"
            )
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.use_signal_channel = self.metadata.get("tofdenoise_use_signal_channel") == "true"
        self.backbone = self.metadata["tofdenoise_backbone"]
        #: (nearest, farthest) training depth [mm] of the exported checkpoint; None: not recorded (older export)
        self.training_depth_range_mm = _depth_range(self.metadata.get("tofdenoise_training_depth_mm"))

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
