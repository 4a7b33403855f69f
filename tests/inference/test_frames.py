"""Frame discovery, reading (PNG16 / npy / EXR, validity, units) and amplitude pairing, with errors naming files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tofdenoise.inference.frames import (
    AmplitudeSource,
    FrameError,
    FrameInput,
    drop_amplitude_files,
    find_frames,
    load_frame,
    read_depth_frame,
)


def depth_with_holes(h: int = 24, w: int = 32) -> np.ndarray:
    d = np.linspace(500, 1500, h * w, dtype=np.float32).reshape(h, w).round()
    d[3:7, 5:9] = 0
    return d


def test_png16_npy_and_exr_read_the_same_frame(tmp_path, write_exr):
    d = depth_with_holes()
    cv2.imwrite(str(tmp_path / "a.png"), d.astype(np.uint16))
    f = d.copy()
    f[3:7, 5:9] = np.nan
    f[0, 0] = -4.0
    np.save(tmp_path / "b.npy", f)
    write_exr(tmp_path / "c.exr", f)
    expected_valid = d > 0
    expected_valid[0, 0] = False
    for name in ("a.png", "b.npy", "c.exr"):
        depth, valid = read_depth_frame(tmp_path / name)
        assert depth.dtype == np.float32 and depth.shape == d.shape
        want = expected_valid if name != "a.png" else d > 0
        np.testing.assert_array_equal(valid, want, err_msg=name)
        np.testing.assert_array_equal(depth[want], d[want])
        assert np.all(depth[~want] == 0)
    depth, _ = read_depth_frame(tmp_path / "a.png", depth_scale_mm=0.25)
    np.testing.assert_allclose(depth[d > 0], 0.25 * d[d > 0])


def test_bad_depth_files_are_named(tmp_path):
    cv2.imwrite(str(tmp_path / "eight.png"), np.full((8, 8), 7, np.uint8))
    cv2.imwrite(str(tmp_path / "colour.png"), np.full((8, 8, 3), 700, np.uint16))
    (tmp_path / "broken.png").write_bytes(b"\x89PNG not really")
    np.save(tmp_path / "cube.npy", np.ones((2, 3, 4), np.float32))
    (tmp_path / "text.npy").write_text("hello")
    np.save(tmp_path / "eight.npy", np.full((8, 8), 88, np.uint8))  # was read as 88 mm
    np.save(tmp_path / "signed.npy", np.full((8, 8), 88, np.int8))
    cases = {
        "eight.png": "8-bit",
        "eight.npy": "dtype uint8; 8-bit values cannot hold depth in millimetres",
        "signed.npy": "dtype int8; 8-bit values cannot hold depth in millimetres",
        "colour.png": "3 channels",
        "broken.png": "could not be decoded",
        "cube.npy": "2-D",
        "text.npy": "could not be read",
    }
    for name, message in cases.items():
        with pytest.raises(FrameError, match=message) as info:
            read_depth_frame(tmp_path / name)
        assert name in str(info.value)


def test_find_frames_recursive_mirrored_and_excluding_outputs(tmp_path):
    (tmp_path / "in" / "sub").mkdir(parents=True)
    (tmp_path / "in" / "out").mkdir()
    for rel in ("x.png", "sub/y.npy", "out/old.png", ".hidden.png", "notes.txt"):
        (tmp_path / "in" / rel).write_bytes(b"")
    frames = find_frames([tmp_path / "in"], exclude=[tmp_path / "in" / "out"])
    assert [f.rel.as_posix() for f in frames] == ["sub/y.npy", "x.png"]
    single = find_frames([tmp_path / "in" / "sub" / "y.npy"])
    assert single[0].rel == Path("y.npy") and single[0].rel_stem == Path("y")
    with pytest.raises(FrameError, match="not found"):
        find_frames([tmp_path / "missing"])
    with pytest.raises(FrameError, match="notes.txt"):
        find_frames([tmp_path / "in" / "notes.txt"])


def test_amplitude_pairing_folder_template_glob_and_errors(tmp_path):
    d = depth_with_holes()
    (tmp_path / "depth" / "sub").mkdir(parents=True)
    (tmp_path / "amp" / "sub").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "depth" / "sub" / "f1.png"), d.astype(np.uint16))
    amp = np.arange(d.size, dtype=np.float32).reshape(d.shape)
    np.save(tmp_path / "amp" / "sub" / "f1.npy", amp)
    np.save(tmp_path / "amp" / "f1_amp.npy", amp * 2)
    frame = find_frames([tmp_path / "depth"])[0]
    loaded = load_frame(frame, amplitude=AmplitudeSource(tmp_path / "amp"))
    np.testing.assert_array_equal(loaded.amplitude, amp)
    assert loaded.name == "sub/f1"
    templ = load_frame(frame, amplitude=AmplitudeSource(str(tmp_path / "amp" / "{stem}_amp.npy")))
    np.testing.assert_array_equal(templ.amplitude, amp * 2)
    globbed = load_frame(frame, amplitude=AmplitudeSource(str(tmp_path / "amp" / "sub" / "*.npy")))
    np.testing.assert_array_equal(globbed.amplitude, amp)
    # another shape: both files named
    np.save(tmp_path / "amp" / "sub" / "f1.npy", amp[:-1])
    with pytest.raises(FrameError, match="shape") as info:
        load_frame(frame, amplitude=AmplitudeSource(tmp_path / "amp"))
    assert "f1.npy" in str(info.value) and "f1.png" in str(info.value)
    # missing amplitude
    other = FrameInput(tmp_path / "depth" / "sub" / "f2.png", Path("sub/f2.png"))
    cv2.imwrite(str(other.path), d.astype(np.uint16))
    with pytest.raises(FrameError, match="no amplitude file for depth frame .*f2.png"):
        load_frame(other, amplitude=AmplitudeSource(tmp_path / "amp"))
    with pytest.raises(FrameError, match="matches no amplitude"):
        AmplitudeSource(str(tmp_path / "nothing" / "*.png"))


@pytest.mark.parametrize("sensor", ["default", "cam75"])
def test_the_built_in_sensors_simulated_frames_pass_the_units_check(tmp_path, sensor):
    """Genuine frames in mm: every simulated scene's input depth of both built-in cameras (their own unambiguous
    range: 2998 mm for default, 1999 mm for cam75) lies in the plausible range, and so does a x10 / 10 copy not."""
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set
    from tofdenoise.data_modules.real_captures import INPUT_DEPTH
    from tofdenoise.inference.frames import check_depth_units_mm, plausible_depth_range_mm
    from tofdenoise.physics.calibration import resolve_calibration

    calib = resolve_calibration(sensor)
    simulate_capture_set(tmp_path / "set", scenes=3, frames=1, height=24, width=32, seed=1, calib=calib)
    scenes = sorted(p for p in (tmp_path / "set").iterdir() if p.is_dir())
    assert len(scenes) == 3
    near, far = plausible_depth_range_mm(calib)
    assert (near, far) == (300.0, pytest.approx(calib.unambiguous_range_mm))
    for scene in scenes:
        frame = load_frame(FrameInput(scene / INPUT_DEPTH, Path(INPUT_DEPTH)))
        check_depth_units_mm(frame, scene / INPUT_DEPTH, (near, far))
        for factor, unit in ((10.0, "0.1 mm units: pass --depth-scale-mm 0.1"), (0.1, "centimetres")):
            scaled = frame.__class__(depth_mm=frame.depth_mm * factor, valid=frame.valid)
            with pytest.raises(FrameError, match=unit):
                check_depth_units_mm(scaled, scene / INPUT_DEPTH, (near, far))


def test_the_units_check_names_the_median_and_the_likely_unit(tmp_path):
    from tofdenoise.inference.frames import Frame, check_depth_units_mm

    valid = np.ones((4, 4), bool)
    cases = {19580.0: ("beyond 2998 mm", "0.1 mm units: pass --depth-scale-mm 0.1"),
             150.0: ("nearer than 300 mm", "centimetres: pass --depth-scale-mm 10"),
             1.5: ("nearer than 300 mm", "metres: pass --depth-scale-mm 1000"),
             90000.0: ("beyond 2998 mm", "give the file's units with --depth-scale-mm")}  # fmt: skip
    for median, (side, hint) in cases.items():
        frame = Frame(depth_mm=np.full((4, 4), median, np.float32), valid=valid)
        with pytest.raises(FrameError) as err:
            check_depth_units_mm(frame, tmp_path / "f.png")
        text = str(err.value)
        assert str(tmp_path / "f.png") in text and f"median valid depth {median:.4g}" in text
        assert side in text and hint in text
    # mostly: a frame with fewer than half of its valid depths beyond the range is taken as mm
    d = np.full((4, 4), 1500.0, np.float32)
    d.flat[:7] = 19580.0
    check_depth_units_mm(Frame(depth_mm=d, valid=valid), tmp_path / "f.png")


def test_a_stem_substitution_pairs_the_adi_sdks_depth_and_ab_files(tmp_path):
    """The ADI ADTF3175D SDK writes frame_mode2_depth_NNNNNN / frame_mode2_ab_NNNNNN into one folder:
    ``{stem:depth=ab}`` pairs them, and the ab files are not taken as depth frames."""
    d = depth_with_holes()
    adi = tmp_path / "adi"
    adi.mkdir()
    amps = {}
    for i in (123, 124):
        np.save(adi / f"frame_mode2_depth_{i:06d}.npy", d)
        amps[i] = np.full(d.shape, float(i), np.float32)
        np.save(adi / f"frame_mode2_ab_{i:06d}.npy", amps[i])
    np.save(adi / "frame_mode2_depth_000125.npy", d)  # no ab file
    source = AmplitudeSource(str(adi / "{stem:depth=ab}.npy"))
    frames = drop_amplitude_files(find_frames([adi]), source)
    assert [f.path.name for f in frames] == [
        "frame_mode2_depth_000123.npy",
        "frame_mode2_depth_000124.npy",
        "frame_mode2_depth_000125.npy",
    ]
    for frame, i in zip(frames[:2], (123, 124)):
        np.testing.assert_array_equal(load_frame(frame, amplitude=source).amplitude, amps[i])
    with pytest.raises(FrameError) as info:
        load_frame(frames[2], amplitude=source)
    message = str(info.value)
    assert "frame_mode2_depth_000125.npy" in message and str(adi / "frame_mode2_ab_000125.npy") in message
    assert "\n" not in message
    # the plain {stem} template still works, and a substitution may remove text
    np.save(adi / "frame_mode2_depth_000123_amp.npy", amps[123] * 2)
    np.testing.assert_array_equal(
        load_frame(frames[0], amplitude=AmplitudeSource(str(adi / "{stem}_amp.npy"))).amplitude, amps[123] * 2
    )
    np.save(adi / "frame_mode2_000123.npy", amps[123] * 3)
    np.testing.assert_array_equal(
        load_frame(frames[0], amplitude=AmplitudeSource(str(adi / "{stem:_depth=}.npy"))).amplitude, amps[123] * 3
    )


def test_a_stem_substitution_is_unambiguous_or_refused(tmp_path):
    d = depth_with_holes()
    np.save(tmp_path / "depth_depth_1.npy", d)
    frame = find_frames([tmp_path / "depth_depth_1.npy"])[0]
    with pytest.raises(FrameError, match=r"needs 'depth' once in the stem 'depth_depth_1', found 2"):
        AmplitudeSource(str(tmp_path / "{stem:depth=ab}.npy")).find(frame)
    with pytest.raises(FrameError, match=r"needs 'zz' once .* found 0"):
        AmplitudeSource(str(tmp_path / "{stem:zz=ab}.npy")).find(frame)
    for bad in ("{stem:depth}.npy", "{stem:=ab}.npy", "{stem:a=b=c}.npy", "{stems}.npy"):
        with pytest.raises(FrameError, match=r"\{stem\} or \{stem:OLD=NEW\}"):
            AmplitudeSource(str(tmp_path / bad))
    with pytest.raises(FrameError, match="itself as its amplitude"):
        AmplitudeSource(str(tmp_path / "{stem}.npy")).find(frame)
