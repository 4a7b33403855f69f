"""One writer per run folder: a lock file in the folder that names its holder.

Two trainings started with the same ``paths.run_dir`` used to both run and exit 0, the second overwriting the
first's checkpoints and records. :class:`RunLock` (``<run_dir>/run.lock``) lets one process write a run folder at a
time; the entry points take it before they touch the folder (``tofdenoise train`` and ``tofdenoise classic``
through a Hydra callback, :class:`HydraRunLock`, before Hydra writes ``.hydra/`` and its log; ``tofdenoise``
(LightningCLI) before any class is instantiated) and release it on exit, exceptions included.

- **Holder.** The lock file is JSON: ``pid``, ``host``, ``started`` (ISO time) and ``command`` (the command line),
  so a refusal can say who writes the folder: one line naming the lock file and its holder
  (:class:`RunLockedError`, a ``RuntimeError``; the commands print it and exit with status 2).
- **Exclusion.** The holder keeps an exclusive ``fcntl.flock`` on the open lock file for as long as it runs. The
  kernel drops it when the process ends in any way (exception, ``SIGKILL``, a crash), so a second writer on the
  same machine can never take a lock that is held; after taking the flock a writer checks that the path still names
  the file it locked (a releasing holder unlinks it), else it tries again.
- **Stale locks.** A lock file left by a process that died without releasing (SIGKILL, power loss) names a pid.
  When that pid is dead on this host the lock is stale: it is taken over with a warning naming the old holder (an
  unreadable lock file whose flock is free is stale too). A holder on another host cannot be checked from here
  and is refused (delete the file once that run is gone).
- **Re-entrant.** The process that holds a folder's lock may take it again (the Hydra callback, then the run
  itself); it is released when the outermost holder releases it. DDP worker processes (``LOCAL_RANK`` or ``RANK``
  set and not 0, started by the rank-0 process that holds the lock; under SLURM the tasks of a multi-task job with
  ``SLURM_PROCID`` not 0, which write to the folder rank 0 holds) do not take it.

Why not ``filelock`` (installed with torch): its ``FileLock`` excludes other processes the same way (``flock``)
but records no holder, so a refusal could not say who holds the folder, and its ``SoftFileLock`` (a plain file)
cannot tell a crashed holder's leftover lock from a live one. Both needs take a few lines on top of ``fcntl``, so
this module uses ``fcntl`` directly rather than wrapping ``filelock`` and re-reading its file. POSIX only.
"""

from __future__ import annotations

import atexit
import fcntl
import importlib
import json
import logging
import os
import shlex
import socket
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["LOCK_NAME", "HydraRunLock", "RunFolderError", "RunLock", "RunLockedError", "is_worker_rank", "release_all"]

log = logging.getLogger("tofdenoise.run_lock")

#: the lock file's name inside a run folder
LOCK_NAME = "run.lock"
#: locks held by this process, by resolved run folder (re-entrant)
_HELD: dict[Path, RunLock] = {}
_ATEXIT = False


class RunLockedError(RuntimeError):
    """The run folder is being written by another process (the message names the lock file and its holder)."""


class RunFolderError(RunLockedError):
    """The run folder cannot be made: a file is in its place, or in the place of a folder above it (the message
    names that file). A ``RunLockedError``, so every command that takes the lock prints it as one line, exit 2."""


def is_worker_rank() -> bool:
    """A DDP process other than rank 0: its launcher (rank 0) holds the run folder's lock. Under SLURM (a run across
    nodes: one task per device, ``srun``) every task is started by SLURM and rank 0 is the task with
    ``SLURM_PROCID`` 0; a job of one task (``SLURM_NTASKS`` 1: a job array task, a plain job) is always rank 0."""
    if any(os.environ.get(k, "0") not in ("", "0") for k in ("LOCAL_RANK", "RANK", "NODE_RANK")):
        return True
    try:
        tasks = int(os.environ.get("SLURM_NTASKS", "1") or 1)
    except ValueError:
        tasks = 1
    return tasks > 1 and os.environ.get("SLURM_PROCID", "0") not in ("", "0")


def _host() -> str:
    return socket.gethostname()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    return True


def _holder_text(holder: dict[str, Any]) -> str:
    return (
        f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('started', '?')} "
        f"({holder.get('command', '?')})"
    )


