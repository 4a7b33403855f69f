"""Rendering runs: the results table, the learning curves and one self-contained offline HTML page, the results page
and the grids' tables.

- :mod:`~tofdenoise.reporting.runs`: :func:`find_runs` (folders holding a ``metrics.json``), :func:`load_run`
  (metrics, names, learning curves, latest sample panel) -> :class:`Run`.
- :mod:`~tofdenoise.reporting.table`: :func:`results_table` (a "Raw input" row per distinct raw result, one row
  per run, the learned guard's flag) and :func:`table_markdown`.
- :mod:`~tofdenoise.reporting.plots`: learning curves of a run and the validation MAE of all runs, as PNG bytes.
- :mod:`~tofdenoise.reporting.page`: :func:`render_html`, the whole page (inline CSS, images as ``data:`` URIs).
- :mod:`~tofdenoise.reporting.numbers`: the metric columns, the number formatter and the reader of stored numbers
  that every table here (and ``experiments.tables``) shares.
- :mod:`~tofdenoise.reporting.results_page`: ``docs/results.md`` from the paper's run records
  (``tofdenoise reproduce``); :mod:`~tofdenoise.reporting.robustness`: the robustness grid's table
  (``tofdenoise grid``). What runs is defined in ``tofdenoise.experiments``; everything rendered lives here.

The command line is ``tofdenoise report`` (``tofdenoise.cli.report``).
"""

from __future__ import annotations

from tofdenoise.reporting.page import render_html
from tofdenoise.reporting.plots import comparison_png, learning_curves_png
from tofdenoise.reporting.runs import Run, find_runs, load_run, load_runs
from tofdenoise.reporting.table import learned_flag, results_table, table_markdown

__all__ = [
    "Run",
    "find_runs",
    "load_run",
    "load_runs",
    "results_table",
    "table_markdown",
    "learned_flag",
    "render_html",
    "learning_curves_png",
    "comparison_png",
]
