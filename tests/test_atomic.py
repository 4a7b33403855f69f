"""The shared atomic writer: complete files only, old file kept on failure, normal permissions, no temp left."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from tofdenoise.atomic import atomic_write, atomic_write_bytes, atomic_write_text


def test_text_and_bytes_round_trip(tmp_path):
    p = atomic_write_text(tmp_path / "sub" / "a.json", '{"x": 1}')
    assert p.read_text() == '{"x": 1}'
    atomic_write_bytes(p, b"xyz")
    assert p.read_bytes() == b"xyz"
    assert [f.name for f in p.parent.iterdir()] == ["a.json"]


def test_failure_keeps_old_file_and_leaves_no_temp(tmp_path):
    p = tmp_path / "keep.txt"
    atomic_write_text(p, "old")

    def broken(tmp):
        tmp.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(p, broken)
    assert p.read_text() == "old"
    assert [f.name for f in tmp_path.iterdir()] == ["keep.txt"]


def test_permissions_follow_umask_not_mkstemp(tmp_path):
    old = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "perm.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644


def test_extension_preserved_for_format_choosing_writers(tmp_path):
    arr = np.arange(6, dtype=np.float32).reshape(2, 3)
    p = atomic_write(tmp_path / "a.npy", lambda tmp: np.save(tmp, arr))
    np.testing.assert_array_equal(np.load(p), arr)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.npy"]


def test_writer_that_writes_nothing_is_an_error(tmp_path):
    def nothing(tmp):
        tmp.unlink()

    with pytest.raises(OSError, match="no file"):
        atomic_write(tmp_path / "x.bin", nothing)
    assert not (tmp_path / "x.bin").exists()


def test_failed_rename_keeps_old_file(tmp_path, monkeypatch):
    p = atomic_write_text(tmp_path / "a.txt", "old")

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(p, "new")
    assert p.read_text() == "old"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.txt"]


def _interrupt_self() -> None:
    """Send SIGINT to this process and give Python a moment to run the handler."""
    import os
    import signal
    import time

    os.kill(os.getpid(), signal.SIGINT)
    for _ in range(100):
        time.sleep(0.001)


@pytest.fixture
def default_sigint():
    """Python's own Ctrl-C handler for the test, whatever the suite was started with (``nohup make test &`` starts
    it with SIGINT ignored, and Python then installs no handler), restored afterwards."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_sigint_deferred_finishes_the_block_then_interrupts(default_sigint):
    import signal

    from tofdenoise.atomic import sigint_deferred

    steps = []
    with pytest.raises(KeyboardInterrupt):
        with sigint_deferred():
            _interrupt_self()
            steps.append("after the first")
            _interrupt_self()  # two signals: one KeyboardInterrupt
            steps.append("after the second")
    assert steps == ["after the first", "after the second"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with sigint_deferred():  # nothing received: nothing raised
        steps.append("quiet")
    assert steps[-1] == "quiet"
    # outside the block Ctrl-C interrupts at once
    with pytest.raises(KeyboardInterrupt):
        _interrupt_self()
        steps.append("never")
    assert steps[-1] == "quiet"


def test_sigint_deferred_lets_the_blocks_own_error_through_and_runs_off_the_main_thread(default_sigint):
    import threading

    from tofdenoise.atomic import sigint_deferred

    with pytest.raises(ValueError, match="disk"):
        with sigint_deferred():
            _interrupt_self()
            raise ValueError("disk")
    ran = []

    def worker():
        with sigint_deferred():  # signal handlers can only be set on the main thread: the block just runs
            ran.append(True)

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert ran == [True]


def test_atomic_group_is_all_or_nothing(tmp_path):
    """A group whose second write fails leaves neither file: the first keeps its old content (it was written into a
    temporary file, never renamed) and no temporary file stays; a group that succeeds renames all of them."""
    from tofdenoise.atomic import WriteError, atomic_group

    (tmp_path / "f.png").write_text("old")

    def fail(tmp):
        raise OSError(28, "No space left on device")

    with pytest.raises(WriteError, match="f.npy: No space left on device"):
        with atomic_group():
            atomic_write_text(tmp_path / "f.png", "new")
            assert (tmp_path / "f.png").read_text() == "old"  # not renamed until the group ends
            atomic_write(tmp_path / "f.npy", fail)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png"]
    assert (tmp_path / "f.png").read_text() == "old"
    with atomic_group():
        atomic_write_text(tmp_path / "f.png", "new")
        atomic_write_text(tmp_path / "f.npy", "array")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.npy", "f.png"]
    assert (tmp_path / "f.png").read_text() == "new"
