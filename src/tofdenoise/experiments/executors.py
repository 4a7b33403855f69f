"""Where the runs of a grid go: one after another (``sequential``), N local workers (``local``), or a SLURM job
array through submitit (``slurm``).

:func:`tofdenoise.experiments.runner.run_all` decides what has to run (finished runs are skipped, interrupted ones
resume from ``checkpoints/last.ckpt``) and hands the unfinished runs to an executor. Whatever the executor, every run
is the same ``python -m tofdenoise.cli.train ... paths.run_dir=<out>/<name>`` process writing the same folder, and
the records are the run's own files, so the records, the tables and the results page do not depend on the
executor. ``run_all`` calls ``after_each`` (the commit of a finished run's records) in the process that called it,
as each run ends.

* ``sequential``: today's behaviour, in the listed order (``run_all`` without an executor).
* ``local``: ``workers`` runs at a time on this machine, each still in its own process (a thread per worker only
  waits for its process).
* ``slurm``: one array task per unfinished run (``sbatch --array``, at most ``array_parallelism`` at once), through
  submitit directly. Each task runs :class:`RunTask`: the same training process, inside the allocation. On a
  timeout or a preemption SLURM signals the task (``--signal=USR2@<signal_delay_s>``); submitit calls
  :meth:`RunTask.checkpoint`, which stops the training process (SIGTERM: Lightning ends the step it is in; SIGKILL
  after ``grace_s``), clears its run lock, and returns the same task for submitit to requeue; the requeued task
  resumes from ``last.ckpt``. A timed-out task is requeued at most ``max_requeues`` times (preemptions do not
  count). The command that submitted the array waits for its tasks and commits each run as it ends.

Why submitit directly and not hydra-submitit-launcher: the launcher launches the jobs of a Hydra multirun, one
job per point of a Cartesian sweep, each composed and run in the launching Python function. The grids here are
lists of named runs (tables share runs, rows are not Cartesian) run by :mod:`tofdenoise.experiments.runner`, whose
skip / resume / one-process-per-run / failure-listing logic would have to be rebuilt inside Hydra's sweep. Submitit
is the library the launcher itself wraps; calling it directly keeps one runner for every executor.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tofdenoise.records import LAST_CHECKPOINT, RUNS_AT_ONCE_ENV, run_finished

from .runner import LOG_NAME, PendingRun, RunOutcome, RunSpec, TimeBudget, _tail, clear_stale_lock, deferred, run_one

__all__ = [
    "EXECUTORS",
    "LocalExecutor",
    "RunTask",
    "SequentialExecutor",
    "SlurmExecutor",
    "SlurmOptions",
    "make_executor",
    "parse_sbatch_extra",
]

EXECUTORS = ("sequential", "local", "slurm")

Started = Callable[[PendingRun, str], None]
Finished = Callable[[PendingRun, RunOutcome], None]


class SequentialExecutor:
    """One run after another, in the listed order: ``run_all``'s own loop (nothing is handed over)."""

    name = "sequential"
    #: a ``--time-budget`` applies (run_all's own loop checks it): executors say whether they take one
    takes_budget = True

    def describe(self) -> str:
        return "sequential (one run after another, each in its own process)"


