"""The report page: one self-contained offline HTML file (inline CSS, images as base64 ``data:`` URIs, nothing
fetched from a network): the results table, the validation MAE of all runs, the runs left out (with the
reason), and per run its learned verdict, learning curves and latest sample panel. Flagged runs (the learned
guard) are shown in red.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tofdenoise.records import learned_status
from tofdenoise.reporting.numbers import METRIC_COLUMNS, format_number
from tofdenoise.reporting.plots import comparison_png, learning_curves_png
from tofdenoise.reporting.runs import Run
from tofdenoise.reporting.table import FLAGGED, MISSING, SET_LABELS, best_value, learned_flag, results_table

__all__ = ["render_html"]


def _png_data_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


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
    head1 = (
        '<tr><th class="l" rowspan="2">Method</th><th class="l" rowspan="2">Noise</th>'
        '<th class="l" rowspan="2">Loss</th><th class="l" rowspan="2">Learned</th>'
        + "".join(f'<th class="set" colspan="{len(METRIC_COLUMNS)}">{e(SET_LABELS.get(s, s))}</th>' for s in sets)
        + "</tr>"
    )
    head2 = "<tr>" + "".join(f"<th>{m.html}</th>" for _ in sets for m in METRIC_COLUMNS) + "</tr>"
    body = []
    for row in rows:
        cells = [
            f'<td class="l">{e(str(row["method"]))}</td>',
            f'<td class="l">{e(str(row["noise"]))}</td>',
            f'<td class="l">{e(str(row["loss"]))}</td>',
            _learned_cell(row),
        ]
        for s in sets:
            for key, _, _, dec, higher in METRIC_COLUMNS:
                v = row.get((s, key))
                text = e(format_number(v, dec, MISSING))
                if (
                    v is not None
                    and row["kind"] == "run"
                    and not row["flagged"]
                    and v == best_value(rows, (s, key), higher, row.get("data"))
                ):
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
    parts = [
        f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{e(title)}</title>'
        f"<style>{_CSS}</style></head><body><h1>{e(title)}</h1>",
        f'<p class="meta">{len(runs)} run(s). Metrics over valid pixels, per image then averaged '
        "(PSNR with D<sub>max</sub> = 1000 mm). &ldquo;Raw input&rdquo; rows: the noisy input itself. "
        "Best run value per column in bold. &ldquo;Learned&rdquo;: NOT LEARNED = the best validation MAE was not "
        "below the raw one by the margin; NOT TRAINED = no optimiser step (the untrained network); unverified = "
        "no validation result; classical = a non-learned filter, parameters tuned on validation. "
        "Flagged runs are red and never bold.</p>",
        "<h2>Results</h2>",
        _table_html(sets, rows),
    ]
    if skipped:
        parts.append(
            "<h2>Runs left out</h2><ul>"
            + "".join(f'<li class="warn">{e(str(p))}: {e(reason)}</li>' for p, reason in skipped)
            + "</ul>"
        )
    comp = comparison_png(runs)
    if comp:
        parts.append(f'<h2>Validation MAE</h2><img alt="validation MAE of all runs" src="{_png_data_uri(comp)}">')
    parts.append("<h2>Runs</h2>")
    for r in runs:
        parts.append(
            f'<div class="run"><h3>{e(r.name)}</h3><p class="meta">{e(str(r.path))} &middot; '
            f"method {e(r.method)} &middot; noise {e(r.noise)} &middot; loss {e(r.loss)}</p>"
        )
        status = learned_status(r.learned)
        css = "warn" if status in FLAGGED else "meta"
        parts.append(f'<p class="{css}">{e(learned_flag(r))}: {e(str(r.learned["learned_reason"]))}</p>')
        curves = learning_curves_png(r)
        if curves:
            parts.append(f'<img alt="learning curves of {e(r.name)}" src="{_png_data_uri(curves)}">')
        else:
            parts.append('<p class="meta">no metrics.csv with learning curves</p>')
        if r.panel is not None:
            parts.append(
                f'<p class="meta">latest validation panel: {e(r.panel.name)}</p>'
                f'<img alt="sample panel of {e(r.name)}" src="{_png_data_uri(r.panel.read_bytes())}">'
            )
        parts.append("</div>")
    parts.append("</body></html>\n")
    return "".join(parts)
