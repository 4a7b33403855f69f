"""Run a list of training runs, each in its own process and folder: resumable, skipped when finished, failures listed.

A *run spec* is a name plus the Hydra overrides of ``tofdenoise-train``. :func:`run_all` gives every spec the
folder ``<out>/<name>`` and

* skips it when it has finished (``run_info.json`` has ``finished`` and ``metrics.json`` exists),
* resumes it from ``checkpoints/last.ckpt`` when a previous attempt was interrupted (``ckpt_path=last``),
* runs it otherwise, in a fresh ``python -m tofdenoise.cli.train`` process (a crash or an out-of-memory kill of
  one run cannot take the others down), with its output in ``<out>/<name>/train.log``,

and goes on after a failing run. The result lists every spec with its status (``done``, ``skipped``, ``failed``)
and the failed ones with the last lines of their log, so a grid of many runs can be completed over several
sittings and a failure is never silent.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tofdenoise.training.results import METRICS_NAME, RUN_INFO_NAME

__all__ = ["RunSpec", "RunOutcome", "run_finished", "run_all", "read_run", "ENTRY_MODULES"]

LOG_NAME = "train.log"
#: RunSpec.entry -> the module run as ``python -m <module> <overrides> paths.run_dir=<folder>``
ENTRY_MODULES = {"train": "tofdenoise.cli.train", "classical": "tofdenoise.cli.classic"}


@dataclass(frozen=True)
class RunSpec:
    """One training run: a folder name (unique in its grid) and the ``tofdenoise-train`` overrides."""

    name: str
    overrides: tuple[str, ...]
    meta: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    #: which command runs it: a key of ``ENTRY_MODULES`` ("train": ``tofdenoise-train``)
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
    status: str  # "done" (ran now), "skipped" (finished before), "failed", "planned" (dry run)
    seconds: float = 0.0
    returncode: int | None = None
    log_tail: str = ""


def read_run(run_dir: Path) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """``(run_info, metrics)`` of a run folder; ``None`` for a file that is missing or does not parse."""
    out: list[dict[str, Any] | None] = []
    for name in (RUN_INFO_NAME, METRICS_NAME):
        try:
            out.append(json.loads((run_dir / name).read_text()))
        except (OSError, ValueError):
            out.append(None)
    return out[0], out[1]


def unreadable_records(run_dirs: Sequence[Path]) -> list[str]:
    """``"<file>: <why>"`` for each record (``run_info.json``, ``metrics.json``) of the run folders that exists but
    is not a JSON object: a finished run whose record broke must not pass for an unfinished one in a table."""
    bad = []
    for run_dir in run_dirs:
        for name in (RUN_INFO_NAME, METRICS_NAME):
            path = Path(run_dir) / name
            if not path.is_file():
                continue
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                bad.append(f"{path}: the record cannot be read ({exc})")
                continue
            if not isinstance(data, dict):
                bad.append(f"{path}: not a JSON object")
    return bad


def run_finished(run_dir: Path) -> bool:
    """True when the run folder holds a finished run: ``run_info.json`` with ``finished`` and a ``metrics.json``."""
    info, metrics = read_run(run_dir)
    return bool(info and info.get("finished")) and metrics is not None


def _tail(path: Path, lines: int = 40) -> str:
    """The last ``lines`` lines of a run's log. 40 keeps the head of a Hydra composition error ("Could not find
    'backbone/nope'"), which is followed by one line per option of the group (9 backbones + 8 lines)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def run_all(
    specs: Sequence[RunSpec],
    out_dir: Path | str,
    dry_run: bool = False,
    python: str | None = None,
    env: dict[str, str] | None = None,
    echo: bool = True,
    after_each: Callable[[RunOutcome], None] | None = None,
) -> list[RunOutcome]:
    """Run every spec not finished yet (see the module docstring); returns one outcome per spec, in order.

    ``after_each(outcome)`` is called after every spec (run, skipped or failed; not in a dry run), e.g. to commit
    a finished run's records at once, so that a grid interrupted later keeps what it has finished."""
    out_dir = Path(out_dir).expanduser().resolve()
    names = [s.name for s in specs]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"run_all: run names must be unique, repeated: {', '.join(dupes)}")
    python = python or sys.executable
    outcomes: list[RunOutcome] = []
    for i, spec in enumerate(specs, 1):
        run_dir = out_dir / spec.name
        head = f"[{i}/{len(specs)}] {spec.name}"
        if run_finished(run_dir):
            outcomes.append(RunOutcome(spec, run_dir, "skipped"))
            if echo:
                print(f"{head}: finished before, skipped", flush=True)
            if after_each is not None:
                after_each(outcomes[-1])
            continue
        resume = (run_dir / "checkpoints" / "last.ckpt").is_file()
        cmd = [python, "-m", ENTRY_MODULES[spec.entry], *spec.overrides, f"paths.run_dir={run_dir}"]
        if resume:
            cmd.append("ckpt_path=last")
        if dry_run:
            outcomes.append(RunOutcome(spec, run_dir, "planned"))
            if echo:
                print(f"{head}: would run{' (resume)' if resume else ''}: {' '.join(cmd[1:])}", flush=True)
            continue
        run_dir.mkdir(parents=True, exist_ok=True)
        if echo:
            print(f"{head}: {'resuming' if resume else 'running'} -> {run_dir}", flush=True)
        t0 = time.perf_counter()
        with open(run_dir / LOG_NAME, "a") as log:
            log.write(f"\n# {time.strftime('%Y-%m-%dT%H:%M:%S')} {' '.join(cmd)}\n")
            log.flush()
            proc = subprocess.run(
                cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}, check=False
            )
        seconds = time.perf_counter() - t0
        ok = proc.returncode == 0 and run_finished(run_dir)
        outcome = RunOutcome(
            spec, run_dir, "done" if ok else "failed", seconds, proc.returncode, "" if ok else _tail(run_dir / LOG_NAME)
        )
        outcomes.append(outcome)
        if echo:
            print(
                f"{head}: {outcome.status} in {seconds / 60:.1f} min"
                + ("" if ok else f" (exit {proc.returncode}; log: {run_dir / LOG_NAME})"),
                flush=True,
            )
        if after_each is not None:
            after_each(outcome)
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