@dataclass
class LocalExecutor:
    """``workers`` runs at a time on this machine, each in its own process; with a time budget (``run``'s
    ``budget``) each run is checked as a worker takes it up (``deferred`` when it would not fit) and stopped at the
    budget's end, as on the sequential runner: several runs share one GPU allocation."""

    workers: int
    name: str = field(default="local", init=False)
    takes_budget: bool = field(default=True, init=False)

    def __post_init__(self) -> None:
        if not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"--workers must be a whole number >= 1, got {self.workers!r}")

    def describe(self) -> str:
        return f"local ({self.workers} worker{'s' if self.workers != 1 else ''}, each run in its own process)"

    def run(
        self,
        jobs: Sequence[PendingRun],
        python: str,
        env: dict[str, str] | None,
        started: Started,
        finished: Finished,
        budget: TimeBudget | None = None,
    ) -> None:
        """Run ``jobs`` ``workers`` at a time; ``finished`` is called in this thread as each ends. On an exception
        here (Ctrl-C) the running processes are killed and no new one starts. ``budget``: see the class. Each run's
        environment says how many train at a time (``RUNS_AT_ONCE_ENV``; its record's ``machine.runs_at_once``)."""
        env = {**(env or {}), RUNS_AT_ONCE_ENV: str(self.workers)}
        processes: set[subprocess.Popen] = set()
        guard = threading.Lock()
        stop = threading.Event()

        def keep(proc: subprocess.Popen) -> None:
            with guard:
                processes.add(proc)

        def work(job: PendingRun) -> RunOutcome | None:
            if stop.is_set():
                return None
            if budget is not None and (late := deferred(job, budget, python)) is not None:
                return late
            started(job, "resuming" if (job.run_dir / LAST_CHECKPOINT).is_file() else "running")
            return run_one(job.spec, job.run_dir, python, env, on_start=keep, budget=budget)

        pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="tofdenoise-run")
        futures: dict[Future, PendingRun] = {}
        try:
            futures = {pool.submit(work, job): job for job in jobs}
            todo = set(futures)
            while todo:
                done, todo = wait(todo, return_when=FIRST_COMPLETED)
                for future in sorted(done, key=lambda f: futures[f].index):
                    outcome = future.result()
                    if outcome is not None:
                        finished(futures[future], outcome)
        except BaseException:
            stop.set()
            for future in futures:
                future.cancel()
            with guard:
                for proc in processes:
                    if proc.poll() is None:
                        proc.kill()
            raise
        finally:
            pool.shutdown(wait=True)


# --------------------------------------------------------------------------------------------------- SLURM


