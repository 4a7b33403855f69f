"""``tofdenoise-report``: one self-contained offline HTML page comparing training runs.

    tofdenoise-report RUNS_DIR [RUNS_DIR ...] --out report.html [--title TEXT]

A run is any folder (searched recursively under each RUNS_DIR, which may itself be a run) that holds a
``metrics.json`` (written by the training, schema in ``tofdenoise.training.results``). From a run
folder the report reads:

- ``metrics.json``: final test metrics per set (``synthetic``, ``real``) with the ``raw`` (noisy input) block,
  and the learned guard's run-level fields (``learned``, ``learned_reason``, ``trained_steps``, ...);
- ``run_info.json`` ``{"backbone", "noise", "loss", "run_name"}`` (optional ``"method"`` label), else
  ``.hydra/config.yaml`` (``backbone.name``, ``noise.name``, ``loss.name``, ``run_name``), else the folder name;
- every ``metrics.csv`` below the run (Lightning's CSVLogger) for learning curves: columns ``step``/``epoch``
  and the logged values; the training loss (``train*loss*``) is drawn against ``step``, validation values
  ending in ``mae_mm`` / ``psnr_db`` against ``epoch`` (``step`` when there is no epoch column);
- ``panels/*.png`` (``ImagePanelLogger``): the latest validation panel (highest epoch number in the name).

The page has a table like the paper's (one "Raw input" row per distinct raw result, then one row per run:
method, noise model, loss, the "Learned" flag, PSNR/SSIM/MSE/MAE on synthetic and, when any run has it, real
data; the best value of each column in bold), a plot of validation MAE of all runs, and per run its learning curves and
latest sample panel. Images are embedded as base64 ``data:`` URIs, CSS is inline, nothing is fetched from
a network. The same table is printed to stdout as Markdown.

The "Learned" column (``learned_flag``) shows the learned guard of each run: ``yes``; ``NOT LEARNED`` (the best
validation MAE was not ``learned_margin`` below the raw MAE); ``NOT TRAINED`` (0 optimiser steps, e.g.
``trainer.max_epochs=0``: the metrics are those of an untrained network); ``unverified`` (no validation result);
``?`` (a metrics.json written before the guard existed). Flagged runs (all but ``yes`` and ``?``) are
shown in red and never get a bold "best" value. Runs whose metrics.json is invalid are listed
(with the reason) instead of stopping the report. Exit status 2 when no run is found.
"""

from __future__ import annotations

import argparse
import base64
import csv
import html
import io
import json
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from tofdenoise.atomic import atomic_write_text
from tofdenoise.training.results import (
    learned_status,
    metric_sets,
    read_metrics_json,
    run_fields,
)
from tofdenoise.cli.output_guard import OutputPathError, check_output_file

__all__ = ["Run", "find_runs", "load_run", "results_table", "table_markdown", "render_html", "main",
           "learned_flag"]

METRIC_COLUMNS = (  # key, header, decimals, higher is better
    ("psnr_db", "PSNR (dB)&uarr;", "PSNR (dB)↑", 2, True),
    ("ssim", "SSIM&uarr;", "SSIM↑", 4, True),
    ("mse_mm2", "MSE (mm&sup2;)&darr;", "MSE (mm²)↓", 2, False),
    ("mae_mm", "MAE (mm)&darr;", "MAE (mm)↓", 2, False),
)
SET_LABELS = {"synthetic": "Synthetic", "real": "Real"}
#: the Learned column per ``tofdenoise.training.results.learned_status``
LEARNED_FLAGS = {"learned": "yes", "did not learn": "NOT LEARNED", "not trained": "NOT TRAINED",
                 "not verified": "unverified", "unknown": "?"}
_FLAGGED = {"did not learn", "not trained", "not verified"}
_SKIP_DIRS = {"wandb", "checkpoints", "panels", ".hydra", "csv", "tensorboard", "predictions", "__pycache__"}


@dataclass
class Run:
    path: Path
    name: str
    method: str
    noise: str
    loss: str
    metrics: dict[str, Any]
    curves: list[dict[str, Any]] = field(default_factory=list)
    panel: Path | None = None
    #: the learned guard's run-level fields of metrics.json (empty for files written before it existed)
    learned: dict[str, Any] = field(default_factory=dict)


