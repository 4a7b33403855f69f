"""Start a run from a trained model: load only the weights of a checkpoint (``model.init_weights``).

Fine-tuning, not resuming: the optimiser, the learning-rate schedule, the epoch and step counters and the
callbacks' state start fresh (``ckpt_path`` restores all of them). :func:`load_init_weights` reads the file with
``torch.load(weights_only=True)`` and accepts

- a Lightning checkpoint of ``tofdenoise train`` / ``tofdenoise fit`` (its ``state_dict``; with an EMA, the
  EMA weights, the network its validation MAE was measured with), or
- a plain state dict: ``DepthRestorer.state_dict()`` (keys ``backbone.*``) or the backbone's own
  (``build_backbone(...).state_dict()``, keys without prefix).

Every weight of the new model's backbone must come from the file with its shape, and the file may hold no other
network weight: a missing key, an unexpected key or a shape mismatch is one :class:`InitWeightsError` that names
the file and the first few layers of each kind with their counts. Nothing is loaded then (no partial load).
A checkpoint whose input conditioning differs (``conditioning``: ``centering``, ``block_px``, ``depth_scale_mm``)
is refused the same way: its weights expect another input.

:func:`file_sha256` gives the digest recorded in ``run_info.json`` (``init_weights``: path and sha256).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from tofdenoise.data_modules.file_stamps import file_sha256
from tofdenoise.training.legacy_hparams import upgrade_hparams

__all__ = ["InitWeightsError", "load_init_weights", "read_init_state", "file_sha256", "INIT_RECORD_KEY"]

#: checkpoint key of the init record ({"path", "sha256"}), so a resumed run still says where it started from
INIT_RECORD_KEY = "tofdenoise_init_weights"
#: the conditioning settings that define what the network's input means: weights trained on another input are
#: refused (``use_signal_channel`` changes the first layer's shape, reported as a shape mismatch)
_INPUT_SETTINGS = ("centering", "block_px", "depth_scale_mm")
_SHOW = 3


class InitWeightsError(ValueError):
    """``model.init_weights`` names a file that cannot initialise this model (message names the file)."""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def read_init_state(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """``(backbone state dict, saved hyper-parameters or {})`` of a checkpoint or plain state-dict file."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise InitWeightsError(f"model.init_weights: {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling/zip error: the file is not usable weights
        raise InitWeightsError(
            f"model.init_weights: {path} is not loadable by torch.load(weights_only=True) ({_first_line(exc)}); "
            "give a checkpoint of tofdenoise train / tofdenoise fit or a state-dict file saved with torch.save"
        ) from None
    hparams: dict[str, Any] = {}
    if isinstance(payload, Mapping) and isinstance(payload.get("state_dict"), Mapping):
        hparams = upgrade_hparams(payload.get("hyper_parameters") or {})  # an old flat layout: today's groups
        state = payload["state_dict"]
    elif isinstance(payload, Mapping):
        state = payload
    else:
        raise InitWeightsError(
            f"model.init_weights: {path} holds a {type(payload).__name__}, not a checkpoint or a state dict"
        )
    bad = [str(k) for k, v in state.items() if not isinstance(v, torch.Tensor)]
    if bad or not state:
        what = f"non-tensor entries ({', '.join(bad[:_SHOW])})" if bad else "no tensors"
        raise InitWeightsError(f"model.init_weights: {path} is not a state dict: {what}")
    return _backbone_state(state), hparams


def _backbone_state(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The network weights to start from: the EMA copy when there is one, else ``backbone.*``, else the keys as
    they are (a backbone's own state dict)."""
    for prefix in ("ema.module.", "backbone."):
        picked = {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        if picked:
            others = {k: v for k, v in state.items() if not k.startswith(("ema.", "backbone."))}
            # anything else is reported as unexpected (another model's weights), under its own name
            return {**picked, **others}
    return dict(state)


def _listed(names: list[str], what: str) -> str:
    shown = ", ".join(names[:_SHOW])
    more = f", ... ({len(names) - _SHOW} more)" if len(names) > _SHOW else ""
    return f"{len(names)} {what} ({shown}{more})"


def _check_input_hparams(path: Path, saved: dict[str, Any], model_hparams: Mapping[str, Any]) -> None:
    theirs, mine = saved.get("conditioning"), dict(model_hparams.get("conditioning") or {})
    if not isinstance(theirs, Mapping):
        raise InitWeightsError(
            f"model.init_weights: {path} is a checkpoint whose hyper_parameters have no 'conditioning' group, so "
            "what its network was trained to see is unknown; give its state dict instead (torch.save of "
            "model.state_dict()) if you know it matches"
        )
    diffs = [
        f"conditioning.{key}: file {theirs.get(key)!r} vs this model {mine.get(key)!r}"
        for key in _INPUT_SETTINGS
        if theirs.get(key) != mine.get(key)
    ]
    if diffs:
        raise InitWeightsError(
            f"model.init_weights: {path} was trained on another network input ({'; '.join(diffs)}); "
            "set the same values for this run"
        )


def load_init_weights(module: Any, path: str | os.PathLike[str]) -> dict[str, str]:
    """Copy the weights of ``path`` into ``module.backbone`` (and its EMA copy), all or nothing; returns the record
    ``{"path": absolute path, "sha256": ...}``. Raises :class:`InitWeightsError` naming the file and the layers."""
    path = Path(path).expanduser().resolve()
    state, hparams = read_init_state(path)
    if hparams:
        _check_input_hparams(path, hparams, getattr(module, "hparams", {}) or {})
    backbone: nn.Module = module.backbone
    target = backbone.state_dict()
    missing = [k for k in target if k not in state]
    unexpected = [k for k in state if k not in target]
    shapes = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(v.shape)}"
        for k, v in target.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    if missing or unexpected or shapes:
        parts = [
            _listed(missing, "missing"),
            _listed(unexpected, "unexpected"),
            _listed(shapes, "shape mismatch(es)"),
        ]
        saved = ""
        if hparams.get("backbone") is not None:
            saved = f"; the file is a {hparams['backbone']!r} with backbone_kwargs {hparams.get('backbone_kwargs')}"
        name = getattr(module, "hparams", {}).get("backbone", type(backbone).__name__)
        raise InitWeightsError(
            f"model.init_weights: {path} does not fit backbone {name!r}: "
            f"{'; '.join(p for p, n in zip(parts, (missing, unexpected, shapes)) if n)}{saved}"
        )
    with torch.no_grad():
        backbone.load_state_dict({k: state[k] for k in target}, strict=True)
        ema = getattr(module, "ema", None)
        if ema is not None:  # the EMA starts from the loaded weights, not from the fresh initialisation
            ema.module.load_state_dict(backbone.state_dict(), strict=True)
    return {"path": str(path), "sha256": file_sha256(path)}
