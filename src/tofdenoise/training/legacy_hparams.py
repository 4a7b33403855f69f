"""Checkpoints written before the settings groups: their hyper-parameters in today's layout.

Until 2026-11-25 (issue 24) a ``DepthRestorer`` took its input conditioning, optimiser and tiling settings as flat
arguments (``depth_scale_mm``, ``input_centering``, ``centering_block_px``, ``use_signal_channel``; ``lr``,
``weight_decay``, ``betas``, ``lr_min``, ``warmup_steps``; ``predict_tile_size``, ``eval_tile_size``,
``tile_overlap``), and its checkpoints store them so. Today they are the groups ``conditioning``, ``optim`` and
``tiling``. Lightning passes a checkpoint's saved hyper-parameters to ``__init__`` and drops the names it does
not take, so without this upgrade an older checkpoint would be rebuilt with today's defaults in place of its own
settings (the architecture check then refuses it). :func:`upgrade_hparams` moves each flat value into its group;
``DepthRestorer.load_from_checkpoint``, its architecture check and ``model.init_weights`` read checkpoints
through it, so every checkpoint of the project's history loads with the settings it was trained with.

On 2026-11-27 (issue 42) two conditioning defaults changed: ``centering`` ``local`` -> ``gaussian`` and the new
``fill`` setting (``pullpush`` before, ``harmonic`` now). A checkpoint stores its whole ``conditioning`` group, so
its ``centering`` is always there; ``fill`` is not in the files written before: :data:`FORMER_DEFAULTS` gives a
setting a checkpoint lacks the value it was trained with.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["FORMER_DEFAULTS", "FORMER_DEFAULTS_UNTIL", "LEGACY_KEYS", "is_legacy", "upgrade_hparams"]

#: flat argument of the old layout -> (group, field) of today's
LEGACY_KEYS: dict[str, tuple[str, str]] = {
    "depth_scale_mm": ("conditioning", "depth_scale_mm"),
    "input_centering": ("conditioning", "centering"),
    "centering_block_px": ("conditioning", "block_px"),
    "use_signal_channel": ("conditioning", "use_signal_channel"),
    "lr": ("optim", "lr"),
    "weight_decay": ("optim", "weight_decay"),
    "betas": ("optim", "betas"),
    "lr_min": ("optim", "lr_min"),
    "warmup_steps": ("optim", "warmup_steps"),
    "predict_tile_size": ("tiling", "predict_tile_px"),
    "eval_tile_size": ("tiling", "eval_tile_px"),
    "tile_overlap": ("tiling", "overlap_px"),
}


#: settings whose default changed, with the value a checkpoint without them was trained with: (group, field) -> value
FORMER_DEFAULTS: dict[tuple[str, str], Any] = {
    ("conditioning", "centering"): "local",
    ("conditioning", "fill"): "pullpush",
}
#: the commit that changed them (2026-11-27): code before it trained with :data:`FORMER_DEFAULTS` (a run's
#: ``config.yaml`` does not name these settings when it keeps the defaults, so a record made before says so only
#: through its commit: ``experiments.reproduce_check`` reruns such a record with them)
FORMER_DEFAULTS_UNTIL = "427bded8e258a9c9b07ff208c24be520285459e9"


def is_legacy(hparams: Mapping[str, Any]) -> bool:
    """Does ``hparams`` hold a flat setting of the old layout, or lack a setting of :data:`FORMER_DEFAULTS`?"""
    if any(key in hparams for key in LEGACY_KEYS):
        return True
    return any(
        isinstance(hparams.get(group), Mapping) and field not in hparams[group] for group, field in FORMER_DEFAULTS
    )


def upgrade_hparams(hparams: Mapping[str, Any]) -> dict[str, Any]:
    """``hparams`` in today's layout: each flat setting of :data:`LEGACY_KEYS` moved into its group (a group's
    own value, if a file somehow has both, wins), and each setting of :data:`FORMER_DEFAULTS` it lacks set to the
    value it was trained with. A dict already in today's layout comes back as a copy."""
    out = {k: v for k, v in hparams.items() if k not in LEGACY_KEYS}
    for key, (group, field) in LEGACY_KEYS.items():
        if key in hparams:
            merged = dict(out.get(group) or {})
            merged.setdefault(field, hparams[key])
            out[group] = merged
    for (group, field), value in FORMER_DEFAULTS.items():
        if isinstance(out.get(group), Mapping):  # a file without the group is not guessed (init_weights refuses it)
            out[group] = {**out[group], field: out[group].get(field, value)}
    return out