def learned_flag(run: Run) -> str:
    """The Learned column of a run: ``yes``, ``NOT LEARNED``, ``NOT TRAINED``, ``unverified`` or ``?``."""
    return LEARNED_FLAGS[learned_status(run.learned)]


def find_runs(roots: Sequence[str | Path]) -> list[Path]:
    """Run folders (holding ``metrics.json``) under ``roots``, sorted, without duplicates."""
    found: set[Path] = set()
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"runs folder not found: {root}")
        for mj in root.rglob("metrics.json"):
            rel = mj.relative_to(root).parts[:-1]
            if any(p in _SKIP_DIRS or p.startswith(".") for p in rel[-1:]):
                continue
            found.add(mj.parent.resolve())
    return sorted(found)


def _hydra_info(path: Path) -> dict[str, Any]:
    """backbone/noise/loss names and run_name from a saved Hydra config (interpolations resolved if possible)."""
    from omegaconf import OmegaConf

    try:
        cfg = OmegaConf.load(path)
    except Exception as exc:  # noqa: BLE001 - any YAML/OmegaConf error: report the file
        raise ValueError(f"{path}: not a readable config ({exc})") from None

    def pick(key: str) -> Any:
        try:
            value = OmegaConf.select(cfg, key, default=None)
        except Exception:  # noqa: BLE001 - unresolvable interpolation (e.g. a resolver not registered here)
            return None
        return value if isinstance(value, (str, int, float)) else None

    return {"backbone": pick("backbone.name"), "noise": pick("noise.name"), "loss": pick("loss.name"),
            "run_name": pick("run_name")}


def _read_info(run_dir: Path) -> dict[str, str]:
    info: dict[str, Any] = {}
    path = run_dir / "run_info.json"
    if path.is_file():
        try:
            info = json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
    else:
        hydra_cfg = run_dir / ".hydra" / "config.yaml"
        if hydra_cfg.is_file():
            info = _hydra_info(hydra_cfg)
    out = {k: str(v) for k, v in info.items() if v is not None and not isinstance(v, (dict, list))}
    out.setdefault("run_name", run_dir.name)
    return out


def _read_curves(run_dir: Path) -> list[dict[str, Any]]:
    """Rows of every ``metrics.csv`` below the run (numbers as float; empty cells dropped)."""
    rows: list[dict[str, Any]] = []
    for csv_path in sorted(run_dir.rglob("metrics.csv")):
        with open(csv_path, newline="", encoding="utf-8") as fh:
            for rec in csv.DictReader(fh):
                row: dict[str, Any] = {}
                for k, v in rec.items():
                    if k is None or v in (None, ""):
                        continue
                    try:
                        row[k] = float(v)
                    except ValueError:
                        continue
                if row:
                    rows.append(row)
    return rows


def _epoch_order(path: Path) -> tuple[int, str]:
    """Sort key: the last number in the file name (epoch_999 < epoch_1000), then the name."""
    numbers = re.findall(r"\d+", path.stem)
    return (int(numbers[-1]) if numbers else -1, path.name)


def load_run(run_dir: str | Path) -> Run:
    """Read one run folder (raises ValueError/FileNotFoundError naming the bad file)."""
    run_dir = Path(run_dir)
    data = read_metrics_json(run_dir / "metrics.json")
    metrics, learned = metric_sets(data), run_fields(data)
    info = _read_info(run_dir)
    panels = sorted((run_dir / "panels").glob("*.png"), key=_epoch_order) if (run_dir / "panels").is_dir() else []
    return Run(path=run_dir, name=info["run_name"], method=info.get("method", info.get("backbone", info["run_name"])),
               noise=info.get("noise", "?"), loss=info.get("loss", "?"), metrics=metrics,
               curves=_read_curves(run_dir), panel=panels[-1] if panels else None, learned=learned)


# ------------------------------------------------------------------------------------------------ table
def _value(v: Any) -> float | None:
    if v is None:
        return None
    if v == "inf":
        return math.inf
    if v == "-inf":
        return -math.inf
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return a == b or abs(a - b) <= 1e-6 * max(1.0, abs(a), abs(b))


