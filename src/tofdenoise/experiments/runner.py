"""Run a list of training runs, each in its own process and folder: resumable, skipped when finished, failures listed.

A *run spec* is a name plus the Hydra overrides of ``tofdenoise train``. :func:`run_all` gives every spec the
folder ``<out>/<name>`` and

* skips it when it has finished (``run_info.json`` has ``finished`` and ``metrics.json`` exists),
* resumes it from ``checkpoints/last.ckpt`` when a previous attempt was interrupted (``ckpt_path=last``),
* runs it otherwise, in a fresh ``python -m tofdenoise.cli.train`` process (a crash or an out-of-memory kill of
  one run cannot take the others down), with its output in ``<out>/<name>/train.log``,

and goes on after a failing run. The result lists every spec with its status (``done``, ``skipped``, ``failed``)
and the failed ones with the last lines of their log, so a grid of many runs can be completed over several
runs of the command and a failure is never silent.

A *time budget* (:class:`TimeBudget`: a GPU allocation of a fixed number of minutes, a SLURM job's time limit) bounds
the sequential runner: a run is not started when its estimated duration (``TimeBudget.estimate``, e.g. from the
committed records of the same row) exceeds the time left (status ``deferred``), and a run still training when the
budget ends is stopped (SIGTERM, so Lightning ends its step; SIGKILL after a grace period) with status ``stopped``:
its folder keeps ``checkpoints/last.ckpt`` (written every epoch), so the next call resumes it, and it is never
recorded half-trained (only a finished run has records).

By default the runs go one after another in the listed order. ``run_all(..., executor=...)`` hands the unfinished
ones to an executor of :mod:`tofdenoise.experiments.executors` instead (N local workers, a SLURM job array); each run
is still the same process writing the same folder, so its records do not depend on the executor.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# the one rule of a finished run, shared with the training job (tofdenoise.experiments.train_job)
from tofdenoise.records import LAST_CHECKPOINT, run_finished
from tofdenoise.run_lock import LOCK_NAME

__all__ = [
    "RunSpec",
    "RunOutcome",
    "TimeBudget",
    "PendingRun",
    "run_command",
    "run_one",
    "run_all",
    "ENTRY_MODULES",
]

LOG_NAME = "train.log"
#: RunSpec.entry -> the module run as ``python -m <module> <overrides> paths.run_dir=<folder>``
ENTRY_MODULES = {"train": "tofdenoise.cli.train", "classical": "tofdenoise.cli.classic"}


@dataclass(frozen=True)
class RunSpec:
    """One training run: a folder name (unique in its grid) and the ``tofdenoise train`` overrides."""

    name: str
    overrides: tuple[str, ...]
    meta: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    #: which command runs it: a key of ``ENTRY_MODULES`` ("train": ``tofdenoise train``)
    entry: str = "train"

    def __post_init__(self) -> None:
        if self.entry not in ENTRY_MODULES:
            raise ValueError(f"RunSpec {self.name}: unknown entry {self.entry!r}; valid: {', '.join(ENTRY_MODULES)}")
        if not self.name or "/" in self.name or self.name.startswith("."):
            raise ValueError(f"RunSpec.name must be a plain folder name, got {self.name!r}")
        for o in self.overrides:
            if o.split("=", 1)[0].lstrip("+") in ("paths.run_dir", "hydra.run.dir"):
                raise ValueError(f"RunSpec {self.name}: the runner sets the run folder; remove the override {o!r}")


@dataclass
class RunOutcome:
    spec: RunSpec
    run_dir: Path
    #: "done" (ran now), "skipped" (finished before), "failed", "planned" (dry run); with a time budget also
    #: "deferred" (not started: too little time left) and "stopped" (stopped at the budget's end, resumable)
    status: str
    seconds: float = 0.0
    returncode: int | None = None
    log_tail: str = ""


def _tail(path: Path, lines: int = 40) -> str:
    """The last ``lines`` lines of a run's log. 40 keeps the head of a Hydra composition error ("Could not find
    'backbone/nope'"), which is followed by one line per option of the group (9 backbones + 8 lines)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


