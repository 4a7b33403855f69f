"""A checkpoint scored on a capture set (``data_modules.real_captures`` layout): against each scene's reference, as
a run's ``real`` test set scores it (the paper's protocol), and, for a simulated capture set, against the rendered
truth on the same pixels (``tofdenoise evaluate --ckpt ... --captures ...``).

Why both: a real camera's reference is the mean of its high-exposure frames. It keeps every static error of the
camera (column fixed-pattern noise, per-pixel offsets, a calibration's systematic phase error), so a denoiser that
removes one of them from the input moves *away* from the reference. A simulated capture set
(``tofdenoise sensor realset``) also stores each scene's rendered depth (``ground_truth_depth_mm.npy``): scored
against it, the same prediction says how close it came to the scene. Every scene must hold that file for a truth
score (a set with some scenes lacking it is an error, not a silently smaller mean).

Pixels scored, per scene: the run's scoring region (``load_real_scene``'s ``mask``: input and reference valid,
sigma_D finite), and for the truth score also where the truth is finite and > 0. Which reference pixels are valid
depends on ``min_count`` (the valid high-exposure frames a reference pixel needs): ``evaluate_checkpoint`` uses the
one the checkpoint's run recorded (``data.real_min_count``, ``recorded_min_count``) unless told another, so that
the numbers are the run's (before 2026-11-29 it used half of each scene's frames whatever the run had, e.g. MAE
7.0965 mm over 33,112 px for a run that recorded 7.0758 mm over 33,579 px with ``real_min_count=2``). Metrics per
image, then averaged (``evaluation.MapScorer``: the same numbers and layout as ``tofdenoise evaluate --pred``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.data_modules.capture_simulation import GROUND_TRUTH
from tofdenoise.data_modules.io import read_array
from tofdenoise.data_modules.real_captures import list_scenes, load_real_scene
from tofdenoise.evaluation import EvalInputError, MapScorer
from tofdenoise.inference.denoise import load_restorer, restore_frame
from tofdenoise.physics.calibration import resolve_calibration
from tofdenoise.training.metrics import D_MAX_MM

__all__ = ["evaluate_checkpoint", "evaluate_on_captures", "has_truth", "read_truth", "recorded_min_count"]

#: the resolved config a training run saves in its folder, next to ``checkpoints/`` (``run_eval.CONFIG_NAME``)
RUN_CONFIG = "config.yaml"


def has_truth(captures_dir: str | Path) -> bool:
    """Whether any scene of the capture set ``captures_dir`` holds a rendered truth map (a simulated set); False for
    a folder that does not exist or holds no scene."""
    folder = Path(captures_dir)
    return folder.is_dir() and any((p / GROUND_TRUTH).is_file() for p in folder.iterdir() if p.is_dir())


def read_truth(scene: Path, shape: tuple[int, ...]) -> np.ndarray:
    """A scene's rendered depth [mm] (float64), checked against the input's ``shape``; errors name the file."""
    path = scene / GROUND_TRUTH
    try:
        truth = read_array(path, what="ground-truth depth").astype(np.float64)
    except (OSError, ValueError) as exc:
        message = str(exc)
        raise EvalInputError(message if str(path) in message else f"{path}: {message}") from exc
    if truth.shape != tuple(shape):
        raise EvalInputError(f"ground-truth depth file {path} has shape {truth.shape}; expected {tuple(shape)}")
    return truth


def evaluate_on_captures(
    model: Any,
    captures_dir: str | Path,
    calib: Any,
    d_max_mm: float = D_MAX_MM,
    min_count: int | None = None,
    precision: str = "bf16",
    log: Callable[[str], None] | None = None,
    edge_jump_mm: float | None = None,
) -> dict[str, Any]:
    """Restore every scene of ``captures_dir`` with ``model`` (a ``DepthRestorer``; ``calib``: the calibration of
    the camera that recorded the set) and score it. Returns ``{"scenes", "reference": R, "truth": R or None,
    "input": {"reference": R, "truth": R or None}, "reference_vs_truth": R or None}``, each ``R`` as
    ``evaluation.MapScorer.result``: the restored maps against the references and the truth, the input frames
    against both (what the restoration starts from), and the references against the truth on the same pixels
    (how far the protocol's reference is from the scene). The ``truth`` entries are None when no scene holds a
    truth map. Errors: ``EvalInputError`` (no scene, truth in some scenes only, an unreadable or misshapen truth
    map)."""
    scenes = list_scenes(captures_dir, config_key="--captures")
    if not scenes:
        raise EvalInputError(f"capture set {captures_dir} holds no scene folder (with input_depth_mm.png)")
    with_truth = [s.name for s in scenes if (s / GROUND_TRUTH).is_file()]
    if with_truth and len(with_truth) != len(scenes):
        lacking = [s.name for s in scenes if s.name not in with_truth]
        raise EvalInputError(
            f"capture set {captures_dir}: {len(lacking)} of {len(scenes)} scene(s) have no {GROUND_TRUTH} "
            f"({', '.join(lacking[:5])}): a truth score needs it in every scene"
        )
    to_reference, to_truth = MapScorer(d_max_mm, edge_jump_mm), MapScorer(d_max_mm, edge_jump_mm)
    input_to_reference, input_to_truth, reference_to_truth = (
        MapScorer(d_max_mm, edge_jump_mm),
        MapScorer(d_max_mm, edge_jump_mm),
        MapScorer(d_max_mm, edge_jump_mm),
    )
    signal = bool(model.conditioning.use_signal_channel)
    for i, scene in enumerate(scenes):
        sample = load_real_scene(scene, calib, min_count)
        depth, mask = sample["noisy"].astype(np.float64), sample["mask"] > 0
        pred = restore_frame(model, depth, depth > 0, sample["amplitude"] if signal else None, precision=precision)
        pred = pred.astype(np.float64)
        reference = sample["clean"].astype(np.float64)
        to_reference.add(scene.name, pred, reference, mask)
        input_to_reference.add(scene.name, depth, reference, mask)
        if with_truth:
            truth = read_truth(scene, depth.shape)
            to_truth.add(scene.name, pred, truth, mask)
            input_to_truth.add(scene.name, depth, truth, mask)
            reference_to_truth.add(scene.name, reference, truth, mask)
        if log is not None:
            log(f"[{i + 1}/{len(scenes)}] {scene.name}")
    return {
        "scenes": len(scenes),
        "reference": to_reference.result(),
        "truth": to_truth.result() if with_truth else None,
        "input": {
            "reference": input_to_reference.result(),
            "truth": input_to_truth.result() if with_truth else None,
        },
        "reference_vs_truth": reference_to_truth.result() if with_truth else None,
    }


def recorded_min_count(ckpt: str | Path) -> tuple[int | None, str | None]:
    """The ``data.real_min_count`` of the run that wrote ``ckpt``: (value, where it was read), the value None for
    "half of each scene's frames" (the run's null). Read from the data module's hyper-parameters Lightning keeps in
    the checkpoint, else from the run folder's ``config.yaml`` (``RUN/checkpoints/NAME.ckpt``); ``(None, None)``
    when neither records it."""
    import torch

    path = Path(ckpt).expanduser()
    try:
        content = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # load_restorer has read it already; an unreadable file is its error to report
        content = None
    hparams = content.get("datamodule_hyper_parameters") if isinstance(content, Mapping) else None
    if isinstance(hparams, Mapping) and "real_min_count" in hparams:
        value = hparams["real_min_count"]
        return (None if value is None else int(value)), f"{path} (data.real_min_count of its run)"
    config = path.parent.parent / RUN_CONFIG
    if path.parent.name == "checkpoints" and config.is_file():
        from omegaconf import OmegaConf

        try:
            data = OmegaConf.to_container(OmegaConf.load(config)).get("data") or {}
        except Exception as exc:
            raise EvalInputError(f"{config}: could not be read for data.real_min_count ({exc})") from exc
        if isinstance(data, Mapping) and "real_min_count" in data:
            value = data["real_min_count"]
            return (None if value is None else int(value)), f"{config} (data.real_min_count)"
    return None, None


def evaluate_checkpoint(
    ckpt: str | Path,
    captures_dir: str | Path,
    sensor: str | Path,
    device: str = "auto",
    d_max_mm: float = D_MAX_MM,
    log: Callable[[str], None] | None = None,
    edge_jump_mm: float | None = None,
    min_count: int | None = None,
) -> dict[str, Any]:
    """The checkpoint ``ckpt`` loaded on ``device`` (auto | cpu | cuda) and scored on the capture set
    ``captures_dir`` recorded by the camera calibrated in ``sensor`` (a preset name or a calibration file):
    ``{"checkpoint", "captures", "sensor", "min_count": {"value", "from"}, **evaluate_on_captures(...)}``, the JSON
    of ``tofdenoise evaluate --ckpt`` and of a run's ``real_vs_truth.json``.

    ``min_count``: the valid high-exposure frames a reference pixel needs; None: the one the checkpoint's run
    recorded (``recorded_min_count``), else half of each scene's frames. ``value`` None in the result means that
    half. Errors: ``CheckpointError``, ``FileNotFoundError`` and the other ``ValueError``s of the calibration and the
    capture set (``EvalInputError``), each naming the file or the option."""
    if min_count is not None and int(min_count) < 1:
        raise EvalInputError(f"--min-count must be >= 1, got {min_count}")
    calib = resolve_calibration(str(sensor))
    model = load_restorer(ckpt, device)
    if min_count is not None:
        used: dict[str, Any] = {"value": int(min_count), "from": "--min-count"}
    else:
        value, source = recorded_min_count(ckpt)
        used = {"value": value, "from": source or "default: half of each scene's frames (no run setting recorded)"}
    result = evaluate_on_captures(
        model, captures_dir, calib, d_max_mm, min_count=used["value"], log=log, edge_jump_mm=edge_jump_mm
    )
    return {"checkpoint": str(ckpt), "captures": str(captures_dir), "sensor": str(sensor), "min_count": used, **result}
