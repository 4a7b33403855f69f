"""The executor options shared by ``tofdenoise reproduce`` and ``tofdenoise grid`` (where a grid's runs go)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from tofdenoise.experiments.executors import EXECUTORS, SlurmOptions, make_executor, parse_sbatch_extra

__all__ = ["add_executor_arguments", "executor_from_args"]


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    d = SlurmOptions()
    g = parser.add_argument_group("where the runs go (docs/cluster.md)")
    g.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="sequential",
        help="sequential: one run after another (default); local: --workers runs at a time on this machine; "
        "slurm: a SLURM job array through submitit, one task per unfinished run, requeued on timeout or preemption",
    )
    g.add_argument("--workers", type=int, default=None, help="runs at a time for --executor local (default 2)")
    g.add_argument("--slurm-partition", default=None, help="sbatch --partition (default: the cluster's default)")
    g.add_argument(
        "--slurm-time-min",
        type=int,
        default=d.time_min,
        help=f"wall time of one task in minutes (default {d.time_min}); a longer run is requeued and resumes",
    )
    g.add_argument("--slurm-gpus-per-task", type=int, default=d.gpus_per_task, help=f"default {d.gpus_per_task}")
    g.add_argument("--slurm-cpus-per-task", type=int, default=d.cpus_per_task, help=f"default {d.cpus_per_task}")
    g.add_argument("--slurm-mem", default=d.mem, help=f"memory per task, sbatch's format (default {d.mem})")
    g.add_argument(
        "--slurm-array-parallelism",
        type=int,
        default=d.array_parallelism,
        help=f"array tasks running at once (default {d.array_parallelism})",
    )
    g.add_argument(
        "--slurm-max-requeues",
        type=int,
        default=d.max_requeues,
        help=f"requeues of a task after a timeout (default {d.max_requeues}; preemptions do not count)",
    )
    g.add_argument(
        "--slurm-signal-delay-s",
        type=int,
        default=d.signal_delay_s,
        help=f"seconds between the warning signal and the end of the allocation (default {d.signal_delay_s})",
    )
    g.add_argument(
        "--slurm-extra",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="extra sbatch options without '--', e.g. account=lab qos=high constraint=a100",
    )
    g.add_argument(
        "--slurm-setup",
        action="append",
        default=[],
        metavar="LINE",
        help="a shell line run in the job before the task (repeatable), e.g. 'module load cuda/12.4'",
    )
    g.add_argument(
        "--slurm-folder", type=Path, default=None, help="submitit's logs and job files (default <out>/slurm)"
    )
    g.add_argument(
        "--slurm-poll-s", type=float, default=d.poll_s, help=f"seconds between looks at the array (default {d.poll_s})"
    )


def executor_from_args(args: argparse.Namespace) -> Any:
    """The executor the options name; ValueError / RuntimeError (submitit missing) with a message naming the
    option."""
    slurm = None
    if args.executor == "slurm":
        slurm = SlurmOptions(
            partition=args.slurm_partition,
            time_min=args.slurm_time_min,
            gpus_per_task=args.slurm_gpus_per_task,
            cpus_per_task=args.slurm_cpus_per_task,
            mem=args.slurm_mem or None,
            array_parallelism=args.slurm_array_parallelism,
            max_requeues=args.slurm_max_requeues,
            signal_delay_s=args.slurm_signal_delay_s,
            extra=parse_sbatch_extra(args.slurm_extra),
            setup=tuple(args.slurm_setup),
            folder=args.slurm_folder,
            poll_s=args.slurm_poll_s,
        )
    return make_executor(args.executor, args.workers, slurm, check_cluster=not args.dry_run)
