"""The learned guard's verdict: did a run learn anything (the one place its rule lives).

The learned rule: ``learned = trained_steps > 0 and best_val_mae_mm <= (1 - margin) x raw_val_mae_mm``, where
``best_val_mae_mm`` is the lowest validation MAE of the run (``val/mae_mm``, what the checkpoint callback picks
``best.ckpt`` by) and ``raw_val_mae_mm`` the MAE of the noisy input on the same validation images
(``val/raw/mae_mm``). A run without training steps is never learned ("not trained"); a run without a validation
result cannot be verified and is not learned either ("not verified"). The margin (default 5 %) is the
``DepthRestorer(learned_margin=...)`` setting.

``method_kind`` tells the two kinds of rows apart: ``"network"`` (the rule above) or ``"classical"`` (a filter
without trainable parameters, ``tofdenoise classic``; ``classical_verdict``): 0 steps and ``learned`` False by
construction, reported as "classical", never as a failed run; its ``best_val_mae_mm`` is the validation MAE of
the parameters its grid search chose. A file without ``method_kind`` was written by a network run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

__all__ = ["DEFAULT_LEARNED_MARGIN", "classical_verdict", "learned_status", "learned_verdict"]

#: default margin of the learned guard: the best validation MAE must be at least 5 % below the raw MAE
DEFAULT_LEARNED_MARGIN = 0.05


def _finite_or_none(value: Any) -> float | None:
    if value is None:
        return None
    v = float(value.item() if hasattr(value, "item") else value)
    return v if math.isfinite(v) else None


def learned_verdict(
    trained_steps: int | None, best_val_mae_mm: Any, raw_val_mae_mm: Any, margin: float = DEFAULT_LEARNED_MARGIN
) -> dict[str, Any]:
    """Did the network learn? ``learned`` is True only when the run took at least one optimiser step and its
    best validation MAE is at most ``(1 - margin)`` times the raw (noisy input) validation MAE.

    Returns the run-level fields of ``metrics.json`` (``RUN_KEYS``); ``learned_reason`` says why in plain
    words (it starts with "not trained", "not verified", "did not learn" or "learned").
    """
    if not 0.0 <= float(margin) < 1.0:
        raise ValueError(f"learned margin must be in [0, 1), got {margin}")
    steps = int(trained_steps or 0)
    best, raw = _finite_or_none(best_val_mae_mm), _finite_or_none(raw_val_mae_mm)
    out: dict[str, Any] = {
        "method_kind": "network",
        "trained_steps": steps,
        "best_val_mae_mm": best,
        "raw_val_mae_mm": raw,
        "learned_margin": float(margin),
    }
    if steps <= 0:
        out["learned"] = False
        out["learned_reason"] = (
            "not trained: 0 optimiser steps (e.g. trainer.max_epochs=0); the metrics are those of the untrained network"
        )
        return out
    if best is None or raw is None:
        missing = " and ".join(n for n, v in (("best val MAE", best), ("raw val MAE", raw)) if v is None)
        out["learned"] = False
        out["learned_reason"] = (
            f"not verified: no {missing} was recorded (validation did not run), so nothing "
            "shows that the network learned"
        )
        return out
    needed = (1.0 - float(margin)) * raw
    out["learned"] = best <= needed
    if out["learned"]:
        out["learned_reason"] = (
            f"learned: best val MAE {best:.2f} mm <= {needed:.2f} mm (raw {raw:.2f} mm less {margin:.0%})"
        )
    else:
        out["learned_reason"] = (
            f"did not learn: best val MAE {best:.2f} mm vs raw {raw:.2f} mm "
            f"(needs <= {needed:.2f} mm, {margin:.0%} below raw)"
        )
    return out


def classical_verdict(
    best_val_mae_mm: Any, raw_val_mae_mm: Any, margin: float = DEFAULT_LEARNED_MARGIN
) -> dict[str, Any]:
    """The run-level fields of a classical (non-learned) method: ``method_kind`` "classical", 0 training steps,
    ``learned`` False (nothing was learned, and that is no failure: ``learned_status`` says "classical"), and
    as ``best_val_mae_mm`` the validation MAE of the parameters its tuning chose (``raw_val_mae_mm`` on the same
    images); ``learned_reason`` says whether that beat the raw input by ``margin``."""
    if not 0.0 <= float(margin) < 1.0:
        raise ValueError(f"learned margin must be in [0, 1), got {margin}")
    best, raw = _finite_or_none(best_val_mae_mm), _finite_or_none(raw_val_mae_mm)
    out: dict[str, Any] = {
        "method_kind": "classical",
        "trained_steps": 0,
        "best_val_mae_mm": best,
        "raw_val_mae_mm": raw,
        "learned_margin": float(margin),
        "learned": False,
    }
    base = "classical method: no trainable parameters, nothing learned"
    if best is None or raw is None:
        out["learned_reason"] = f"{base}; no validation result of its parameter tuning was recorded"
    else:
        needed = (1.0 - float(margin)) * raw
        verdict = "below" if best <= needed else "NOT below"
        out["learned_reason"] = (
            f"{base}; parameters tuned on the validation split: val MAE {best:.2f} mm vs raw "
            f"{raw:.2f} mm ({verdict} {needed:.2f} mm, {margin:.0%} below raw)"
        )
    return out


def learned_status(fields: Mapping[str, Any]) -> str:
    """One word-group for a verdict (``learned_verdict``, ``classical_verdict`` or the run fields of a
    ``metrics.json``): ``"learned"``, ``"not trained"``, ``"did not learn"``, ``"not verified"``,
    or ``"classical"`` (a non-learned method: not a failure)."""
    if fields.get("method_kind") == "classical":
        return "classical"
    if int(fields.get("trained_steps") or 0) <= 0:
        return "not trained"
    if fields["learned"] is True:
        return "learned"
    if fields.get("best_val_mae_mm") is None or fields.get("raw_val_mae_mm") is None:
        return "not verified"
    return "did not learn"