def parse_sbatch_extra(items: Sequence[str]) -> dict[str, str]:
    """``["account=lab", "qos=high"]`` -> ``{"account": "lab", "qos": "high"}``: extra ``#SBATCH --key=value``
    lines (``--slurm-extra``)."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip().lstrip("-")
        if not sep or not key:
            raise ValueError(f"--slurm-extra expects KEY=VALUE (an sbatch option without its '--'), got {item!r}")
        out[key] = value
    return out


@dataclass(frozen=True)
class SlurmOptions:
    """The sbatch settings of every array task (one task = one training run)."""

    partition: str | None = None
    #: wall time of one task in minutes (a longer run is requeued at its timeout and resumes)
    time_min: int = 24 * 60
    gpus_per_task: int = 1
    cpus_per_task: int = 8
    #: memory per task, sbatch's format ("64G"); None: the partition's default
    mem: str | None = "64G"
    #: how many array tasks may run at once (sbatch --array=0-N%P)
    array_parallelism: int = 32
    #: how many times a task is requeued after a timeout (preemptions do not count)
    max_requeues: int = 5
    #: seconds between the warning signal and the end of the allocation
    signal_delay_s: int = 120
    #: seconds a stopped training process gets to end its step before it is killed
    grace_s: int = 60
    #: extra sbatch options, without the "--": {"account": "lab", "qos": "high", "constraint": "a100"}
    extra: dict[str, str] = field(default_factory=dict)
    #: shell lines run in the job before the task ("module load cuda/12.4", "source .venv/bin/activate")
    setup: tuple[str, ...] = ()
    #: submitit's folder (job scripts, pickles, the tasks' stdout/stderr); default <out>/slurm
    folder: Path | None = None
    #: seconds between two looks at the array's state
    poll_s: float = 30.0
    #: submitit cluster: "slurm"; "local" runs the same tasks through submitit's LocalExecutor (tests, a try-out)
    cluster: str = "slurm"

    def __post_init__(self) -> None:
        for name in ("time_min", "cpus_per_task", "array_parallelism", "signal_delay_s"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"--slurm-{name.replace('_', '-')} must be a whole number >= 1, got {value!r}")
        for name in ("gpus_per_task", "max_requeues", "grace_s"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise ValueError(f"--slurm-{name.replace('_', '-')} must be a whole number >= 0, got {value!r}")
        if self.signal_delay_s >= 60 * self.time_min:
            raise ValueError(
                f"--slurm-signal-delay-s ({self.signal_delay_s} s) must be shorter than --slurm-time-min "
                f"({self.time_min} min)"
            )
        if self.cluster not in ("slurm", "local"):
            raise ValueError(f"SlurmOptions.cluster must be 'slurm' or 'local', got {self.cluster!r}")


def _import_submitit() -> Any:
    try:
        import submitit  # optional: the `cluster` extra
    except ImportError as exc:
        raise RuntimeError(
            "--executor slurm needs submitit, which is not installed: pip install -e '.[cluster]' "
            "(make venv installs it)"
        ) from exc
    return submitit


#: the training process of the task running in this process (a SLURM array task runs one run)
_ACTIVE: dict[str, subprocess.Popen] = {}


def _preempt_signal() -> signal.Signals:
    """The signal submitit treats as "timeout or preemption" (its ``SUBMITIT_PREEMPT_SIGNAL``, USR2 by default)."""
    name = os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2")
    return getattr(signal, f"SIG{name}", signal.SIGUSR2)


def _ignore_preempt_signal() -> None:  # runs in the training process before exec: the task decides, not it
    signal.signal(_preempt_signal(), signal.SIG_IGN)


class RunTask:
    """One array task: train one run (``run_one``) unless it has finished. Submitit calls :meth:`checkpoint` on a
    timeout or preemption signal and requeues what it returns: this task, which resumes the run from
    ``last.ckpt`` (``run_command`` adds ``ckpt_path=last``)."""

    def __init__(self, spec: RunSpec, run_dir: Path, python: str, env: dict[str, str] | None = None, grace_s=60):
        self.spec, self.run_dir, self.python, self.env, self.grace_s = spec, Path(run_dir), python, env, grace_s

    def __call__(self) -> RunOutcome:
        if run_finished(self.run_dir):  # a requeued task whose run had finished, or a duplicate submission
            return RunOutcome(self.spec, self.run_dir, "skipped")

        def keep(proc: subprocess.Popen) -> None:
            _ACTIVE[self.spec.name] = proc

        try:
            return run_one(
                self.spec, self.run_dir, self.python, self.env, on_start=keep, preexec_fn=_ignore_preempt_signal
            )
        finally:
            _ACTIVE.pop(self.spec.name, None)

    def stop_training(self) -> int | None:
        """Stop this task's training process: SIGTERM (Lightning ends the current step and exits), SIGKILL after
        ``grace_s``; then clear the lock it may leave. Its exit status, None when none was running.

        It runs inside submitit's signal handler, which may interrupt ``Popen.poll`` in ``run_one`` while that holds
        the process's wait lock: so it waits with ``os.waitpid`` itself, never through the ``Popen``."""
        proc = _ACTIVE.get(self.spec.name)
        if proc is None:
            return None
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            deadline, killed = time.monotonic() + self.grace_s, False
            while True:
                try:
                    pid, status = os.waitpid(proc.pid, os.WNOHANG)
                except ChildProcessError:  # reaped meanwhile
                    break
                if pid == proc.pid:
                    proc.returncode = os.waitstatus_to_exitcode(status)
                    break
                if not killed and time.monotonic() > deadline:
                    proc.kill()
                    killed = True
                time.sleep(0.1)
        clear_stale_lock(self.run_dir, proc.pid)
        return proc.returncode

    def checkpoint(self, *args: Any, **kwargs: Any) -> Any:
        """Submitit's hook on a timeout / preemption: stop the training, note it in the run's log, requeue."""
        from submitit.helpers import DelayedSubmission  # the task runs under submitit: it is installed

        code = self.stop_training()
        try:
            with open(self.run_dir / LOG_NAME, "a") as log:
                log.write(
                    f"\n# {time.strftime('%Y-%m-%dT%H:%M:%S')} timeout or preemption signal: training stopped "
                    f"(exit {code}); the task is requeued and resumes from checkpoints/last.ckpt\n"
                )
        except OSError:
            pass
        return DelayedSubmission(self)


