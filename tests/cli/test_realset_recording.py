"""tofdenoise sensor realset --from-recording: a static recording -> one capture-set scene (input frame, reference =
mean of the other frames' valid depths) that the real-capture reader loads; a moving scene is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tofdenoise.cli.sensor import main
from tofdenoise.data_modules.io import read_png_uint16
from tofdenoise.data_modules.real_captures import build_reference, list_scenes, load_real_scene
from tofdenoise.physics.calibration import resolve_calibration

H, W = 10, 14


def static_frames(t: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    d = np.rint(1200 + 6 * x + 4 * y + rng.normal(0, 3, (t, H, W))).astype(np.uint16)
    d[:, 7:9, 10:13] = 0  # a hole in every frame
    # pixel (0, 0): 1000 in the input frame, then 1001, 1003, invalid, 1010, 1006
    d[:6, 0, 0] = [1000, 1001, 1003, 0, 1010, 1006][:t]
    d[2, 5, 5] = 0  # flickers once
    ir = rng.integers(100, 3000, (t, H, W)).astype(np.uint16)
    return d, ir


def run(*args: str) -> int:
    return main(["realset", *args])


def test_static_bag_becomes_a_scene_with_the_hand_computed_reference(tmp_path, recording_files, capsys):
    d, ir = static_frames()
    bag = recording_files.write_bag(tmp_path / "desk.bag", 1, d, amplitude=ir)
    out = tmp_path / "set"
    assert run("--from-recording", str(bag), "--out", str(out), "--min-count", "4") == 0
    printed = capsys.readouterr().out
    assert f"scene {out / 'desk'}" in printed and f"++data.real_dir={out} ++data.real_min_count=4" in printed
    scene = out / "desk"
    assert np.array_equal(read_png_uint16(scene / "input_depth_mm.png"), d[0])
    assert np.array_equal(read_png_uint16(scene / "input_amplitude.png"), ir[0])
    assert sorted(p.name for p in (scene / "hiexp").iterdir()) == sorted(
        [f"depth_mm_{k:03d}.png" for k in range(5)] + [f"saturated_{k:03d}.png" for k in range(5)]
    )
    reference = np.load(scene / "reference_depth_mm.npy")
    assert reference[0, 0] == pytest.approx((1001 + 1003 + 1010 + 1006) / 4)  # frame 3 invalid there, input left out
    # every pixel: the mean over the valid ones of frames 1..5, NaN with fewer than 4 valid
    refs = d[1:].astype(np.float64)
    count = (refs > 0).sum(axis=0)
    mean = np.where(count >= 4, refs.sum(axis=0) / np.maximum(count, 1), np.nan)
    np.testing.assert_allclose(reference, mean.astype(np.float32), rtol=0, atol=0, equal_nan=True)
    assert np.isnan(reference[7:9, 10:13]).all()
    assert np.array_equal(np.load(scene / "reference_count.npy"), count)
    meta = json.loads((scene / "recording.json").read_text())
    assert meta["input_frame"] == 0 and meta["reference_frames"] == [1, 2, 3, 4, 5] and meta["min_count"] == 4
    assert meta["recording"] == str(bag) and meta["depth_stream"] == "/camera/depth/image_raw"
    # the existing real-capture reader loads it: the scoring mask is input valid and reference valid
    assert list_scenes(out) == [scene]
    assert build_reference(scene, min_count=4).rebuilt is False  # read as written, not rebuilt
    sample = load_real_scene(scene, resolve_calibration(None), min_count=4)
    expected_mask = (d[0] > 0) & np.isfinite(mean)
    assert np.array_equal(sample["mask"] > 0, expected_mask)
    assert np.array_equal(sample["noisy"], d[0].astype(np.float32))
    np.testing.assert_array_equal(sample["clean"][expected_mask], mean[expected_mask].astype(np.float32))


def test_default_reference_is_what_data_real_dir_loads(tmp_path, recording_files, capsys):
    d, ir = static_frames()
    mkv = recording_files.write_kinect_mkv(tmp_path / "wall.mkv", d, ir)
    out = tmp_path / "set"
    assert run("--from-recording", str(mkv), "--out", str(out), "--input-frame", "1") == 0
    scene = out / "wall"
    assert np.array_equal(read_png_uint16(scene / "input_depth_mm.png"), d[1])
    reference = np.load(scene / "reference_depth_mm.npy")
    others = d[[0, 2, 3, 4, 5]].astype(np.float64)
    count = (others > 0).sum(axis=0)
    assert np.array_equal(np.isfinite(reference), count >= 3)  # half of the 5 reference frames, rounded up
    assert reference[0, 0] == pytest.approx((1000 + 1003 + 1010 + 1006) / 4)  # frame 3 invalid there
    np.testing.assert_array_equal(reference[count == 5], others.mean(axis=0)[count == 5].astype(np.float32))
    assert build_reference(scene).rebuilt is False  # the datamodule's default (data.real_min_count: null)
    capsys.readouterr()
    # an existing scene is not replaced without --force; with it, it is
    assert run("--from-recording", str(mkv), "--out", str(out)) == 2
    assert "exists; --force replaces it" in capsys.readouterr().err
    assert run("--from-recording", str(mkv), "--out", str(out), "--force") == 0
    assert np.array_equal(read_png_uint16(scene / "input_depth_mm.png"), d[0])
    assert sorted(p.name for p in out.iterdir()) == ["wall"]  # no temporary or old folder left


def test_a_moving_scene_is_refused_and_nothing_is_written(tmp_path, recording_files, capsys):
    d, ir = static_frames()
    moving = d.copy()
    moving[4, :, 3:9] = 700  # something 0.5 m in front of the wall in frame 4: 6 of 14 columns
    bag = recording_files.write_bag(tmp_path / "walk", 2, moving, amplitude=ir)
    out = tmp_path / "set"
    assert run("--from-recording", str(bag), "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "the scene moved" in err and "frames 4 (" in err and "--motion-tolerance-mm" in err
    assert not out.exists() or list(out.iterdir()) == []
    # a static scene with the camera's noise passes the same check
    still = recording_files.write_bag(tmp_path / "still", 2, d, amplitude=ir)
    assert run("--from-recording", str(still), "--out", str(out)) == 0


def test_bad_recordings_are_errors_that_write_nothing(tmp_path, recording_files, capsys):
    d, ir = static_frames(8)
    no_amp = recording_files.write_bag(tmp_path / "noamp.bag", 1, d)
    out = tmp_path / "set"
    assert run("--from-recording", str(no_amp), "--out", str(out)) == 2
    assert "needs the input's amplitude" in capsys.readouterr().err
    full = recording_files.write_kinect_mkv(tmp_path / "full.mkv", d, ir)
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    assert run("--from-recording", str(cut), "--out", str(out)) == 2
    assert "cut.mkv is truncated" in capsys.readouterr().err
    nodepth = recording_files.write_bag(tmp_path / "nodepth.bag", 1, d, depth_topic="/tof/range", amplitude=ir)
    assert run("--from-recording", str(nodepth), "--out", str(out)) == 2
    assert "/tof/range" in capsys.readouterr().err
    assert run("--from-recording", str(nodepth), "--out", str(out), "--depth-stream", "/tof/range") == 0
    assert run("--from-recording", str(full), "--out", str(out), "--input-frame", "8") == 2
    assert "--input-frame 8 is not a frame (0 .. 7)" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["nodepth"]


def test_two_runs_onto_one_scene_one_publishes_and_the_other_is_refused(tmp_path, recording_files, capsys, monkeypatch):
    """Two runs started together onto one scene name, no --force (issue 41): both passed the "exists" check, both
    exited 0 and the folder held one of them. Here the second run starts and finishes while the first works (after
    its check, before its publish): the first is refused, exit 2, its partial work removed, the other's scene kept."""
    import tofdenoise.inference.recording_realset as rr

    d, ir = static_frames()
    first = recording_files.write_bag(tmp_path / "first.bag", 1, d, amplitude=ir)
    second = recording_files.write_bag(tmp_path / "second.bag", 1, d + 5, amplitude=ir)
    out = tmp_path / "rs7"
    build, started, statuses = rr.build_reference, [], []

    def the_other_run_finishes_meanwhile(*args, **kwargs):
        if not started:  # once: the other run's own work passes straight through
            started.append(True)
            statuses.append(run("--from-recording", str(second), "--out", str(out), "--scene", "desk"))
        return build(*args, **kwargs)

    monkeypatch.setattr(rr, "build_reference", the_other_run_finishes_meanwhile)
    assert run("--from-recording", str(first), "--out", str(out), "--scene", "desk") == 2
    assert statuses == [0]
    err = capsys.readouterr().err
    (line,) = [x for x in err.splitlines() if "error" in x]
    assert f"scene folder {out / 'desk'} exists" in line and "another run wrote it" in line and "--force" in line
    assert json.loads((out / "desk" / "recording.json").read_text())["recording"] == str(second)
    assert np.array_equal(read_png_uint16(out / "desk" / "input_depth_mm.png"), d[0] + 5)
    assert sorted(p.name for p in out.iterdir()) == ["desk"]  # no partial folder left

    # with --force replacing stays allowed, also when another run published meanwhile
    started.clear(), statuses.clear()
    assert run("--from-recording", str(first), "--out", str(out), "--scene", "desk", "--force") == 0
    assert statuses == [2]  # the other run (no --force) found the scene and was refused before its work
    assert json.loads((out / "desk" / "recording.json").read_text())["recording"] == str(first)
    assert sorted(p.name for p in out.iterdir()) == ["desk"]