def results_table(runs: Sequence[Run]) -> tuple[list[str], list[dict[str, Any]]]:
    """(set names shown, rows); a row: {"kind": "raw"|"run", "method", "noise", "loss", "learned" (the flag),
    (set, key) -> float}; run rows also carry "name", "flagged" (bool) and "learned_reason"."""
    sets = [s for s in ("synthetic", "real") if any(s in r.metrics for r in runs)]
    sets += sorted({s for r in runs for s in r.metrics} - set(sets))
    raw_rows: list[dict[str, Any]] = []
    for r in runs:
        values = {(s, k): _value(r.metrics[s]["raw"][k]) for s in sets if s in r.metrics and "raw" in r.metrics[s]
                  for k, *_ in METRIC_COLUMNS}
        if not values:
            continue
        # runs evaluated on the same data share one raw row: merge when no common value differs
        for row in raw_rows:
            common = [c for c in values if c in row]
            if common and all(_same(row[c], values[c]) for c in common):
                row.update(values)
                if r.noise not in row["noises"]:
                    row["noises"].append(r.noise)
                break
        else:
            raw_rows.append({"kind": "raw", "method": "Raw input", "loss": "–", "learned": "–", "noises": [r.noise],
                             **values})
    for row in raw_rows:
        row["noise"] = ", ".join(row.pop("noises"))
    run_rows = []
    for r in runs:
        status = learned_status(r.learned)
        row: dict[str, Any] = {"kind": "run", "method": r.method, "noise": r.noise, "loss": r.loss, "name": r.name,
                               "learned": LEARNED_FLAGS[status], "flagged": status in _FLAGGED,
                               "learned_reason": str(r.learned.get("learned_reason", ""))}
        for s in sets:
            for k, *_ in METRIC_COLUMNS:
                row[(s, k)] = _value(r.metrics.get(s, {}).get(k))
        run_rows.append(row)
    return sets, raw_rows + run_rows


def _best(rows: list[dict[str, Any]], col: tuple[str, str], higher: bool) -> float | None:
    """Best value of a column among the runs not flagged by the learned guard (None with fewer than two)."""
    vals = [row[col] for row in rows if row["kind"] == "run" and not row.get("flagged") and row.get(col) is not None]
    if len(vals) < 2:
        return None
    return max(vals) if higher else min(vals)


def _fmt(v: float | None, decimals: int) -> str:
    if v is None:
        return "–"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.{decimals}f}"


def table_markdown(sets: Sequence[str], rows: list[dict[str, Any]]) -> str:
    """The comparison table as GitHub Markdown (best run value per column in bold)."""
    header = (["Method", "Noise", "Loss", "Learned"]
              + [f"{SET_LABELS.get(s, s)} {m[2]}" for s in sets for m in METRIC_COLUMNS])
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 4 + ["---:"] * (len(header) - 4)) + "|"]
    for row in rows:
        cells = [row["method"], row["noise"], row["loss"], row["learned"]]
        for s in sets:
            for key, _, _, dec, higher in METRIC_COLUMNS:
                v = row.get((s, key))
                text = _fmt(v, dec)
                if v is not None and row["kind"] == "run" and not row["flagged"] and v == _best(rows, (s, key), higher):
                    text = f"**{text}**"
                cells.append(text)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ plots
def _png_data_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _figure_png(draw, size=(9.0, 3.0), ncols: int = 1) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=90)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    draw(axes)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _series(rows: list[dict[str, Any]], key: str, x_pref: Sequence[str]) -> tuple[list[float], list[float], str]:
    for x in x_pref:
        pts = [(r[x], r[key]) for r in rows if key in r and x in r and math.isfinite(r[key])]
        if pts:
            pts.sort()
            # one value per x (Lightning may log a metric once per epoch on several rows)
            dedup: dict[float, float] = {}
            for xv, yv in pts:
                dedup[xv] = yv
            return list(dedup), list(dedup.values()), x
    return [], [], x_pref[-1]


def _curve_groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[str], tuple[str, ...]]]:
    cols = sorted({k for r in rows for k in r} - {"step", "epoch"})
    groups = [
        ("training loss", [c for c in cols if c.startswith("train") and "loss" in c], ("step",)),
        ("validation MAE (mm)", [c for c in cols if c.startswith("val") and c.endswith("mae_mm")], ("epoch", "step")),
        ("validation PSNR (dB)", [c for c in cols if c.startswith("val") and c.endswith("psnr_db")],
         ("epoch", "step")),
    ]
    return [g for g in groups if g[1]]


