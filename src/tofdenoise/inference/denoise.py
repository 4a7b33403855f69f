"""Denoise camera frames with a trained ``DepthRestorer``: the one restoration path of ``tofdenoise denoise``, the
Python API ``tofdenoise.denoise`` and LightningCLI ``predict`` on a folder of frames.

A frame is restored as ``DepthRestorer.predict_step`` does: ``model.restore_mm({"noisy", "mask"[, "amplitude"]},
tile=...)`` (the model fills invalid input pixels before the network and centres the input), then pixels invalid
in the input are set back to 0 unless ``fill_holes``. A frame runs whole unless its activations do not fit the
memory budget of the device, or a tile side is given (``frame_tile_plan``, ``training/tile_memory.py``).
On CUDA the network runs under bf16 autocast (``precision="bf16"``; ``"fp32"`` to turn it off).
"""

from __future__ import annotations

import math
import pickle
from contextlib import nullcontext
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from tofdenoise.physics.uncertainty import amplitude_to_signal_e, sigma_depth_mm
from tofdenoise.training.module import DepthRestorer
from tofdenoise.training.tile_memory import TilePlan

__all__ = [
    "CheckpointError",
    "denoise",
    "frame_tile_plan",
    "load_restorer",
    "resolve_device",
    "restore_frame",
    "sigma_map_mm",
]


class CheckpointError(ValueError):
    """A file given as a checkpoint is not a DepthRestorer checkpoint."""


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """``"auto"`` -> CUDA when available, else CPU; ``"cuda"`` without a GPU is an error."""
    name = str(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available (use --device cpu or auto)")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {name!r}")
    return dev


