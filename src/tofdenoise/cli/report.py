"""``tofdenoise report``: one self-contained offline HTML page comparing training runs.

    tofdenoise report RUNS_DIR [RUNS_DIR ...] --out report.html [--title TEXT]

A run is any folder (searched recursively under each RUNS_DIR, which may itself be a run) that holds a
``metrics.json`` (written by the training, schema in ``tofdenoise.records``). The page has a table
like the paper's (a "Raw input" row per distinct raw result, then one row per run: method, noise model, loss,
the "Learned" flag, PSNR/SSIM/MSE/MAE on synthetic and, when any run has it, real data; the best value of each
column in bold), a plot of validation MAE of all runs, and per run its learning curves and latest sample
panel; the same table is printed to stdout as Markdown. What is read from a run folder, the table, the plots
and the page: :mod:`tofdenoise.reporting`.

The "Learned" column shows the learned guard of each run: ``yes``; ``NOT LEARNED``; ``NOT TRAINED``;
``unverified``; ``classical`` (a non-learned method, not flagged); ``?`` (``tofdenoise.reporting.table``). Flagged
runs are shown in red and never get a bold
"best" value. Runs whose metrics.json is invalid are listed (with the reason) instead of stopping the report.
``--out`` must be a new or replaceable ``.html`` file outside the runs' records. Exit status 2 when no run is
found or ``--out`` is refused.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from tofdenoise.atomic import WriteError, atomic_write_text
from tofdenoise.output_guard import OutputPathError, check_output_file

__all__ = ["main"]


def _check_out(out: Path, run_dirs: Sequence[Path]) -> None:
    """``--out`` must be a new or replaceable ``.html`` file, never a file a run records (``metrics.json``,
    ``run_info.json``, a CSV log, a checkpoint: anything inside a run folder) or a name beside one
    (``tofdenoise.output_guard``)."""
    inputs = [f for d in run_dirs for f in d.iterdir() if f.is_file()]
    check_output_file(out, (".html", ".htm"), [*inputs, *run_dirs])


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="tofdenoise report",
        description="Self-contained offline HTML report comparing tofdenoise runs; "
        "prints the results table as Markdown.",
    )
    p.add_argument("runs_dir", nargs="+", type=Path, help="folder(s) searched recursively for runs (metrics.json)")
    p.add_argument("--out", required=True, type=Path, help="output HTML file")
    p.add_argument("--title", default="tofdenoise runs", help="page title")
    args = p.parse_args(argv)
    # the report's renderers (omegaconf, the plots): once the arguments are parsed
    from tofdenoise.reporting import find_runs, load_runs, render_html, results_table, table_markdown

    try:
        dirs = find_runs(args.runs_dir)
        _check_out(args.out, dirs)
    except (FileNotFoundError, OutputPathError) as exc:
        print(f"tofdenoise report: error: {exc}", file=sys.stderr)
        return 2
    runs, skipped = load_runs(dirs)
    for d, why in skipped:
        print(f"tofdenoise report: warning: run {d} left out: {why}", file=sys.stderr)
    if not runs:
        where = ", ".join(str(d) for d in args.runs_dir)
        print(f"tofdenoise report: error: no run with a valid metrics.json found under {where}", file=sys.stderr)
        return 2
    try:
        atomic_write_text(args.out, render_html(runs, args.title, skipped))
    except WriteError as exc:  # a full disk: one line naming the file, nothing half-written
        print(f"tofdenoise report: error: {exc}", file=sys.stderr)
        return 2
    sets, rows = results_table(runs)
    print(table_markdown(sets, rows))
    print(f"\nreport: {args.out} ({len(runs)} run(s))", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
