"""The probe rows that need a separate process (``runner="signal"`` in probes.py): Ctrl-C and SIGKILL of a long
``tofdenoise denoise``, two of them writing one output folder. Run through ``.venv/bin/tofdenoise denoise``."""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("_reliability_probes", Path(__file__).with_name("probes.py"))
probes = sys.modules.get(_spec.name) or importlib.util.module_from_spec(_spec)
if _spec.name not in sys.modules:
    sys.modules[_spec.name] = probes
    _spec.loader.exec_module(probes)

FRAMES = 300


def _command(verb: str) -> list[str]:
    """``tofdenoise <verb>`` as a user runs it: the console script next to this interpreter (else on PATH)."""
    path = Path(sys.executable).parent / "tofdenoise"
    return [str(path) if path.exists() else shutil.which("tofdenoise") or "tofdenoise", verb]


def _many_frames(world) -> Path:
    """FRAMES copies of the world's 16-bit frame: a command that runs for a while."""
    folder = world / "many"
    folder.mkdir()
    data = (world / "frames/a.png").read_bytes()
    for i in range(FRAMES):
        (folder / f"f{i:03d}.png").write_bytes(data)
    return folder


def _default_sigint() -> None:
    """In the child, before it starts: SIGINT at its default disposition, so that Python installs its Ctrl-C handler
    even when this suite runs where SIGINT is ignored (``nohup make test &``, a background job of a non-interactive
    shell: children inherit the ignored disposition)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(world, frames: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [*_command("denoise"), str(frames), "--ckpt", str(world / "model.ckpt"), "--out", str(out),
         "--device", "cpu", "--quiet"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint,
    )  # fmt: skip


def _wait_for_outputs(proc: subprocess.Popen, out: Path, count: int, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if out.is_dir() and len(list(out.glob("*.png"))) >= count:
            return
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no {count} outputs in {out} (exit {proc.poll()}): {proc.communicate()[1][-2000:]}")


def _complete_outputs(out: Path, expected: np.ndarray | None = None) -> list[Path]:
    """Every visible output decodes as a whole 16-bit frame of the input's size (equal to ``expected`` if given)."""
    files = sorted(out.glob("*.png"))
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.dtype == np.uint16 and img.shape == (36, 48), f
        if expected is not None:
            np.testing.assert_array_equal(img, expected)
    return files


def _row(case: str):
    (row,) = [p for p in probes.PROBES if p.command == "tofdenoise denoise" and p.case == case]
    return row


def test_ctrl_c_over_many_frames(world):
    """SIGINT mid-way: exit 130, the summary names how far it got, no traceback, every written frame complete,
    the inputs unchanged."""
    row = _row("sigint-over-many-frames")
    frames = _many_frames(world)
    before = world.snapshot()
    out = world / "out/d"
    proc = _start(world, frames, out)
    _wait_for_outputs(proc, out, 3)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == row.status, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    summary = [line for line in err.splitlines() if "interrupted (Ctrl-C) after" in line]
    assert len(summary) == 1 and f"of {FRAMES} frame(s)" in summary[0], err[-2000:]
    done = _complete_outputs(out)
    assert 3 <= len(done) < FRAMES
    assert f"{len(done)} frame(s) done" in summary[0]
    after = world.snapshot()
    assert {k: v for k, v in after.items() if not k.startswith("out/")} == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"


@pytest.mark.slow
def test_sigkill_over_many_frames_leaves_only_complete_frames(world):
    """SIGKILL cannot be handled: what is left are complete frames (atomic renames) and at most the one temporary
    file being written at that moment, never a partial frame under an output's name; a second run redoes it all."""
    frames = _many_frames(world)
    out = world / "out/d"
    proc = _start(world, frames, out)
    _wait_for_outputs(proc, out, 3)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == _row("sigkill-over-many-frames").status
    done = _complete_outputs(out)
    assert 3 <= len(done) < FRAMES
    assert len([p for p in out.iterdir() if p.name.startswith(".")]) <= 1


@pytest.mark.slow
def test_two_writers_of_one_output_folder_leave_complete_identical_frames(world):
    """Two tofdenoise denoise processes on the same --out (no lock: writes are atomic renames): both exit 0 and
    every frame is complete and equal to the frame a single run writes."""
    frames = world / "many"
    frames.mkdir()
    for i in range(40):
        shutil.copy(world / "frames/a.png", frames / f"f{i:03d}.png")
    single = world / "out/single"
    ref = _start(world, frames, single)
    assert ref.wait(timeout=300) == 0, ref.communicate()[1][-2000:]
    expected = cv2.imread(str(single / "f000.png"), cv2.IMREAD_UNCHANGED)
    out = world / "out/d"
    a, b = _start(world, frames, out), _start(world, frames, out)
    assert a.wait(timeout=300) == 0 and b.wait(timeout=300) == _row("two-writers-one-out").status
    assert len(_complete_outputs(out, expected)) == 40
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("sig", "status", "said"),
    [(signal.SIGINT, None, "interrupted (Ctrl-C)"), (signal.SIGTERM, 143, "stopped by SIGTERM")],
)
def test_ctrl_c_mid_training_is_one_line_and_leaves_a_resumable_unfinished_run(world, tmp_path, sig, status, said):
    """SIGINT during tofdenoise train: Lightning shuts down; the run is not tested and writes no metrics.json (it
    never passes for a finished run), last.ckpt is whole, the lock is released, and one line says how to resume.
    SIGTERM (a scheduler's preemption) the same, said as such, exit status 143 (it read "Ctrl-C", 130).
    SIGKILL and the resume: tests/cli/test_train.py::test_resume_after_sigkill_reaches_the_same_number_of_steps and
    tests/training/test_mid_epoch_resume.py."""
    import json

    import torch

    row = [p for p in probes.PROBES if p.command == "tofdenoise train" and p.family == "signals"][0]
    run_dir = world / "out/run"
    args = probes.train_args(world, "trainer.max_epochs=500", "callbacks.model_checkpoint.every_n_train_steps=2")
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "WANDB_MODE": "offline"}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.Popen(
        [*_command("train"), *map(str, args)], env=env, cwd=tmp_path, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint,
    )  # fmt: skip
    last = run_dir / "checkpoints" / "last.ckpt"
    deadline = time.time() + 300
    while not last.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()[1][-3000:]
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == (row.status if status is None else status), err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    (line,) = [x for x in err.splitlines() if x.startswith(f"tofdenoise train: {said} at step")]
    assert "ckpt_path=last" in line and str(last) in line
    assert not (run_dir / "metrics.json").exists()
    assert not json.loads((run_dir / "run_info.json").read_text()).get("finished")
    assert torch.load(last, weights_only=True)["global_step"] > 0
    assert not (run_dir / "run.lock").exists()  # released on the way out


