"""The comparison table of runs, like the paper's: one "Raw input" row per distinct raw result, then one row per
run (method, noise model, loss, the "Learned" flag, PSNR/SSIM/MSE/MAE per test set; the best value of each
column in bold, never that of a run flagged by the learned guard).

The "Learned" column (:func:`learned_flag`) shows the learned guard of each run: ``yes``; ``NOT LEARNED`` (the
best validation MAE was not ``learned_margin`` below the raw MAE); ``NOT TRAINED`` (0 optimiser steps, e.g.
``trainer.max_epochs=0``: the metrics are those of an untrained network); ``unverified`` (no validation
result); ``classical`` (a non-learned method, ``method_kind`` "classical": its parameters were tuned on the
validation split, no training is expected; not flagged).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tofdenoise.records import learned_status
from tofdenoise.reporting.numbers import METRIC_COLUMNS, format_number, read_number
from tofdenoise.reporting.runs import Run

__all__ = [
    "SET_LABELS",
    "MISSING",
    "LEARNED_FLAGS",
    "FLAGGED",
    "learned_flag",
    "results_table",
    "table_markdown",
    "best_value",
]

#: column-group labels of the report (the words of each set: ``records.TEST_SET_LABELS``)
SET_LABELS = {"synthetic": "Synthetic", "simulated": "Simulator-noised", "real": "Real"}
#: a cell without a value
MISSING = "–"
#: the Learned column per ``tofdenoise.records.learned_status``
LEARNED_FLAGS = {
    "learned": "yes",
    "did not learn": "NOT LEARNED",
    "not trained": "NOT TRAINED",
    "not verified": "unverified",
    "classical": "classical",
}
#: learned-guard statuses shown in red and never bold
FLAGGED = {"did not learn", "not trained", "not verified"}


def learned_flag(run: Run) -> str:
    """The Learned column of a run: ``yes``, ``NOT LEARNED``, ``NOT TRAINED``, ``unverified``, ``classical`` or
    ``?``."""
    return LEARNED_FLAGS[learned_status(run.learned)]


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return a == b or abs(a - b) <= 1e-6 * max(1.0, abs(a), abs(b))


def results_table(runs: Sequence[Run]) -> tuple[list[str], list[dict[str, Any]]]:
    """(set names shown, rows); a row: {"kind": "raw"|"run", "method", "noise", "loss", "learned" (the flag),
    (set, key) -> float}; run rows also carry "name", "flagged" (bool), "learned_reason" and "data" (the number of
    the raw row of the test data the run was scored on; None without raw values)."""
    sets = [s for s in ("synthetic", "simulated", "real") if any(s in r.metrics for r in runs)]
    sets += sorted({s for r in runs for s in r.metrics} - set(sets))
    raw_rows: list[dict[str, Any]] = []
    data_of: dict[int, int] = {}  # run's place in ``runs`` -> its raw row: the test data it was scored on
    for place, r in enumerate(runs):
        values = {
            (s, k): read_number(r.metrics[s]["raw"][k])
            for s in sets
            if s in r.metrics and "raw" in r.metrics[s]
            for k, *_ in METRIC_COLUMNS
        }
        if not values:
            continue
        # runs evaluated on the same data share one raw row: merge when no common value differs
        for number, row in enumerate(raw_rows):
            common = [c for c in values if c in row]
            if common and all(_same(row[c], values[c]) for c in common):
                row.update(values)
                if r.noise not in row["noises"]:
                    row["noises"].append(r.noise)
                data_of[place] = number
                break
        else:
            data_of[place] = len(raw_rows)
            raw_rows.append(
                {"kind": "raw", "method": "Raw input", "loss": "–", "learned": "–", "noises": [r.noise], **values}
            )
    for row in raw_rows:
        row["noise"] = ", ".join(row.pop("noises"))
    run_rows = []
    for place, r in enumerate(runs):
        status = learned_status(r.learned)
        row: dict[str, Any] = {
            "kind": "run",
            "method": r.method,
            "noise": r.noise,
            "loss": r.loss,
            "name": r.name,
            "learned": LEARNED_FLAGS[status],
            "flagged": status in FLAGGED,
            "learned_reason": str(r.learned.get("learned_reason", "")),
            "data": data_of.get(place),
        }
        for s in sets:
            for k, *_ in METRIC_COLUMNS:
                row[(s, k)] = read_number(r.metrics.get(s, {}).get(k))
        run_rows.append(row)
    return sets, raw_rows + run_rows


def best_value(rows: list[dict[str, Any]], col: tuple[str, str], higher: bool, data: Any = None) -> float | None:
    """Best value of a column among the runs not flagged by the learned guard that were scored on the test data
    ``data`` (a run row's ``"data"``: runs on other data, an easier test set, are never compared); None with fewer
    than two."""
    vals = [
        row[col]
        for row in rows
        if row["kind"] == "run" and not row.get("flagged") and row.get(col) is not None and row.get("data") == data
    ]
    if len(vals) < 2:
        return None
    return max(vals) if higher else min(vals)


def table_markdown(sets: Sequence[str], rows: list[dict[str, Any]]) -> str:
    """The comparison table as GitHub Markdown (best run value per column in bold)."""
    header = ["Method", "Noise", "Loss", "Learned"] + [
        f"{SET_LABELS.get(s, s)} {m.text}" for s in sets for m in METRIC_COLUMNS
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 4 + ["---:"] * (len(header) - 4)) + "|"]
    for row in rows:
        cells = [row["method"], row["noise"], row["loss"], row["learned"]]
        for s in sets:
            for key, _, _, dec, higher in METRIC_COLUMNS:
                v = row.get((s, key))
                text = format_number(v, dec, MISSING)
                if (
                    v is not None
                    and row["kind"] == "run"
                    and not row["flagged"]
                    and v == best_value(rows, (s, key), higher, row.get("data"))
                ):
                    text = f"**{text}**"
                cells.append(text)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