@dataclass(frozen=True)
class TimeBudget:
    """A wall-clock limit for a list of runs: ``deadline`` on ``time.monotonic()``'s clock.

    ``estimate(spec)``: the seconds a run is expected to take (None: unknown, the run is started and stopped at the
    deadline if it has not finished); ``grace_s``: how long a stopped run may take to end its step after SIGTERM
    before it is killed."""

    deadline: float
    estimate: Callable[[RunSpec], float | None] = field(default=lambda spec: None)
    grace_s: float = 60.0

    @classmethod
    def minutes(cls, minutes: float, **kwargs: Any) -> TimeBudget:
        """A budget of ``minutes`` from now."""
        if not minutes > 0:
            raise ValueError(f"a time budget must be a positive number of minutes, got {minutes}")
        return cls(time.monotonic() + 60.0 * minutes, **kwargs)

    def left_s(self) -> float:
        return self.deadline - time.monotonic()


def clear_stale_lock(run_dir: Path, pid: int) -> bool:
    """Remove ``run_dir/run.lock`` when it names ``pid`` on this host, a process that has ended (killed: it could not
    release it). A folder carried to another machine, or a task requeued on another node, could not check a stale
    lock of this host and would refuse the run."""
    path = run_dir / LOCK_NAME
    try:
        holder = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    if isinstance(holder, dict) and holder.get("pid") == pid and holder.get("host") == socket.gethostname():
        path.unlink(missing_ok=True)
        return True
    return False