class RunLock:
    """The lock of ``run_dir`` (module docstring). ``acquire()`` / ``release()``, or use it as a context manager.

    ``command``: what the holder runs, recorded in the lock file (default: this process's command line)."""

    def __init__(self, run_dir: str | os.PathLike[str], command: str | None = None):
        self.run_dir = Path(run_dir).expanduser().resolve()
        self.path = self.run_dir / LOCK_NAME
        self.command = command if command is not None else shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])
        self._fd: int | None = None
        self._depth = 0

    # -------------------------------------------------------------- the lock file
    def _read_holder(self, fd: int) -> dict[str, Any] | None:
        os.lseek(fd, 0, os.SEEK_SET)
        raw = b""
        while chunk := os.read(fd, 65536):
            raw += chunk
        if not raw.strip():
            return None
        try:
            holder = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            return {"command": f"unreadable lock file ({len(raw)} bytes)"}
        return holder if isinstance(holder, dict) else {"command": "unreadable lock file"}

    def _refuse(self, holder: dict[str, Any] | None, why: str) -> RunLockedError:
        who = _holder_text(holder) if holder else "another process"
        return RunLockedError(f"run folder {self.run_dir} is locked by {who}: {why} (lock file {self.path})")

    def _open_locked(self) -> int:
        """An fd of the lock file with the flock held, the path still naming that file."""
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            blocker = next((p for p in (self.run_dir, *self.run_dir.parents) if p.exists() and not p.is_dir()), None)
            what = "is a file" if blocker in (None, self.run_dir) else f"cannot be made: {blocker} is a file"
            raise RunFolderError(f"run folder {self.run_dir} {what}, not a folder; choose another run folder") from None
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._read_holder(fd)
                os.close(fd)
                raise self._refuse(
                    holder, "one writer per run folder; wait for it or choose another run folder"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fd
            os.close(fd)  # the holder released (unlinked) it between our open and flock: try again

    # -------------------------------------------------------------- public
    def acquire(self) -> RunLock:
        """Take the lock (or, in the process holding it already, count one more holder); RunLockedError when
        another live process holds it."""
        held = _HELD.get(self.run_dir)
        if held is not None:
            held._depth += 1
            return held
        fd = self._open_locked()
        try:
            holder = self._read_holder(fd)
            if holder is not None and not (holder.get("pid") == os.getpid() and holder.get("host") == _host()):
                same_host = holder.get("host") == _host()
                pid = holder.get("pid")
                if "host" in holder and not same_host:
                    raise self._refuse(
                        holder,
                        "a holder on another host cannot be checked from here; delete the lock file once "
                        "that run is gone",
                    )
                if isinstance(pid, int) and _pid_alive(pid) and pid != os.getpid():
                    raise self._refuse(
                        holder, "that process is alive; delete the lock file if it is not a tofdenoise run"
                    )
                log.warning("run folder %s: stale lock of %s taken over", self.run_dir, _holder_text(holder))
                print(
                    f"warning: taking over the stale lock {self.path}: {_holder_text(holder)} is no longer running",
                    file=sys.stderr,
                )
            record = {
                "pid": os.getpid(),
                "host": _host(),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "command": self.command,
            }
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)
            os.write(fd, (json.dumps(record) + "\n").encode("utf-8"))
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        self._fd, self._depth = fd, 1
        global _ATEXIT
        if not _ATEXIT:  # an interrupted run (KeyboardInterrupt) leaves no lock behind
            _ATEXIT = atexit.register(release_all) is not None
        _HELD[self.run_dir] = self
        return self

    def release(self) -> None:
        """Drop one hold; the last one removes the lock file and the flock."""
        held = _HELD.get(self.run_dir)
        if held is None:
            return
        held._depth -= 1
        if held._depth > 0:
            return
        del _HELD[self.run_dir]
        fd, held._fd = held._fd, None
        try:
            self.path.unlink(missing_ok=True)
        finally:
            if fd is not None:
                os.close(fd)

    def __enter__(self) -> RunLock:
        if not is_worker_rank():
            self.acquire()
            self._entered = True
        else:
            self._entered = False
        return self

    def __exit__(self, *exc: object) -> None:
        if getattr(self, "_entered", False):
            self.release()


def release_all() -> None:
    """Release every run-folder lock this process holds (an entry point's last step)."""
    for lock in list(_HELD.values()):
        lock._depth = 1
        lock.release()