def learning_curves_png(run: Run) -> bytes | None:
    """Learning curves of one run (training loss; validation MAE and PSNR, raw dashed), or None."""
    groups = _curve_groups(run.curves)
    if not groups:
        return None

    def draw(axes):
        for ax, (title, cols, xs) in zip(axes, groups):
            for c in cols:
                x, y, xname = _series(run.curves, c, xs)
                if x:
                    ax.plot(x, y, "--" if "raw" in c else "-", marker="o" if len(x) < 30 else None, ms=3,
                            label=c)
                    ax.set_xlabel(xname)
            ax.set_title(title, fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)

    return _figure_png(draw, size=(4.0 * len(groups), 3.0), ncols=len(groups))


def comparison_png(runs: Sequence[Run]) -> bytes | None:
    """Validation MAE (mm) of all runs on one plot, or None when no run logged one."""
    series = []
    for r in runs:
        cols = [c for c in sorted({k for row in r.curves for k in row}) if c.startswith("val")
                and c.endswith("mae_mm") and "raw" not in c and "pooled" not in c]
        if cols:
            x, y, xname = _series(r.curves, cols[0], ("epoch", "step"))
            if x:
                series.append((r.name, x, y, xname))
    if not series:
        return None

    def draw(axes):
        ax = axes[0]
        for name, x, y, xname in series:
            ax.plot(x, y, marker="o" if len(x) < 30 else None, ms=3, label=name)
            ax.set_xlabel(xname)
        ax.set_ylabel("validation MAE (mm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)

    return _figure_png(draw, size=(7.0, 3.4))


# ------------------------------------------------------------------------------------------------ html
_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px;color:#1d1d1f;background:#fff}
h1{font-size:22px} h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ddd;padding-bottom:4px}
h3{font-size:15px;margin-bottom:4px} .meta{color:#666;font-size:12px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{padding:4px 9px;border-bottom:1px solid #e3e3e3;text-align:right;white-space:nowrap}
th{background:#f5f5f7;border-bottom:2px solid #999} td.l,th.l{text-align:left}
tr.raw td{color:#666;font-style:italic} th.set{text-align:center;border-bottom:1px solid #bbb}
img{max-width:100%;border:1px solid #ddd;margin:4px 0} .run{margin-bottom:28px}
.warn{color:#a40000} tr.flagged td{color:#a40000} tr.flagged td.learned{font-weight:bold}
"""


def _learned_cell(row: dict[str, Any]) -> str:
    e = html.escape
    reason = row.get("learned_reason")
    title = f' title="{e(reason)}"' if reason else ""
    return f'<td class="l learned"{title}>{e(str(row["learned"]))}</td>'


def _table_html(sets: Sequence[str], rows: list[dict[str, Any]]) -> str:
    e = html.escape
    head1 = '<tr><th class="l" rowspan="2">Method</th><th class="l" rowspan="2">Noise</th>' \
            '<th class="l" rowspan="2">Loss</th><th class="l" rowspan="2">Learned</th>' + "".join(
                f'<th class="set" colspan="{len(METRIC_COLUMNS)}">{e(SET_LABELS.get(s, s))}</th>' for s in sets) + \
            "</tr>"
    head2 = "<tr>" + "".join(f"<th>{m[1]}</th>" for _ in sets for m in METRIC_COLUMNS) + "</tr>"
    body = []
    for row in rows:
        cells = [f'<td class="l">{e(str(row["method"]))}</td>', f'<td class="l">{e(str(row["noise"]))}</td>',
                 f'<td class="l">{e(str(row["loss"]))}</td>', _learned_cell(row)]
        for s in sets:
            for key, _, _, dec, higher in METRIC_COLUMNS:
                v = row.get((s, key))
                text = e(_fmt(v, dec))
                if v is not None and row["kind"] == "run" and not row["flagged"] and v == _best(rows, (s, key), higher):
                    text = f"<b>{text}</b>"
                cells.append(f"<td>{text}</td>")
        title = f' title="{e(str(row["name"]))}"' if "name" in row else ""
        kind = row["kind"] + (" flagged" if row.get("flagged") else "")
        body.append(f'<tr class="{kind}"{title}>' + "".join(cells) + "</tr>")
    return f"<table><thead>{head1}{head2}</thead><tbody>{''.join(body)}</tbody></table>"


def render_html(runs: Sequence[Run], title: str = "tofdenoise runs", skipped: Sequence[tuple[Path, str]] = ()) -> str:
    """The whole report page (self-contained)."""
    e = html.escape
    sets, rows = results_table(runs)
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{e(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{e(title)}</h1>",
             f'<p class="meta">{len(runs)} run(s). Metrics over valid pixels, per image then averaged '
             "(PSNR with D<sub>max</sub> = 1000 mm). &ldquo;Raw input&rdquo; rows: the noisy input itself. "
             "Best run value per column in bold. &ldquo;Learned&rdquo;: NOT LEARNED = the best validation MAE was not "
             "below the raw one by the margin; NOT TRAINED = no optimiser step (the untrained network); unverified = "
             "no validation result; ? = written before this check existed. Flagged runs are red and never bold.</p>",
             "<h2>Results</h2>", _table_html(sets, rows)]
    if skipped:
        parts.append("<h2>Runs left out</h2><ul>" + "".join(
            f'<li class="warn">{e(str(p))}: {e(reason)}</li>' for p, reason in skipped) + "</ul>")
    comp = comparison_png(runs)
    if comp:
        parts.append(f'<h2>Validation MAE</h2><img alt="validation MAE of all runs" src="{_png_data_uri(comp)}">')
    parts.append("<h2>Runs</h2>")
    for r in runs:
        parts.append(f'<div class="run"><h3>{e(r.name)}</h3><p class="meta">{e(str(r.path))} &middot; '
                     f"method {e(r.method)} &middot; noise {e(r.noise)} &middot; loss {e(r.loss)}</p>")
        status = learned_status(r.learned)
        if status != "unknown":
            css = "warn" if status in _FLAGGED else "meta"
            parts.append(f'<p class="{css}">{e(learned_flag(r))}: {e(str(r.learned.get("learned_reason", "")))}</p>')
        curves = learning_curves_png(r)
        if curves:
            parts.append(f'<img alt="learning curves of {e(r.name)}" src="{_png_data_uri(curves)}">')
        else:
            parts.append('<p class="meta">no metrics.csv with learning curves</p>')
        if r.panel is not None:
            parts.append(f'<p class="meta">latest validation panel: {e(r.panel.name)}</p>'
                         f'<img alt="sample panel of {e(r.name)}" src="{_png_data_uri(r.panel.read_bytes())}">')
        parts.append("</div>")
    parts.append("</body></html>\n")
    return "".join(parts)


def _check_out(out: Path, run_dirs: Sequence[Path]) -> None:
    """``--out`` must be a new or replaceable ``.html`` file, never a file a run records (``metrics.json``,
    ``run_info.json``, a CSV log, a checkpoint: anything inside a run folder) or a name beside one."""
    inputs = [f for d in run_dirs for f in d.iterdir() if f.is_file()]
    check_output_file(out, (".html", ".htm"), inputs)
    if out.exists():
        target = out.resolve()
        for d in run_dirs:
            if target.is_relative_to(d.resolve()):
                raise OutputPathError(f"--out {out} is a file of the run {d}; write the report outside the run "
                                      f"folders or under a new name")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tofdenoise-report",
                                description="Self-contained offline HTML report comparing tofdenoise runs; "
                                            "prints the results table as Markdown.")
    p.add_argument("runs_dir", nargs="+", type=Path, help="folder(s) searched recursively for runs (metrics.json)")
    p.add_argument("--out", required=True, type=Path, help="output HTML file")
    p.add_argument("--title", default="tofdenoise runs", help="page title")
    args = p.parse_args(argv)
    try:
        dirs = find_runs(args.runs_dir)
        _check_out(args.out, dirs)
    except (FileNotFoundError, OutputPathError) as exc:
        print(f"tofdenoise-report: error: {exc}", file=sys.stderr)
        return 2
    runs: list[Run] = []
    skipped: list[tuple[Path, str]] = []
    for d in dirs:
        try:
            runs.append(load_run(d))
        except (OSError, ValueError) as exc:
            skipped.append((d, str(exc)))
            print(f"tofdenoise-report: warning: run {d} left out: {exc}", file=sys.stderr)
    if not runs:
        where = ", ".join(str(d) for d in args.runs_dir)
        print(f"tofdenoise-report: error: no run with a valid metrics.json found under {where}", file=sys.stderr)
        return 2
    runs.sort(key=lambda r: r.name)
    atomic_write_text(args.out, render_html(runs, args.title, skipped))
    sets, rows = results_table(runs)
    print(table_markdown(sets, rows))
    print(f"\nreport: {args.out} ({len(runs)} run(s))", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