class SlurmExecutor:
    """A SLURM job array through submitit, one task per run (module docstring); waits for the tasks."""

    name = "slurm"

    def __init__(self, options: SlurmOptions | None = None):
        self.options = options or SlurmOptions()

    def describe(self) -> str:
        o = self.options
        where = "SLURM job array through submitit" if o.cluster == "slurm" else "submitit's local executor"
        extra = "".join(f", --{k}={v}" for k, v in o.extra.items())
        return (
            f"slurm ({where}: partition {o.partition or '(default)'}, {o.time_min} min per task, "
            f"{o.gpus_per_task} GPU(s), {o.cpus_per_task} CPUs, mem {o.mem or '(default)'} per task, at most "
            f"{o.array_parallelism} at once, requeued up to {o.max_requeues} times on timeout{extra}; "
            f"submitit logs in {o.folder or '<out>/slurm'})"
        )

    def folder(self, out_dir: Path) -> Path:
        return Path(self.options.folder or out_dir / "slurm").expanduser().resolve()

    def make_submitit_executor(self, out_dir: Path) -> Any:
        submitit = _import_submitit()
        o = self.options
        executor = submitit.AutoExecutor(
            folder=str(self.folder(out_dir) / "%j"),
            cluster=o.cluster,
            slurm_max_num_timeout=o.max_requeues,
            local_max_num_timeout=o.max_requeues,
        )
        params: dict[str, Any] = {"name": "tofdenoise", "timeout_min": o.time_min, "cpus_per_task": o.cpus_per_task}
        if o.cluster == "slurm":
            params.update(
                slurm_partition=o.partition,
                slurm_gpus_per_task=o.gpus_per_task or None,
                slurm_mem=o.mem,
                slurm_array_parallelism=o.array_parallelism,
                slurm_signal_delay_s=o.signal_delay_s,
                slurm_additional_parameters=dict(o.extra) or None,
                slurm_setup=list(o.setup) or None,
                slurm_stderr_to_stdout=True,
            )
        else:
            params.update(local_setup=list(o.setup) or None)  # its warning signal comes 30 s before the end
        executor.update_parameters(**params)
        return executor

    def run(
        self,
        jobs: Sequence[PendingRun],
        python: str,
        env: dict[str, str] | None,
        started: Started,
        finished: Finished,
    ) -> None:
        """Submit one array of ``jobs``, then wait; ``finished`` is called in this thread as each task ends."""
        out_dir = jobs[0].run_dir.parent
        executor = self.make_submitit_executor(out_dir)
        tasks = [RunTask(job.spec, job.run_dir, python, env, self.options.grace_s) for job in jobs]
        submitted = executor.submit_array(tasks)
        for job, sub in zip(jobs, submitted):
            started(job, f"submitted as job {sub.job_id} (submitit log {sub.paths.stdout})")
        remaining = dict(zip(range(len(jobs)), submitted))
        while remaining:
            for k in sorted(remaining):
                if remaining[k].done():
                    finished(jobs[k], self._outcome(jobs[k], remaining.pop(k)))
            if remaining:
                time.sleep(self.options.poll_s)

    @staticmethod
    def _outcome(job: PendingRun, sub: Any) -> RunOutcome:
        """The task's own outcome, or ``failed`` with the run log's and submitit log's tails when the task did not
        return one (it raised, was cancelled, or timed out more than ``max_requeues`` times)."""
        try:
            outcome = sub.result()
        except Exception as exc:  # submitit raises UncompletedJobError / FailedJobError with the task's error
            tail = _tail(job.run_dir / LOG_NAME, 20)
            sub_tail = _tail(Path(sub.paths.stdout), 20)
            text = f"{tail}\n--- submitit ({sub.paths.stdout}):\n{sub_tail}\n--- {type(exc).__name__}: {exc}"
            return RunOutcome(job.spec, job.run_dir, "failed", 0.0, None, text.strip()[-6000:])
        if not isinstance(outcome, RunOutcome):
            return RunOutcome(job.spec, job.run_dir, "failed", 0.0, None, f"task returned {outcome!r}")
        return RunOutcome(job.spec, job.run_dir, outcome.status, outcome.seconds, outcome.returncode, outcome.log_tail)


def make_executor(
    name: str, workers: int | None = None, slurm: SlurmOptions | None = None, check_cluster: bool = False
) -> Any:
    """The executor called ``name`` (``EXECUTORS``); a clear error for a bad name or option. ``check_cluster``:
    also refuse ``slurm`` where SLURM's ``sbatch`` and ``srun`` are not on PATH (a dry run needs neither)."""
    if name == "sequential":
        if workers not in (None, 1):
            raise ValueError(f"--workers {workers} needs --executor local (sequential runs one at a time)")
        return SequentialExecutor()
    if name == "local":
        return LocalExecutor(2 if workers is None else workers)
    if name == "slurm":
        if workers is not None:
            raise ValueError("--workers is for --executor local; a SLURM array's width is --slurm-array-parallelism")
        _import_submitit()  # fail before anything runs
        options = slurm or SlurmOptions()
        missing = [tool for tool in ("sbatch", "srun") if shutil.which(tool) is None]
        if check_cluster and options.cluster == "slurm" and missing:
            raise RuntimeError(
                f"--executor slurm submits with SLURM's sbatch, and {' and '.join(missing)} is not on PATH here: "
                "run the command on the cluster's login node (--dry-run works anywhere)"
            )
        return SlurmExecutor(options)
    raise ValueError(f"--executor must be one of {', '.join(EXECUTORS)}, got {name!r}")