# ------------------------------------------------------------------------- tofdenoise sensor realset --from-recording

#: frames of the long recording (60 x 80): writing its scene takes a second or more
REALSET_FRAMES = 120


def _realset_row(case: str):
    (row,) = [p for p in probes.PROBES if p.command == "tofdenoise sensor realset" and p.case == case]
    return row


def _start_realset(world, recording: Path, out: Path, scene: str = "desk") -> subprocess.Popen:
    return subprocess.Popen(
        [*_command("sensor"), "realset", "--from-recording", str(recording), "--out", str(out), "--scene", scene],
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_default_sigint,
    )  # fmt: skip


def _wait_for_partial(proc: subprocess.Popen, out: Path, scene: str = "desk", files: int = 6) -> Path:
    """The run's partial scene folder once it holds ``files`` reference frames."""
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        for folder in out.glob(f".{scene}.*.partial") if out.is_dir() else ():
            if len(list(folder.glob("hiexp/*.png"))) >= files:
                return folder
        time.sleep(0.005)
    proc.kill()
    raise AssertionError(f"no partial scene in {out} (exit {proc.poll()}): {proc.communicate()[1][-2000:]}")


def test_ctrl_c_while_realset_writes_a_scene(world):
    """SIGINT while the scene is being written: one line, exit 130, no traceback, nothing published, no partial
    folder left, the recording unchanged."""
    row = _realset_row("sigint-while-writing-a-scene")
    rec = probes.static_recording(world, "rec/long.bag", frames=REALSET_FRAMES, h=60, w_px=80)
    before = world.snapshot()
    out = world / "out/rs"
    proc = _start_realset(world, rec, out)
    _wait_for_partial(proc, out)
    proc.send_signal(signal.SIGINT)
    stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == row.status, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "interrupted (Ctrl-C)" in lines[0] and str(out / "desk") in lines[0], err
    assert "nothing published" in lines[0]
    assert not stdout.strip(), stdout  # no success line
    assert sorted(p.name for p in out.iterdir()) == [], "a scene or a partial folder was left"
    assert world.snapshot() == before


@pytest.mark.slow
def test_sigkill_while_realset_writes_a_scene_then_a_rerun_cleans_up(world):
    """SIGKILL leaves the run's partial folder; capture-set readers skip it (hidden), and the next run onto the
    scene removes it (its lock is free, it holds only a scene's files) and publishes. Another run's partial (its lock
    held) and a hidden folder of the user's with a partial's name are left as they are."""
    import fcntl
    import warnings

    from tofdenoise.data_modules.real_captures import list_scenes

    rec = probes.static_recording(world, "rec/long.bag", frames=REALSET_FRAMES, h=60, w_px=80)
    out = world / "out/rs"
    short = probes.static_recording(world, "rec/wall.bag")
    first = _start_realset(world, short, out, scene="wall")
    assert first.wait(timeout=120) == 0, first.communicate()[1][-2000:]
    proc = _start_realset(world, rec, out)
    killed = _wait_for_partial(proc, out)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == _realset_row("sigkill-while-writing-a-scene-then-rerun").status
    assert killed.is_dir() and (killed / "input_depth_mm.png").is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even "a scene folder without an input frame"
        assert list_scenes(out) == [out / "wall"]  # the partial folder is no scene
    # a partial of a run that is still writing (its lock held here) and a folder of the user's with such a name
    running = out / ".desk.abcd1234.partial"
    running.mkdir()
    (running / "input_depth_mm.png").write_bytes(b"x")
    users = out / ".desk.notes123.partial"
    users.mkdir()
    (users / "notes.txt").write_text("mine\n")
    fd = os.open(running, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        rerun = _start_realset(world, rec, out)
        stdout, err = rerun.communicate(timeout=300)
    finally:
        os.close(fd)
    assert rerun.returncode == 0, err[-3000:]
    assert f"removed {killed}" in err and "Traceback" not in err
    assert not killed.exists() and running.is_dir() and (users / "notes.txt").read_text() == "mine\n"
    assert sorted(p.name for p in out.iterdir()) == sorted([".desk.abcd1234.partial", ".desk.notes123.partial",
                                                             "desk", "wall"])  # fmt: skip
    assert list_scenes(out) == [out / "desk", out / "wall"]
