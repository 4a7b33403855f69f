"""``tofdenoise grid``: run a named grid of training runs (resumable) and print its table.

    tofdenoise grid robustness --out runs/robustness                 # all 108 runs (hours on 2 CPU cores)
    tofdenoise grid robustness --out runs/robustness --backbones unet --seeds 0 1 2
    tofdenoise grid robustness --out runs/robustness --table-only --markdown docs/robustness.md
    tofdenoise grid robustness --out runs/robustness --dry-run       # list what would run
    tofdenoise grid robustness --out runs/robustness --executor local --workers 2
    tofdenoise grid robustness --out runs/robustness --executor slurm --slurm-partition gpu   # docs/cluster.md

Finished runs are skipped, interrupted ones resume from their last checkpoint, a failing run does not stop the
others (they are listed at the end). Exit status: 0 when every selected run finished and passes, 1 otherwise, 2
when ``--markdown`` is refused (not ``.md``, or it would replace a file of a run: ``tofdenoise.output_guard``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tofdenoise.atomic import WriteError, atomic_write_text
from tofdenoise.cli.executor_args import add_executor_arguments, executor_from_args
from tofdenoise.experiments.grids import (
    ROBUSTNESS_BACKBONES,
    ROBUSTNESS_LOSSES,
    ROBUSTNESS_NOISES,
    ROBUSTNESS_SEEDS,
    ROBUSTNESS_SENSORS,
    robustness_rows,
    robustness_specs,
)
from tofdenoise.experiments.runner import run_all
from tofdenoise.output_guard import OutputPathError, check_output_file
from tofdenoise.records import RecordError, unreadable_records

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise grid",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("grid", choices=["robustness"], help="which grid")
    p.add_argument("--out", required=True, type=Path, help="folder of the grid's runs (one sub-folder per run)")
    p.add_argument("--backbones", nargs="+", default=list(ROBUSTNESS_BACKBONES), choices=list(ROBUSTNESS_BACKBONES))
    p.add_argument("--noises", nargs="+", default=list(ROBUSTNESS_NOISES), choices=list(ROBUSTNESS_NOISES))
    p.add_argument("--losses", nargs="+", default=list(ROBUSTNESS_LOSSES), choices=list(ROBUSTNESS_LOSSES))
    p.add_argument(
        "--sensors", nargs="+", default=list(ROBUSTNESS_SENSORS), help="sensor presets (configs/sensor/<name>.yaml)"
    )
    p.add_argument("--seeds", nargs="+", type=int, default=list(ROBUSTNESS_SEEDS))
    p.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    p.add_argument("--table-only", action="store_true", help="print the table of what has finished, run nothing")
    p.add_argument("--markdown", type=Path, default=None, help="also write the table to this Markdown file")
    add_executor_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        executor = executor_from_args(args)
    except (ValueError, RuntimeError) as exc:
        print(f"tofdenoise grid: error: {exc}", file=sys.stderr)
        return 2
    specs = robustness_specs(args.backbones, args.noises, args.losses, args.sensors, args.seeds, args.extra)
    if args.markdown is not None:
        try:  # the table never replaces a file of the runs it is made from
            check_output_file(args.markdown, (".md",), [args.out / s.name for s in specs], "--markdown", shadow=False)
        except OutputPathError as exc:
            print(f"tofdenoise grid: error: {exc}", file=sys.stderr)
            return 2
    if not args.table_only:
        run_all(specs, args.out, dry_run=args.dry_run, executor=executor)
    if args.dry_run:
        return 0
    broken = unreadable_records([args.out / s.name for s in specs])
    if broken:  # a table with that run as "incomplete" would hide a finished run's broken record
        print(
            f"tofdenoise grid: error: {broken[0]}" + (f" (and {len(broken) - 1} more)" if len(broken) > 1 else ""),
            file=sys.stderr,
        )
        return 2
    from tofdenoise.reporting.robustness import robustness_table  # omegaconf: only for the table

    try:
        rows = robustness_rows(specs, args.out)
    except RecordError as exc:  # a record the table cannot use: never a row that quietly lacks it
        print(f"tofdenoise grid: error: {exc}", file=sys.stderr)
        return 2
    table = robustness_table(rows)
    print(table)
    if args.markdown is not None:
        try:
            atomic_write_text(args.markdown, table + "\n")
        except WriteError as exc:  # a full disk: one line naming the file, nothing half-written
            print(f"tofdenoise grid: error: {exc}", file=sys.stderr)
            return 2
    return 0 if all(r["status"] == "pass" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