def test_publish_scene_is_exclusive_without_force(tmp_path):
    """The publish step itself, twice onto one target: the first wins, the second is refused and left to its caller
    (nothing of the winner touched); with force the second replaces the first and no folder is left aside."""
    from tofdenoise.inference.recording_realset import SceneExistsError, publish_scene

    def scene(name: str, text: str):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "recording.json").write_text(text)
        return folder

    target = tmp_path / "desk"
    publish_scene(scene(".a.partial", "a"), target)
    b = scene(".b.partial", "b")
    with pytest.raises(SceneExistsError, match=f"scene folder {target} exists .*another run wrote it.*--force"):
        publish_scene(b, target)
    assert (target / "recording.json").read_text() == "a" and (b / "recording.json").read_text() == "b"
    publish_scene(b, target, force=True)
    assert (target / "recording.json").read_text() == "b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["desk"]
    # a file where the scene goes is never replaced either
    (tmp_path / "notes").write_text("mine")
    with pytest.raises(SceneExistsError):
        publish_scene(scene(".c.partial", "c"), tmp_path / "notes")
    assert (tmp_path / "notes").read_text() == "mine"


def test_ctrl_c_during_the_publish_lets_the_scene_stand(tmp_path, recording_files, capsys, monkeypatch):
    """A Ctrl-C that arrives while the finished scene is renamed into place (issue 41: the success line and exit 130
    together, and a traceback): the rename completes, the scene is whole, the command ends with its success line and
    exit 0. Python's Ctrl-C handler is set here, so the test holds where SIGINT is ignored (``nohup``)."""
    import os
    import signal

    import tofdenoise.inference.recording_realset as rr

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    d, ir = static_frames()
    bag = recording_files.write_bag(tmp_path / "desk.bag", 1, d, amplitude=ir)
    out = tmp_path / "set"
    publish = rr.publish_scene

    def ctrl_c_while_renaming(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return publish(*args, **kwargs)

    monkeypatch.setattr(rr, "publish_scene", ctrl_c_while_renaming)
    try:
        assert run("--from-recording", str(bag), "--out", str(out)) == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    captured = capsys.readouterr()
    assert f"scene {out / 'desk'}" in captured.out and "interrupted" not in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["desk"]
    assert list_scenes(out) == [out / "desk"]


def test_ctrl_c_before_the_publish_writes_nothing(tmp_path, recording_files, capsys, monkeypatch):
    """A Ctrl-C while the scene is written: one line, exit 130, nothing published and no partial folder left."""
    import tofdenoise.inference.recording_realset as rr

    d, ir = static_frames()
    bag = recording_files.write_bag(tmp_path / "desk.bag", 1, d, amplitude=ir)
    out = tmp_path / "set"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rr, "build_reference", interrupted)
    assert run("--from-recording", str(bag), "--out", str(out)) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"tofdenoise sensor realset: interrupted (Ctrl-C); scene {out / 'desk'} not written (nothing "
                   "published)"]  # fmt: skip
    assert list(out.iterdir()) == []