def load_failure_reason(exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` failed, in one line and without torch's advice to load with
    ``weights_only=False`` (which would run whatever code the file pickles: never do that for a file you did not
    write)."""

    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) or "weights_only" in text:
        found = [ln.strip() for ln in text.splitlines() if "Unsupported global" in ln or "Unsupported operand" in ln]
        what = f": {found[0]}" if found else ""
        return (
            f"it holds pickled Python objects that a weights-only load refuses{what}; a tofdenoise checkpoint "
            "holds plain values only"
        )
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first.split("  (Could this error message be improved?")[0].strip()


#: file signatures of what is given as a checkpoint by mistake: (leading bytes, what the file is)
_NOT_A_CHECKPOINT = (
    (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"II*\x00", "a TIFF image"),
    (b"MM\x00*", "a TIFF image"),
    (b"\x93NUMPY", "a NumPy array (.npy)"),
)


def looks_like(path: Path) -> str:
    """What a file that is no PyTorch checkpoint looks like ("" when it is none of the known kinds): an image, a
    NumPy array or an ONNX graph (a protobuf ``ModelProto``: field 1 ``ir_version``, then ``producer_name``,
    ``opset_import`` or ``graph``)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return ""
    for signature, what in _NOT_A_CHECKPOINT:
        if head.startswith(signature):
            return what
    onnx_fields = len(head) > 2 and head[0] == 0x08 and head[1] < 0x80 and head[2] in (0x12, 0x1A, 0x3A, 0x42)
    if path.suffix.lower() == ".onnx" or onnx_fields:
        return "an ONNX graph (an exported model; `tofdenoise denoise --onnx` runs one)"
    return ""


def load_restorer(ckpt: str | Path, device: str | torch.device = "cpu") -> DepthRestorer:
    """Load a trained restorer once, for many frames.

    Args:
        ckpt: a checkpoint of ``tofdenoise train`` / ``tofdenoise fit`` (``runs/NAME/checkpoints/best.ckpt``),
            read with ``weights_only=True``.
        device: where the model goes: ``"cpu"``, ``"cuda"``, ``"auto"`` (CUDA when available) or a
            ``torch.device``.

    Returns:
        The ``DepthRestorer`` in eval mode on ``device``.

    Raises:
        CheckpointError: the file is missing or is not a DepthRestorer checkpoint (an image, an ONNX model, a
            truncated file ...); the message names the file and what was expected.
    """

    path = Path(ckpt).expanduser()
    expected = "expected a DepthRestorer checkpoint (.ckpt written by tofdenoise train or tofdenoise fit)"
    if not path.is_file():
        raise CheckpointError(f"checkpoint file not found: {path}")
    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # not a torch file, truncated, pickled objects ...
        kind = looks_like(path)
        if kind:
            raise CheckpointError(
                f"checkpoint {path} is {kind}, not a checkpoint; expected a Lightning checkpoint (.ckpt) of a "
                "DepthRestorer, written by tofdenoise train or tofdenoise fit"
            ) from exc
        raise CheckpointError(
            f"checkpoint {path} could not be read as a PyTorch checkpoint ({load_failure_reason(exc)}); {expected}"
        ) from exc
    hparams = content.get("hyper_parameters") if isinstance(content, dict) else None
    if (
        not isinstance(content, dict)
        or "state_dict" not in content
        or not isinstance(hparams, dict)
        or "backbone" not in hparams
    ):
        keys = sorted(content)[:8] if isinstance(content, dict) else type(content).__name__
        raise CheckpointError(f"checkpoint {path} is not a DepthRestorer checkpoint (found {keys}); {expected}")
    if not any(k.startswith("backbone.") for k in content["state_dict"]):
        raise CheckpointError(f"checkpoint {path} has no backbone weights; {expected}")
    del content
    try:
        model = DepthRestorer.load_from_checkpoint(path, map_location="cpu")
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path} could not be loaded as a DepthRestorer: {exc}") from exc
    return model.to(resolve_device(device)).eval()


def _as_model(model_or_ckpt: Any, device: str | torch.device):

    if isinstance(model_or_ckpt, DepthRestorer):
        return model_or_ckpt.eval()
    if isinstance(model_or_ckpt, (str, Path)):
        return load_restorer(model_or_ckpt, device)
    raise TypeError(f"model_or_ckpt: expected a DepthRestorer or a checkpoint path, got {type(model_or_ckpt).__name__}")


def _autocast(device: torch.device, precision: str):
    if precision not in ("bf16", "fp32"):
        raise ValueError(f"precision must be 'bf16' or 'fp32', got {precision!r}")
    if device.type == "cuda" and precision == "bf16":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return nullcontext()


@torch.no_grad()
def restore_frame(
    model: Any,
    depth_mm: np.ndarray,
    valid: np.ndarray,
    amplitude: np.ndarray | None = None,
    fill_holes: bool = False,
    tile: int | TilePlan | None = None,
    precision: str = "bf16",
) -> np.ndarray:
    """Restored depth [mm] float32 (H, W) of one frame (0 at invalid input pixels unless ``fill_holes``).

    ``depth_mm``: float (H, W), any value at invalid pixels (set to 0 here); ``valid``: bool (H, W);
    ``amplitude``: (H, W) or None (required when the model uses the signal channel); ``tile``: None = the whole
    frame when its activations fit the memory budget, else tiles of the model's ``tiling.predict_tile_px``
    (``frame_tile_plan``); a side in pixels forces tiles of that side; or a ``TilePlan``. The model's device is used.
    """
    if model.conditioning.use_signal_channel and amplitude is None:
        raise ValueError(
            "this checkpoint uses the amplitude (signal) channel: give the frame's amplitude "
            "(tofdenoise denoise --amplitude DIR_OR_PATTERN)"
        )
    device = model.device
    valid_t = torch.from_numpy(np.ascontiguousarray(valid, dtype=np.float32))[None, None].to(device)
    depth = np.where(valid, depth_mm, 0.0).astype(np.float32)
    batch: dict[str, torch.Tensor] = {"noisy": torch.from_numpy(depth)[None, None].to(device), "mask": valid_t}
    if model.conditioning.use_signal_channel:
        batch["amplitude"] = torch.from_numpy(np.ascontiguousarray(amplitude, dtype=np.float32))[None, None].to(device)
    if not isinstance(tile, TilePlan):
        tile = frame_tile_plan(model, depth.shape, tile, precision)
    with _autocast(device, precision):
        pred = model.restore_mm(batch, tile=tile.tile)
    pred = pred.float()
    if not fill_holes:
        pred = torch.where(valid_t > 0, pred, torch.zeros_like(pred))
    return pred[0, 0].cpu().numpy().astype(np.float32)


def frame_tile_plan(model: Any, shape: tuple[int, ...], tile: int | None = None, precision: str = "bf16") -> TilePlan:
    """Whole frame or tiles for a frame of ``shape`` on ``model`` (``DepthRestorer.predict_tile_plan``): ``tile``
    forces tiles of that side; else the network's activations, measured once on a small probe under the autocast of
    ``precision``, against the memory budget of the model's device, and the checkpoint's ``tiling.predict_tile_px``
    as the tile side when they do not fit."""
    device = model.device
    tag = precision if device.type == "cuda" else "fp32"
    return model.predict_tile_plan(tuple(shape), tile, tag, _autocast(device, precision))


def denoise(
    depth_mm: Any,
    model_or_ckpt: Any,
    amplitude: Any = None,
    fill_holes: bool = False,
    device: str | torch.device = "auto",
    tile: int | None = None,
    precision: str = "bf16",
    depth_scale_mm: float | None = None,
) -> np.ndarray:
    """Denoise one depth frame: ``tofdenoise.denoise(depth_mm, "best.ckpt")``.

    The same result as ``tofdenoise denoise`` on the same frame (a test checks it), for arrays in memory, with the
    same check of the frame's units: a frame whose valid depths lie mostly outside the depths a millimetre map can
    hold here (``inference.frames.plausible_depth_range_mm``) is refused, as a map in metres read as millimetres
    would be restored as a scene 1 mm away and returned without a word.

    Args:
        depth_mm: the frame [mm], (H, W) or (1, H, W), a numpy array or a tensor; NaN, inf, 0 and negative
            values mark invalid pixels.
        model_or_ckpt: a ``DepthRestorer`` (used on its own device) or the path of a checkpoint (loaded on
            ``device`` at every call; load it once with ``load_restorer`` for many frames).
        amplitude: the frame's amplitude, same shape as ``depth_mm``; required by models that use the signal
            channel. NaN / inf are invalid (the signal channel reads 0 there), as in the command's frames
            (``inference.frames.checked_amplitude``).
        fill_holes: give every pixel a depth, the invalid ones included; by default they stay 0.
        device: where a checkpoint path is loaded: ``"auto"`` (CUDA when available), ``"cpu"`` or ``"cuda"``.
        tile: force tiles of this side. Default None: the whole frame, unless the network's activations for it
            exceed the memory budget; then tiles of the model's ``tiling.predict_tile_px`` (``frame_tile_plan``).
        precision: ``"bf16"`` (bf16 autocast on CUDA; the CPU computes in float32) or ``"fp32"``.
        depth_scale_mm: millimetres per unit of ``depth_mm`` (1000 for metres), as ``--depth-scale-mm``: the frame
            is multiplied by it and its units are not checked. Default None: ``depth_mm`` is in millimetres, checked.

    Returns:
        The restored depth [mm], float32 (H, W); 0 at invalid input pixels unless ``fill_holes``.

    Raises:
        ValueError: ``depth_mm`` is not a numeric (H, W) map, its median valid depth is implausible in millimetres
            (without ``depth_scale_mm``; the message names the likely unit), ``amplitude`` has another shape, holds
            no finite value where the depth is valid or is missing for a model that needs it, or ``precision`` is
            neither ``"bf16"`` nor ``"fp32"``.
        TypeError: ``model_or_ckpt`` is neither a ``DepthRestorer`` nor a path.
        CheckpointError: ``model_or_ckpt`` is a path to a file that is not a DepthRestorer checkpoint.
    """
    model = _as_model(model_or_ckpt, device)
    depth = depth_mm.detach().cpu().numpy() if isinstance(depth_mm, torch.Tensor) else np.asarray(depth_mm)
    depth = np.squeeze(depth) if depth.ndim > 2 else depth
    if depth.ndim != 2 or not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise ValueError(f"denoise: depth_mm must be a numeric (H, W) map, got {depth.dtype} {np.shape(depth_mm)}")
    depth = depth.astype(np.float64)
    if depth_scale_mm is not None:
        if not (math.isfinite(depth_scale_mm) and depth_scale_mm > 0):
            raise ValueError(f"denoise: depth_scale_mm must be a positive number, got {depth_scale_mm}")
        depth = depth * float(depth_scale_mm)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    if depth_scale_mm is None:
        _check_units(depth, valid)
    amp = None
    if amplitude is not None:
        amp = amplitude.detach().cpu().numpy() if isinstance(amplitude, torch.Tensor) else np.asarray(amplitude)
        amp = np.squeeze(amp) if amp.ndim > 2 else amp
        from .frames import FrameError, checked_amplitude

        try:  # the checks of the command's frames: shape, and a finite value somewhere the depth is valid
            amp = checked_amplitude(amp, depth, valid, "amplitude", "depth_mm")[0]
        except FrameError as exc:
            raise ValueError(f"denoise: {exc}") from None
    return restore_frame(model, depth, valid, amp, fill_holes=fill_holes, tile=tile, precision=precision)


def _check_units(depth_mm: np.ndarray, valid: np.ndarray) -> None:
    """``inference.frames.check_depth_units_mm`` for an array given to :func:`denoise`: a ValueError that names the
    argument to pass (``depth_scale_mm``) where the command line's names its option."""
    from .frames import FrameError, check_depth_units_mm

    try:
        frame = SimpleNamespace(depth_mm=depth_mm, valid=valid)
        check_depth_units_mm(frame, "(the depth_mm array)", option="depth_scale_mm=")
    except FrameError as exc:
        raise ValueError(f"denoise: {exc}") from None


def sigma_map_mm(depth_mm: np.ndarray, valid: np.ndarray, amplitude: np.ndarray, calib: Any) -> np.ndarray:
    """Per-pixel sigma_D [mm] of a camera frame (paper Eqs. 1-17), the map ``tofdenoise denoise`` writes.

    The returned signal a(p) comes from the amplitude as in training (``amplitude_to_signal_e``: per-image
    percentiles of the valid amplitudes mapped to the calibration's signal interval, paper Sec. III-A);
    sigma_D from ``sigma_depth_mm`` at the measured depth.

    Args:
        depth_mm: measured depth [mm], (H, W).
        valid: bool (H, W), the pixels to compute.
        amplitude: the frame's amplitude, (H, W), any positive scale.
        calib: the camera's ``SensorCalibration``.

    Returns:
        sigma_D [mm], float32 (H, W); NaN at invalid pixels and where the amplitude is not finite or negative.
    """

    amp = np.asarray(amplitude, dtype=np.float32)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(amp) & (amp >= 0)
    signal = np.asarray(
        amplitude_to_signal_e(np.where(ok, np.maximum(amp, 1e-12), 0.0), calib, valid=ok), dtype=np.float32
    )
    ok &= np.isfinite(signal)
    safe_depth = np.where(ok, depth_mm, 1.0).astype(np.float32)
    safe_signal = np.where(ok, signal, calib.signal_min_e).astype(np.float32)
    sigma = np.asarray(sigma_depth_mm(safe_depth, safe_signal, calib), dtype=np.float32)
    return np.where(ok & np.isfinite(sigma), sigma, np.nan).astype(np.float32)