class HydraRunLock:
    """Hydra callback (``hydra.callbacks.run_lock`` in ``configs/train.yaml``): takes the lock of ``hydra.run.dir``
    before Hydra writes ``.hydra/`` and its log there, releases it at the end of the run. A refusal is one line on
    stderr and exit status 2.

    ``before_job``: the dotted name of a function ``f(config, run_dir)`` called with the lock held, still before
    Hydra writes anything (``config``: the composed config without its ``hydra`` node). A ``ValueError`` it raises
    (a run folder that holds another run: ``tofdenoise.experiments.train_job.check_finished_run``) is a refusal
    too, the lock released: a refused run leaves the folder as it was.

    In a multirun (``-m``) Hydra writes each job's ``.hydra/`` and log before any callback sees the job, so
    ``before_job`` runs for every job of the sweep at its start (:meth:`on_multirun_start`, before Hydra writes the
    sweep's ``multirun.yaml``): each job's config composed as Hydra's launcher composes it, with its folder
    (``hydra.sweep.dir``/``hydra.sweep.subdir``). One refused job refuses the sweep, one line naming it, exit status
    2, nothing written. A sweeper other than Hydra's basic one (Optuna) chooses its jobs as it goes: each of them is
    checked by the run itself."""

    def __init__(self, prog: str = "tofdenoise train", before_job: str | None = None):
        self.prog = prog  # the command named in a refusal
        self.before_job = before_job

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        from omegaconf import OmegaConf

        if is_worker_rank():
            return
        run_dir = OmegaConf.select(config, "hydra.run.dir")
        try:
            lock = RunLock(str(run_dir)).acquire()
        except RunLockedError as exc:
            print(f"{self.prog}: error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        if self.before_job:
            try:
                self._before_job(config, str(run_dir))
            except ValueError as exc:
                lock.release()
                print(f"{self.prog}: error: {exc}", file=sys.stderr)
                raise SystemExit(2) from None
            except BaseException:
                lock.release()
                raise

    def _before_job(self, config: Any, run_dir: str) -> None:
        from omegaconf import open_dict

        module, _, name = self.before_job.rpartition(".")
        task = config.copy()
        with open_dict(task):
            del task["hydra"]
        getattr(importlib.import_module(module), name)(task, run_dir)

    def _sweep_jobs(self, config: Any) -> list[tuple[Any, str]]:
        """(config, folder) of every job of a basic sweep, composed as Hydra's basic launcher composes them; [] for
        another sweeper."""
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.global_hydra import GlobalHydra
        from hydra.core.override_parser.overrides_parser import OverridesParser
        from omegaconf import OmegaConf, open_dict

        if OmegaConf.select(config, "hydra.sweeper._target_") != f"{BasicSweeper.__module__}.BasicSweeper":
            return []
        loader = GlobalHydra.instance().config_loader()
        params = OmegaConf.select(config, "hydra.sweeper.params") or {}
        arguments = [f"{k}={v}" for k, v in params.items()]
        arguments += list(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
        overrides = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
        jobs = []
        for num, job in enumerate(j for batch in BasicSweeper.split_arguments(overrides, None) for j in batch):
            sweep_config = loader.load_sweep_config(config, list(job))
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = num
                sweep_config.hydra.job.num = num
                run_dir = os.path.join(str(sweep_config.hydra.sweep.dir), str(sweep_config.hydra.sweep.subdir))
                sweep_config.paths.run_dir = run_dir  # as the job's entry sets it (config.hydra_console_script)
            jobs.append((sweep_config, run_dir))
        return jobs

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        from hydra.core.hydra_config import HydraConfig

        if not self.before_job or is_worker_rank():
            return
        hydra_config = HydraConfig.instance()
        saved = hydra_config.cfg
        jobs = self._sweep_jobs(config)
        try:
            for sweep_config, run_dir in jobs:
                hydra_config.set_config(sweep_config)  # what ${hydra:...} reads while the job runs
                try:
                    self._before_job(sweep_config, run_dir)
                except ValueError as exc:
                    print(f"{self.prog}: error: multirun job {run_dir}: {exc}", file=sys.stderr)
                    raise SystemExit(2) from None
        finally:
            hydra_config.cfg = saved
        folders: dict[str, int] = {}
        for num, (_, run_dir) in enumerate(jobs):  # two jobs of one folder: the second was refused after the first ran
            first = folders.setdefault(os.path.realpath(run_dir), num)
            if first != num:
                print(
                    f"{self.prog}: error: multirun jobs #{first} and #{num} would both write {run_dir}: give each job "
                    "its own folder (run_name=... naming what the sweep varies, or hydra.sweep.subdir=...)",
                    file=sys.stderr,
                )
                raise SystemExit(2)

    def on_run_end(self, config: Any, **kwargs: Any) -> None:
        release_all()

    # the remaining Hydra callback hooks (hydra.experimental.callback.Callback) do nothing
    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        pass

    def on_job_start(self, config: Any, **kwargs: Any) -> None:
        pass

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        pass

    def on_compute_sweep_start(self, config: Any, **kwargs: Any) -> None:
        pass