def stop_process(proc: subprocess.Popen, grace_s: float) -> int | None:
    """Stop a training process: SIGTERM (Lightning ends the step it is in and exits), SIGKILL after ``grace_s``
    seconds; its exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


@dataclass(frozen=True)
class PendingRun:
    """A run that an executor has to train: its place in the grid (``index``, 0-based), its spec and folder."""

    index: int
    total: int
    spec: RunSpec
    run_dir: Path

    @property
    def head(self) -> str:
        return f"[{self.index + 1}/{self.total}] {self.spec.name}"


def run_command(spec: RunSpec, run_dir: Path, python: str | None = None) -> tuple[list[str], bool]:
    """The command that trains ``spec`` in ``run_dir`` and whether it resumes (``checkpoints/last.ckpt`` exists
    now: decided when the run starts, so a run requeued after a preemption resumes)."""
    resume = (run_dir / LAST_CHECKPOINT).is_file()
    cmd = [python or sys.executable, "-m", ENTRY_MODULES[spec.entry], *spec.overrides, f"paths.run_dir={run_dir}"]
    if resume:
        cmd.append("ckpt_path=last")
    return cmd, resume


def run_one(
    spec: RunSpec,
    run_dir: Path,
    python: str | None = None,
    env: dict[str, str] | None = None,
    on_start: Callable[[subprocess.Popen], None] | None = None,
    preexec_fn: Callable[[], None] | None = None,
    budget: TimeBudget | None = None,
) -> RunOutcome:
    """Train one run in a fresh process (output appended to ``<run_dir>/train.log``) and return its outcome:
    ``done`` when the process exits 0 and the folder holds a finished run, else ``failed`` with the log's tail.

    ``on_start(process)`` is called once the process has started (an executor that must stop it on a
    preemption keeps it); ``preexec_fn`` runs in the child before it starts (``subprocess.Popen``). An exception in
    the caller (Ctrl-C, a preemption handler's exit) kills the process and propagates. At ``budget``'s deadline a
    process still running is stopped (:func:`stop_process`, with the budget's grace period) and the outcome is
    ``stopped``: the folder keeps its last epoch's checkpoint and the next run of it resumes there. A process stopped
    after its folder holds a finished run (between the test's records and its exit) is ``done``."""
    deadline = None if budget is None else budget.deadline
    cmd, _ = run_command(spec, run_dir, python)
    run_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(run_dir / LOG_NAME, "a") as log:
        log.write(f"\n# {time.strftime('%Y-%m-%dT%H:%M:%S')} {' '.join(cmd)}\n")
        log.flush()
        with subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}, preexec_fn=preexec_fn
        ) as proc:
            try:
                if on_start is not None:
                    on_start(proc)
                # polled, not proc.wait(): a signal handler (a SLURM task's preemption) may then wait for the
                # process itself without meeting the wait lock held by this frame
                while (returncode := proc.poll()) is None:
                    if deadline is not None and time.monotonic() >= deadline:
                        returncode = stop_process(proc, budget.grace_s)
                        log.write(
                            f"\n# {time.strftime('%Y-%m-%dT%H:%M:%S')} the time budget ended: training stopped "
                            f"(exit {returncode}); the next run of this folder resumes from {LAST_CHECKPOINT}\n"
                        )
                        break
                    time.sleep(0.2)
            except BaseException:
                proc.kill()
                raise
    seconds = time.perf_counter() - t0
    ok = returncode == 0 and run_finished(run_dir)
    if not ok and deadline is not None and time.monotonic() >= deadline:
        clear_stale_lock(run_dir, proc.pid)
        if run_finished(run_dir):  # stopped on its way out, its records complete: a finished run, not lost
            with open(run_dir / LOG_NAME, "a") as log:
                log.write("# it had written its records (run_info.json finished, metrics.json) before: recorded\n")
            return RunOutcome(spec, run_dir, "done", seconds, returncode)
        return RunOutcome(spec, run_dir, "stopped", seconds, returncode)
    return RunOutcome(
        spec, run_dir, "done" if ok else "failed", seconds, returncode, "" if ok else _tail(run_dir / LOG_NAME)
    )


def _ended_line(head: str, outcome: RunOutcome) -> str:
    if outcome.status == "deferred":
        return f"{head}: {outcome.log_tail}"
    if outcome.status == "stopped":
        return (
            f"{head}: stopped at the end of the time budget after {outcome.seconds / 60:.1f} min; not recorded, "
            f"resumes from {outcome.run_dir / LAST_CHECKPOINT} next time"
        )
    ok = outcome.status == "done"
    return f"{head}: {outcome.status} in {outcome.seconds / 60:.1f} min" + (
        "" if ok else f" (exit {outcome.returncode}; log: {outcome.run_dir / LOG_NAME})"
    )


def run_all(
    specs: Sequence[RunSpec],
    out_dir: Path | str,
    dry_run: bool = False,
    python: str | None = None,
    env: dict[str, str] | None = None,
    echo: bool = True,
    after_each: Callable[[RunOutcome], None] | None = None,
    executor: Any = None,
    budget: TimeBudget | None = None,
) -> list[RunOutcome]:
    """Run every spec not finished yet (see the module docstring); returns one outcome per spec, in order.

    ``after_each(outcome)`` is called after every spec (run, skipped or failed; not in a dry run), in this process,
    e.g. to commit a finished run's records at once, so that a grid interrupted later keeps what it has finished.

    ``executor``: where the runs go (``tofdenoise.experiments.executors``): None (or the sequential executor) runs
    them one after another, as listed; a parallel executor gets every unfinished run at once and
    ``after_each`` is called as each ends (finished runs first, then in the order they end).

    ``budget``: a :class:`TimeBudget` (the sequential runner, or an executor that takes one: the local one; a
    ``ValueError`` otherwise): runs that would not fit are ``deferred``, a run still training at its end is
    ``stopped`` (module docstring). With local workers each run is checked as a worker takes it up."""
    out_dir = Path(out_dir).expanduser().resolve()
    names = [s.name for s in specs]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"run_all: run names must be unique, repeated: {', '.join(dupes)}")
    python = python or sys.executable
    parallel = executor is not None and getattr(executor, "name", "") != "sequential"
    if budget is not None and parallel and not getattr(executor, "takes_budget", False):
        raise ValueError(f"a time budget needs the sequential or the local executor, not {executor.name}")
    if parallel:
        outcomes = _run_parallel(specs, out_dir, dry_run, python, env, echo, after_each, executor, budget)
    else:
        if echo and dry_run:
            print("executor: sequential (one run after another, each in its own process)", flush=True)
        outcomes = _run_sequential(specs, out_dir, dry_run, python, env, echo, after_each, budget)
    failed = [o for o in outcomes if o.status == "failed"]
    if echo and failed:
        print(f"{len(failed)} run(s) failed:", flush=True)
        for o in failed:
            print(
                f"  {o.spec.name} (exit {o.returncode}), last lines of {o.run_dir / LOG_NAME}:\n"
                + "\n".join("    " + line for line in o.log_tail.splitlines()),
                flush=True,
            )
    return outcomes


def _skipped_or_planned(
    job: PendingRun,
    python: str,
    dry_run: bool,
    echo: bool,
    after_each: Callable[[RunOutcome], None] | None,
) -> RunOutcome | None:
    """The outcome of a run that needs no process: ``skipped`` (finished before; ``after_each`` is called for it)
    or, in a dry run, ``planned``; None for a run that must run."""
    if run_finished(job.run_dir):
        outcome = RunOutcome(job.spec, job.run_dir, "skipped")
        if echo:
            print(f"{job.head}: finished before, skipped", flush=True)
        if after_each is not None:
            after_each(outcome)
        return outcome
    if not dry_run:
        return None
    cmd, resume = run_command(job.spec, job.run_dir, python)
    if echo:
        print(f"{job.head}: would run{' (resume)' if resume else ''}: {' '.join(cmd[1:])}", flush=True)
    return RunOutcome(job.spec, job.run_dir, "planned")


