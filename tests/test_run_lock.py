"""tofdenoise.run_lock: one writer per run folder, the holder named, stale locks of dead processes taken over."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tofdenoise.run_lock import LOCK_NAME, RunLock, RunLockedError

HOLD = (
    "import sys; from tofdenoise.run_lock import RunLock; RunLock(sys.argv[1], command='holder test').acquire(); "
    "print('ready', flush=True); sys.stdin.read()"
)


class Holder:
    """Another process that holds the lock of ``run_dir`` until ``release()`` (or until it dies)."""

    def __init__(self, run_dir: Path):
        self.proc = subprocess.Popen(
            [sys.executable, "-c", HOLD, str(run_dir)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert self.proc.stdout.readline().strip() == "ready"

    def release(self) -> None:
        self.proc.stdin.close()
        assert self.proc.wait(timeout=30) == 0

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait(timeout=30)


@pytest.fixture
def holder(tmp_path):
    h = Holder(tmp_path / "run")
    yield h
    if h.proc.poll() is None:
        h.kill()


def test_a_second_writer_is_refused_naming_the_lock_and_its_holder(tmp_path, holder):
    run_dir = tmp_path / "run"
    before = (run_dir / LOCK_NAME).read_bytes()
    with pytest.raises(RunLockedError) as info:
        RunLock(run_dir).acquire()
    msg = str(info.value)
    assert str(run_dir / LOCK_NAME) in msg and f"pid {holder.proc.pid} on {socket.gethostname()}" in msg
    assert "holder test" in msg and "\n" not in msg
    assert (run_dir / LOCK_NAME).read_bytes() == before  # the holder's record is untouched
    holder.release()
    assert not (run_dir / LOCK_NAME).exists()  # released on exit
    with RunLock(run_dir) as lock:  # free again
        assert json.loads(lock.path.read_text())["pid"] == os.getpid()
    assert not (run_dir / LOCK_NAME).exists()


def test_a_lock_left_by_a_dead_process_is_taken_over_with_a_warning(tmp_path, holder, capsys):
    run_dir = tmp_path / "run"
    dead = holder.proc.pid
    holder.kill()  # SIGKILL: no clean-up, the lock file stays
    assert json.loads((run_dir / LOCK_NAME).read_text())["pid"] == dead
    with RunLock(run_dir, command="taker") as lock:
        record = json.loads(lock.path.read_text())
        assert record["pid"] == os.getpid() and record["command"] == "taker" and record["host"] == socket.gethostname()
        assert record["started"]
    err = capsys.readouterr().err
    assert "taking over the stale lock" in err and f"pid {dead}" in err


def test_released_on_an_exception_and_re_entrant_in_the_holding_process(tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(ZeroDivisionError):
        with RunLock(run_dir):
            with RunLock(run_dir):  # the same process again (Hydra's callback, then the run)
                pass
            assert (run_dir / LOCK_NAME).exists()  # still held by the outer one
            raise ZeroDivisionError
    assert not (run_dir / LOCK_NAME).exists()


def test_a_holder_on_another_host_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    record = {"pid": 1, "host": "elsewhere.example", "started": "2026-11-25T10:00:00+0000", "command": "train"}
    (run_dir / LOCK_NAME).write_text(json.dumps(record))
    with pytest.raises(RunLockedError, match="pid 1 on elsewhere.example .* another host"):
        RunLock(run_dir).acquire()


def test_slurm_tasks_other_than_0_of_a_multi_task_job_are_worker_ranks(monkeypatch):
    """A run across nodes (srun, one task per device): task 0 takes the run folder's lock, the others write into
    it as its workers; a one-task job (an array task) always takes it."""
    from tofdenoise.run_lock import is_worker_rank

    for key in ("LOCAL_RANK", "RANK", "NODE_RANK", "SLURM_NTASKS", "SLURM_PROCID"):
        monkeypatch.delenv(key, raising=False)
    assert not is_worker_rank()
    monkeypatch.setenv("SLURM_NTASKS", "8")
    monkeypatch.setenv("SLURM_PROCID", "3")
    assert is_worker_rank()
    monkeypatch.setenv("SLURM_PROCID", "0")
    assert not is_worker_rank()
    monkeypatch.setenv("SLURM_NTASKS", "1")  # a job array task or a plain job: SLURM_PROCID 0 anyway
    monkeypatch.setenv("SLURM_PROCID", "0")
    assert not is_worker_rank()