def test_stale_partial_folders_are_removed_and_nothing_else(tmp_path, recording_files, capsys):
    """A partial scene folder that a killed run left (its lock free, only a scene's files) is no scene to the
    readers and is removed by the next run onto that scene, which says so; a partial folder whose lock is held (a
    run still writing), one holding a file of the user's, and another scene's partial folder stay."""
    import fcntl
    import os

    d, ir = static_frames()
    bag = recording_files.write_bag(tmp_path / "desk.bag", 1, d, amplitude=ir)
    out = tmp_path / "set"
    assert run("--from-recording", str(bag), "--out", str(out), "--scene", "wall") == 0

    def partial(name: str, *files: str):
        folder = out / name
        (folder / "hiexp").mkdir(parents=True)
        for f in files:
            (folder / f).write_bytes(b"x")
        return folder

    killed = partial(".desk.k1ll3d00.partial", "input_depth_mm.png", "hiexp/depth_mm_000.png", ".input.png.tmp.png")
    running = partial(".desk.runn1ng0.partial", "input_depth_mm.png")
    users = partial(".desk.n0tes123.partial", "input_depth_mm.png", "notes.txt")
    other = partial(".lamp.k1ll3d00.partial", "input_depth_mm.png")
    assert list_scenes(out) == [out / "wall"]  # hidden folders are no scenes
    fd = os.open(running, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        capsys.readouterr()
        assert run("--from-recording", str(bag), "--out", str(out), "--scene", "desk") == 0
    finally:
        os.close(fd)
    assert f"removed {killed}: the partial scene of an earlier run that was killed" in capsys.readouterr().err
    assert not killed.exists() and running.is_dir() and users.is_dir() and other.is_dir()
    assert list_scenes(out) == [out / "desk", out / "wall"]