def _run_sequential(
    specs: Sequence[RunSpec],
    out_dir: Path,
    dry_run: bool,
    python: str,
    env: dict[str, str] | None,
    echo: bool,
    after_each: Callable[[RunOutcome], None] | None,
    budget: TimeBudget | None = None,
) -> list[RunOutcome]:
    outcomes: list[RunOutcome] = []
    for i, spec in enumerate(specs):
        job = PendingRun(i, len(specs), spec, out_dir / spec.name)
        settled = _skipped_or_planned(job, python, dry_run, echo, after_each)
        if settled is None and budget is not None:
            settled = deferred(job, budget, python)
            if settled is not None and echo:
                print(_ended_line(job.head, settled), flush=True)
        if settled is not None:
            outcomes.append(settled)
            continue
        _, resume = run_command(spec, job.run_dir, python)
        if echo:
            print(f"{job.head}: {'resuming' if resume else 'running'} -> {job.run_dir}", flush=True)
        outcome = run_one(spec, job.run_dir, python, env, budget=budget)
        outcomes.append(outcome)
        if echo:
            print(_ended_line(job.head, outcome), flush=True)
        if after_each is not None:
            after_each(outcome)
    return outcomes


def deferred(job: PendingRun, budget: TimeBudget, python: str) -> RunOutcome | None:
    """``deferred`` (the reason in ``log_tail``) when ``budget`` has too little time left for ``job`` (none at all,
    or less than its estimate; a run that resumes is started whenever time is left: what it trains is kept); None
    when it may start. The sequential runner and the local executor ask it before each run."""
    left_s = budget.left_s()
    _, resume = run_command(job.spec, job.run_dir, python)
    needed_s = None if resume else budget.estimate(job.spec)
    if left_s > 0 and (needed_s is None or needed_s <= left_s):
        return None
    need = "" if needed_s is None else f"needs about {needed_s / 60:.1f} min, "
    reason = f"not started: {need}{max(left_s, 0.0) / 60:.1f} min left of the time budget"
    return RunOutcome(job.spec, job.run_dir, "deferred", log_tail=reason)


def _run_parallel(
    specs: Sequence[RunSpec],
    out_dir: Path,
    dry_run: bool,
    python: str,
    env: dict[str, str] | None,
    echo: bool,
    after_each: Callable[[RunOutcome], None] | None,
    executor: Any,
    budget: TimeBudget | None = None,
) -> list[RunOutcome]:
    """Finished runs are skipped here; every other run goes to ``executor.run`` at once. ``after_each`` and the
    printing happen in this thread only (the executor calls back from the thread that called it)."""
    if echo:
        print(f"executor: {executor.describe()}", flush=True)
    outcomes: list[RunOutcome | None] = [None] * len(specs)
    pending: list[PendingRun] = []
    for i, spec in enumerate(specs):
        job = PendingRun(i, len(specs), spec, out_dir / spec.name)
        outcomes[i] = _skipped_or_planned(job, python, dry_run, echo, after_each)
        if outcomes[i] is None:
            pending.append(job)

    lock = threading.Lock()  # a local executor reports a start from its worker threads

    def started(job: PendingRun, where: str) -> None:
        if echo:
            with lock:
                print(f"{job.head}: {where} -> {job.run_dir}", flush=True)

    def finished(job: PendingRun, outcome: RunOutcome) -> None:
        outcomes[job.index] = outcome
        if echo:
            with lock:
                print(_ended_line(job.head, outcome), flush=True)
        if after_each is not None:
            after_each(outcome)

    if pending:
        extra = {} if budget is None else {"budget": budget}
        executor.run(pending, python=python, env=env, started=started, finished=finished, **extra)
    missing = [specs[i].name for i, o in enumerate(outcomes) if o is None]
    if missing:  # an executor that lost a run: never silent
        raise RuntimeError(f"executor {executor.name} returned no outcome for: {', '.join(missing)}")
    return [o for o in outcomes if o is not None]
