"""``tofdenoise reproduce``: one of the paper's tables or figures, or a study, resumable, and ``docs/results.md``.

    tofdenoise reproduce --table 3 --profile cpu --seeds 0 1 2      # make reproduce TABLE=3 PROFILE=cpu SEEDS=0,1,2
    tofdenoise reproduce --figure 6 --profile cpu                   # the noise-model validation figure
    tofdenoise reproduce --figure 7                                 # qualitative figures (7 synthetic, 8 real)
    tofdenoise reproduce --study dynrange                           # beyond the paper: the dynamic-range study
    tofdenoise reproduce --table 1 --dry-run                        # list what would run
    tofdenoise reproduce --page-only                                # rebuild docs/results.md from docs/results/
    tofdenoise reproduce --table 3 --prepare-only --skip-recorded   # stand-in set and every run's data, no training
    tofdenoise reproduce --check                                    # rerun one record per table, compare (make
                                                                    # reproduce-check); --check 3 dynrange: those
    tofdenoise reproduce --table 3 --executor local --workers 2     # two runs at a time on this machine
    tofdenoise reproduce --table 3 --profile gpu-short --seeds 0  # the paper's recipe on the procedural world, one GPU
    tofdenoise reproduce --table 3 --profile gpu-short --seeds 0 --skip-recorded   # a fresh machine: the rest only
    tofdenoise reproduce --table 3 --profile gpu-short --seeds 0 1 2 --time-budget 12   # what fits 12 minutes
    tofdenoise reproduce --table 3 --profile gpu --executor slurm --slurm-partition gpu \
        --extra data.source_kwargs.root=...                          # a SLURM job array (docs/cluster.md)

This module parses the options and calls ``tofdenoise.experiments.reproduce.reproduce`` (the steps: the stand-in
real set, the runs, their records, the page; the targets: ``tofdenoise.experiments.targets``). Exit status 0 when
every run of the target finished, 1 when one did not; 2 for a usage error, for ``--page`` that would replace what
the page is built from (the discussion, a record: ``tofdenoise.output_guard``, checked before anything runs) and
for a record that cannot be used (``records.RecordError``, naming the file; a run without a record
is listed on the page as missing), and for ``--page-only`` with a ``--results`` folder that does not exist.
``--check`` (``tofdenoise.experiments.reproduce_check``): exit status 0 when every rerun matches its record within
the stated tolerance, 1 when one does not (the table says which), 2 when a table has no record to rerun. A
missing ``<results>/discussion.md`` is a warning naming it: the page is rebuilt without its discussion (a fresh
results folder has none yet).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tofdenoise.atomic import WriteError
from tofdenoise.cli.executor_args import add_executor_arguments, executor_from_args
from tofdenoise.experiments.targets import CHECK_TABLES, KINDS, PROFILES, Target
from tofdenoise.output_guard import OutputPathError, check_output_file
from tofdenoise.paths import REPO_ROOT
from tofdenoise.records import RecordError

__all__ = ["build_parser", "main"]

PROG = "tofdenoise reproduce"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    what = p.add_mutually_exclusive_group()
    what.add_argument("--table", choices=KINDS["table"], help="one of the paper's tables (I, II, III)")
    what.add_argument(
        "--figure",
        choices=KINDS["figure"],
        help="one of the paper's figures: 6 (noise-model validation), 7 / 8 (qualitative, synthetic / real)",
    )
    what.add_argument(
        "--study",
        choices=KINDS["study"],
        help="a study beyond the paper (dynrange: across the dynamic range; schedule: DVSS's training "
        "noises at 10x gpu-short's steps; dataseed: Table III on a second data seed)",
    )
    what.add_argument(
        "--check",
        nargs="*",
        choices=CHECK_TABLES,
        metavar="TABLE",
        help="rerun one small recorded run per table at this commit and compare it with its record within a stated "
        f"tolerance (default: every table, {' '.join(CHECK_TABLES)}); run folders under runs/reproduce-check/<profile>",
    )
    p.add_argument("--profile", choices=sorted(PROFILES), default="cpu")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--out", type=Path, default=None, help="run folders (default runs/reproduce/<profile>)")
    p.add_argument(
        "--results",
        type=Path,
        default=REPO_ROOT / "docs" / "results",
        help="where the run records are committed (default docs/results)",
    )
    p.add_argument("--page", type=Path, default=REPO_ROOT / "docs" / "results.md", help="the results page")
    p.add_argument(
        "--extra", nargs="*", default=[], help="extra Hydra overrides for every run (e.g. data.source_kwargs.root=...)"
    )
    p.add_argument(
        "--skip-recorded",
        action="store_true",
        help="do not run again a run whose records are committed in <results>/<profile>/ (for a machine without "
        "its run folder, such as a fresh GPU machine); tables and studies only",
    )
    p.add_argument(
        "--rerun-earlier",
        action="store_true",
        help="with --skip-recorded: a committed record of the earlier test protocol (no simulator-noised split) "
        "does not count, so the run trains again and its record moves the table to the current protocol",
    )
    p.add_argument(
        "--rerun-without-truth",
        action="store_true",
        help="with --skip-recorded: a committed record without its score against the stand-in set's truth "
        "(real_vs_truth.json, which needs the run's checkpoint) does not count, so the run trains again",
    )
    p.add_argument(
        "--time-budget",
        type=float,
        default=None,
        metavar="MINUTES",
        help="train for at most MINUTES (a GPU allocation's limit; the sequential or the local executor): a run "
        "whose recorded "
        "duration on this profile does not fit the time left is not started, a run still training at the end is "
        "stopped and resumes from its last epoch's checkpoint in the same --out next time; never recorded "
        "half-trained. Leave a margin for the real-set scoring after each run",
    )
    p.add_argument(
        "--run-minutes",
        nargs="+",
        default=[],
        metavar="NAME=MIN",
        help="with --time-budget: the minutes a run of this backbone (dvss=5) or this run name is expected to take, in "
        "place of the committed records' median wall time (which may come from other code or a shared machine)",
    )
    p.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    p.add_argument(
        "--page-only",
        action="store_true",
        help="only rebuild the results page and the study figures (dynamic-range gains, long-schedule curves) "
        "from the records",
    )
    p.add_argument(
        "--prepare-only",
        action="store_true",
        help="build the stand-in set and prepare the data of every run still to train (each distinct data config "
        "once, every CPU core), then stop: no training, no page (tables and studies; e.g. on a GPU machine beside "
        "other work, so that a later --time-budget call spends its minutes training)",
    )
    add_executor_arguments(p)
    return p


def _target(args: argparse.Namespace) -> Target | None:
    for kind in KINDS:
        name = getattr(args, kind)
        if name is not None:
            return Target(kind, name)
    return None


def _check(args: argparse.Namespace) -> int:
    from tofdenoise.experiments.reproduce_check import reproduce_check  # omegaconf, the configs: only for a check

    out = (args.out or REPO_ROOT / "runs" / "reproduce-check" / args.profile).expanduser().resolve()
    try:
        result = reproduce_check(
            args.results,
            out,
            profile=args.profile,
            tables=args.check or CHECK_TABLES,
            dry_run=args.dry_run,
            extra=args.extra,
        )
    except (RecordError, WriteError, ValueError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    return 0 if args.dry_run or result.passed else 1


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.check is not None:
        return _check(args)
    target = _target(args)
    if target is None and not args.page_only:  # a usage error: exit 2, as argparse's own
        studies = "|".join(KINDS["study"])
        print(
            f"{PROG}: error: give --table 1|2|3, --figure 6|7|8 or --study {studies} (or --page-only)", file=sys.stderr
        )
        return 2
    if args.skip_recorded and (target is None or target.kind == "figure"):
        print(
            f"{PROG}: error: --skip-recorded applies to --table and --study (a figure needs its runs' checkpoints)",
            file=sys.stderr,
        )
        return 2
    if args.prepare_only and (target is None or target.kind == "figure"):
        print(f"{PROG}: error: --prepare-only applies to --table and --study", file=sys.stderr)
        return 2
    for flag, given in (("--rerun-earlier", args.rerun_earlier), ("--rerun-without-truth", args.rerun_without_truth)):
        if given and not args.skip_recorded:
            print(f"{PROG}: error: {flag} applies with --skip-recorded", file=sys.stderr)
            return 2
    if args.time_budget is not None and (target is None or target.kind == "figure" or not args.time_budget > 0):
        print(
            f"{PROG}: error: --time-budget takes a positive number of minutes and applies to --table and --study",
            file=sys.stderr,
        )
        return 2
    try:
        executor = executor_from_args(args)
    except (ValueError, RuntimeError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    if args.time_budget is not None and not getattr(executor, "takes_budget", False):
        print(
            f"{PROG}: error: --time-budget needs the sequential or the local executor (a SLURM job has its own "
            "time limit)",
            file=sys.stderr,
        )
        return 2
    # the runner, the figures and the page renderer (numpy, Pillow, omegaconf): once the arguments are checked
    from tofdenoise.experiments.reproduce import Reproduction, parse_run_minutes, profile_needs, reproduce

    if args.run_minutes and args.time_budget is None:
        print(f"{PROG}: error: --run-minutes applies with --time-budget", file=sys.stderr)
        return 2
    try:
        run_minutes = parse_run_minutes(args.run_minutes)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    from tofdenoise.reporting.results_page import DISCUSSION_NAME, page_inputs

    job = Reproduction(
        target=None if args.page_only else target,
        results=args.results,
        page=args.page,
        profile=args.profile,
        seeds=args.seeds,
        extra=args.extra,
        dry_run=args.dry_run,
        executor=executor,
        skip_recorded=args.skip_recorded,
        rerun_earlier=args.rerun_earlier,
        rerun_without_truth=args.rerun_without_truth,
        time_budget_min=args.time_budget,
        run_minutes=run_minutes,
        prepare_only=args.prepare_only,
    )
    if job.target is None and not args.results.is_dir():  # else an empty page, exit 0
        print(
            f"{PROG}: error: --results {args.results}: no such folder (the run records the page is built from)",
            file=sys.stderr,
        )
        return 2
    discussion = args.results / DISCUSSION_NAME
    if not args.dry_run and not discussion.is_file():  # the page is still rebuilt, but not silently without it
        print(
            f"{PROG}: warning: {discussion}: no such file; the page is rebuilt without its discussion", file=sys.stderr
        )
    try:
        # the page is rebuilt from the discussion and the records: it may never replace one of them
        check_output_file(args.page, (".md",), page_inputs(args.results), what="--page", shadow=False)
        if job.target is not None:
            # a SLURM array trains on the cluster's GPUs: the submitting machine needs none
            slurm = True if args.executor == "slurm" else None
            missing = profile_needs(args.profile, args.extra, cuda_available=slurm)
            if missing:  # before the real set is built or any run starts, in a dry run too
                print(f"{PROG}: error: --profile {args.profile} needs {missing}", file=sys.stderr)
                return 2
            job.out = (args.out or REPO_ROOT / "runs" / "reproduce" / args.profile).expanduser().resolve()
        return reproduce(job)
    except (OutputPathError, RecordError, WriteError, ValueError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
