"""Capture sets: reference building (saturated / invalid frames excluded), caching, the `real` test loader."""

from __future__ import annotations

import json
import os
import time
import warnings

import cv2
import numpy as np
import pytest
import torch

from tofdenoise.data_modules.real_captures import (
    REFERENCE_COUNT,
    REFERENCE_DEPTH,
    REFERENCE_META,
    accumulate_reference,
    build_reference,
    load_real_scene,
)

H, W = 6, 8


def write_scene(scene, frames, saturated, input_depth=None, amplitude=None):
    (scene / "hiexp").mkdir(parents=True, exist_ok=True)
    for k, (depth, sat) in enumerate(zip(frames, saturated)):
        cv2.imwrite(str(scene / "hiexp" / f"depth_mm_{k:03d}.png"), depth.astype(np.uint16))
        cv2.imwrite(str(scene / "hiexp" / f"saturated_{k:03d}.png"), (sat * 255).astype(np.uint8))
    if input_depth is not None:
        cv2.imwrite(str(scene / "input_depth_mm.png"), input_depth.astype(np.uint16))
        cv2.imwrite(str(scene / "input_amplitude.png"), amplitude.astype(np.uint16))


def hand_frames():
    frames = [np.full((H, W), v, np.float64) for v in (1000, 1002, 1004, 1006)]
    sat = [np.zeros((H, W), bool) for _ in frames]
    frames[0][0, 0] = 3000  # saturated and biased: must be excluded
    sat[0][0, 0] = True
    frames[1][0, 0] = 0  # invalid frame at this pixel
    frames[2][1, 1] = frames[3][1, 1] = 0  # pixel (1,1): only 2 valid frames
    frames[1][2, 2] = 0
    frames[2][2, 2] = 0
    frames[3][2, 2] = 0  # pixel (2,2): 1 valid frame
    return frames, sat


def test_reference_excludes_saturated_and_invalid_frames(tmp_path):
    frames, sat = hand_frames()
    write_scene(tmp_path, frames, sat)
    ref = build_reference(tmp_path, min_count=2)
    assert ref.rebuilt
    assert ref.depth_mm.dtype == np.float32 and ref.count.dtype == np.uint16
    assert ref.depth_mm[0, 0] == pytest.approx((1004 + 1006) / 2)  # frames 2, 3 only
    assert ref.count[0, 0] == 2
    assert ref.depth_mm[1, 1] == pytest.approx(1001.0) and ref.count[1, 1] == 2
    assert np.isnan(ref.depth_mm[2, 2]) and ref.count[2, 2] == 1  # too few frames -> invalid
    assert ref.depth_mm[5, 7] == pytest.approx(1003.0) and ref.count[5, 7] == 4
    np.testing.assert_array_equal(np.load(tmp_path / REFERENCE_DEPTH), ref.depth_mm)
    np.testing.assert_array_equal(np.load(tmp_path / REFERENCE_COUNT), ref.count)
    mean, count = accumulate_reference(list(zip(frames, sat)), 3)
    assert np.isnan(mean[0, 0]) and np.isnan(mean[1, 1]) and mean[5, 7] == pytest.approx(1003.0)
    # default min_count = half the frames (2 of 4): pixel (1,1) with 2 frames stays valid
    assert build_reference(tmp_path).depth_mm[1, 1] == pytest.approx(1001.0)


def test_reference_cache_and_rebuild_when_inputs_newer(tmp_path):
    frames, sat = hand_frames()
    write_scene(tmp_path, frames, sat)
    build_reference(tmp_path)
    assert not build_reference(tmp_path).rebuilt  # up to date: reused
    assert not build_reference(tmp_path, min_count=3).rebuilt  # a larger threshold: derived from the cache
    frames[3][:] = 2000
    later = time.time() + 5
    cv2.imwrite(str(tmp_path / "hiexp" / "depth_mm_003.png"), frames[3].astype(np.uint16))
    os.utime(tmp_path / "hiexp" / "depth_mm_003.png", (later, later))
    rebuilt = build_reference(tmp_path, min_count=3)
    assert rebuilt.rebuilt and rebuilt.depth_mm[5, 7] == pytest.approx((1000 + 1002 + 1004 + 2000) / 4)
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_one_cache_serves_every_min_count_exactly_and_is_never_replaced_without_a_warning(tmp_path):
    """The cached reference at min_count c gives any m >= c bit for bit as a build at m does, without a rebuild or
    a write; a smaller m is rebuilt, cached in its place with a warning naming both values, and c is then derived
    from it (before: every other min_count rewrote the cache silently, e.g. 2 -> 5 by ``evaluate --ckpt``)."""
    frames, sat = hand_frames()
    for name in ("a", "b1", "b2", "b3", "b4"):
        write_scene(tmp_path / name, frames, sat)
    fresh = {m: build_reference(tmp_path / f"b{m}", min_count=m).depth_mm for m in (1, 2, 3, 4)}
    assert [int(np.isfinite(fresh[m]).sum()) for m in (1, 2, 3, 4)] == [48, 47, 45, 45]
    scene = tmp_path / "a"
    build_reference(scene, min_count=2)
    cached = {p: p.read_bytes() for p in (scene / REFERENCE_DEPTH, scene / REFERENCE_META)}
    for m in (2, 3, 4):
        ref = build_reference(scene, min_count=m)
        assert not ref.rebuilt and ref.min_count == m and ref.cached_min_count == 2
        np.testing.assert_array_equal(ref.depth_mm, fresh[m])  # NaN where the fresh build has NaN, equal elsewhere
    assert {p: p.read_bytes() for p in cached} == cached  # nothing written
    with pytest.warns(UserWarning, match=r"built with min_count 2 \(reference.json\); rebuilt with min_count 1"):
        ref = build_reference(scene, min_count=1)
    assert ref.rebuilt and json.loads((scene / REFERENCE_META).read_text())["min_count"] == 1
    np.testing.assert_array_equal(ref.depth_mm, fresh[1])
    again = build_reference(scene, min_count=2)
    assert not again.rebuilt and again.cached_min_count == 1
    np.testing.assert_array_equal(again.depth_mm, fresh[2])
    # a forced build at a larger threshold says what it replaced
    with pytest.warns(UserWarning, match=r"min_count 1 .*rebuilt with min_count 3 .*now needs a rebuild"):
        build_reference(scene, min_count=3, force=True)
    # a cache whose arrays are not those it recorded, or do not hold its recorded threshold (a pixel of enough
    # frames without a depth; here the arrays of min_count 3 with a reference.json edited to say 1) is rebuilt
    np.save(scene / REFERENCE_DEPTH, fresh[4])  # the same bytes as the forced build at 3 (45 valid pixels each)
    meta = json.loads((scene / REFERENCE_META).read_text())
    meta["min_count"] = 1
    (scene / REFERENCE_META).write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rebuilt at its recorded threshold: nothing of another setting replaced
        ref = build_reference(scene, min_count=2)
    assert ref.rebuilt and json.loads((scene / REFERENCE_META).read_text())["min_count"] == 1
    np.testing.assert_array_equal(ref.depth_mm, fresh[2])
    np.save(scene / REFERENCE_DEPTH, fresh[2])  # arrays other than the recorded ones
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref = build_reference(scene, min_count=2)
    assert ref.rebuilt
    np.testing.assert_array_equal(np.load(scene / REFERENCE_DEPTH), fresh[1])


def test_frames_rewritten_with_their_old_mtimes_make_the_reference_stale(tmp_path):
    """Frames rewritten +100 mm but with their old mtimes (``cp -p``, ``rsync -a``) rebuild the reference: the
    cache records each file's size and SHA-256 (before: mtime only, and the reference stayed 100 mm off). A set
    whose files only got other times (a copy, a touch) is not rebuilt."""
    frames, sat = hand_frames()
    write_scene(tmp_path, frames, sat)
    stored = [cv2.IMWRITE_PNG_COMPRESSION, 0]  # uncompressed: a rewritten frame keeps its size exactly
    for k, depth in enumerate(frames):
        cv2.imwrite(str(tmp_path / "hiexp" / f"depth_mm_{k:03d}.png"), depth.astype(np.uint16), stored)
    before = build_reference(tmp_path, min_count=2).depth_mm
    info = json.loads((tmp_path / REFERENCE_META).read_text())
    assert len(info["files"]) == 8 and all(len(r["sha256"]) == 64 for r in info["files"].values())
    for k, depth in enumerate(frames):
        path = tmp_path / "hiexp" / f"depth_mm_{k:03d}.png"
        st = os.stat(path)
        cv2.imwrite(str(path), np.where(depth > 0, depth + 100, 0).astype(np.uint16), stored)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
        # same mtime and, here, the same size: only the content tells
        assert (os.stat(path).st_mtime_ns, os.stat(path).st_size) == (st.st_mtime_ns, st.st_size)
    after = build_reference(tmp_path, min_count=2)
    assert after.rebuilt
    np.testing.assert_allclose(after.depth_mm, before + 100, equal_nan=True)
    # same bytes, other times (a copy of the set, a touch): the digests match
    for path in (tmp_path / "hiexp").iterdir():
        os.utime(path, ns=(0, os.stat(path).st_mtime_ns + 10**9))
    assert not build_reference(tmp_path, min_count=2).rebuilt
    # one byte more in a saturation mask (a size change) is a change too
    with open(tmp_path / "hiexp" / "saturated_001.png", "ab") as fh:
        fh.write(b"\0")
    assert build_reference(tmp_path, min_count=2).rebuilt
    # a cache written before the file records (format 1, no "files") is rebuilt once
    meta = json.loads((tmp_path / REFERENCE_META).read_text())
    del meta["files"], meta["format"]
    (tmp_path / REFERENCE_META).write_text(json.dumps(meta))
    assert build_reference(tmp_path, min_count=2).rebuilt and not build_reference(tmp_path, min_count=2).rebuilt


def test_missing_saturation_mask_and_shape_mismatch(tmp_path):
    frames, sat = hand_frames()
    write_scene(tmp_path, frames, sat)
    (tmp_path / "hiexp" / "saturated_002.png").unlink()
    with pytest.raises(FileNotFoundError, match="saturated_002.png"):
        build_reference(tmp_path)
    cv2.imwrite(str(tmp_path / "hiexp" / "saturated_002.png"), np.zeros((H, W + 1), np.uint8))
    with pytest.raises(ValueError, match=r"saturated_002.png has shape \(6, 9\); expected \(6, 8\)"):
        build_reference(tmp_path)


def test_load_real_scene_common_valid_region(tmp_path):
    from tofdenoise.physics.calibration import default_calibration

    frames, sat = hand_frames()
    input_depth = np.full((H, W), 1010, np.uint16)
    input_depth[4, 4] = 0  # invalid input pixel
    amplitude = np.arange(H * W, dtype=np.uint16).reshape(H, W) * 100 + 500
    write_scene(tmp_path, frames, sat, input_depth, amplitude)
    item = load_real_scene(tmp_path, default_calibration(), min_count=2)
    mask = item["mask"] > 0
    assert not mask[4, 4] and not mask[2, 2] and mask[0, 0] and mask.sum() == H * W - 2
    np.testing.assert_array_equal(item["noisy"][mask], 1010)
    assert item["clean"][0, 0] == pytest.approx(1005.0)
    assert np.all(item["sigma"][mask] > 0) and np.all(item["sigma"][~mask] == 0)
    np.testing.assert_array_equal(item["amplitude"][mask], amplitude[mask])
    # brighter pixels get a smaller sigma_D at equal depth
    assert item["sigma"][5, 7] < item["sigma"][0, 1]


def test_real_test_dataloader_on_simulated_set(tmp_path):
    from tofdenoise.data_modules import ToFDataModule
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    simulate_capture_set(tmp_path / "set", scenes=3, frames=4, height=32, width=48, seed=1)
    dm = ToFDataModule(
        source_kwargs=dict(num_samples=6, height=32, width=48),
        crop_size=16,
        cache_dir=str(tmp_path / "c"),
        real_dir=str(tmp_path / "set"),
    )
    dm.prepare_data()
    dm.setup("test")
    assert dm.test_set_names == ["synthetic", "simulated", "real"]
    loaders = dm.test_dataloader()
    assert len(loaders) == 3
    batches = list(loaders[2])
    assert [b["name"][0] for b in batches] == ["scene_0000", "scene_0001", "scene_0002"]
    b = batches[0]
    m = b["mask"] > 0
    inp = cv2.imread(str(tmp_path / "set" / "scene_0000" / "input_depth_mm.png"), cv2.IMREAD_UNCHANGED)
    ref = np.load(tmp_path / "set" / "scene_0000" / "reference_depth_mm.npy")
    np.testing.assert_array_equal(b["noisy"][0, 0].numpy()[m[0, 0].numpy()], inp[m[0, 0].numpy()])
    np.testing.assert_allclose(b["clean"][0, 0].numpy()[m[0, 0].numpy()], ref[m[0, 0].numpy()])
    assert torch.all(b["clean"][~m] == 0) and m.float().mean() > 0.3
    # the scoring mask is exactly the common valid region of the input frame and the reference
    np.testing.assert_array_equal(m[0, 0].numpy(), (inp > 0) & np.isfinite(ref))


def test_missing_real_dir_names_the_key(tmp_path):
    from tofdenoise.data_modules import ToFDataModule

    # checked when the datamodule is built, before any trainer exists (it was found only in prepare_data)
    with pytest.raises(FileNotFoundError, match="data.real_dir"):
        ToFDataModule(
            source_kwargs=dict(num_samples=6, height=32, width=48),
            crop_size=16,
            cache_dir=str(tmp_path / "c"),
            real_dir=str(tmp_path / "nowhere"),
        )


def test_scene_without_common_valid_region_is_skipped(tmp_path):
    from tofdenoise.data_modules import ToFDataModule
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    simulate_capture_set(tmp_path / "set", scenes=2, frames=2, height=16, width=24, seed=2)
    cv2.imwrite(str(tmp_path / "set" / "scene_0001" / "input_depth_mm.png"), np.zeros((16, 24), np.uint16))
    dm = ToFDataModule(
        source_kwargs=dict(num_samples=6, height=16, width=24),
        crop_size=8,
        cache_dir=str(tmp_path / "c"),
        real_dir=str(tmp_path / "set"),
    )
    with pytest.warns(UserWarning, match="1 scene\\(s\\) with no common valid pixel skipped: scene_0001"):
        dm.prepare_data()
    assert dm.skipped_samples["real"] == ["scene_0001"] and dm.summary()["real_scenes"] == 1


def test_scene_without_input_frame_is_warned_and_counted(tmp_path):
    from tofdenoise.data_modules import ToFDataModule
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set
    from tofdenoise.data_modules.real_captures import list_scenes

    simulate_capture_set(tmp_path / "set", scenes=3, frames=2, height=16, width=24, seed=2)
    (tmp_path / "set" / "scene_0001" / "input_depth_mm.png").unlink()
    (tmp_path / "set" / "notes").mkdir()  # an unrelated folder is no scene and no warning
    incomplete: list[str] = []
    with pytest.warns(
        UserWarning,
        match=r"1 scene folder\(s\) with hiexp/ but no input_depth_mm\.png skipped: "
        r"scene_0001",
    ):
        scenes = list_scenes(tmp_path / "set", incomplete=incomplete)
    assert [s.name for s in scenes] == ["scene_0000", "scene_0002"] and incomplete == ["scene_0001"]
    # an empty-mask scene and the incomplete one are both counted as skipped by the datamodule
    cv2.imwrite(str(tmp_path / "set" / "scene_0002" / "input_depth_mm.png"), np.zeros((16, 24), np.uint16))
    dm = ToFDataModule(
        source_kwargs=dict(num_samples=6, height=16, width=24),
        crop_size=8,
        cache_dir=str(tmp_path / "c"),
        real_dir=str(tmp_path / "set"),
    )
    with pytest.warns(UserWarning, match="hiexp/ but no input_depth_mm.png"):
        dm.prepare_data()
    assert dm.skipped_samples["real"] == ["scene_0001", "scene_0002"]
    assert dm.summary()["real_scenes"] == 1 and dm.summary()["skipped"]["real"] == 2


def test_metrics_json_counts_the_scenes_the_datamodule_skipped(tmp_path):
    """The real set's skipped_images = scenes left out by the datamodule + images without a valid pixel."""
    import json
    from types import SimpleNamespace

    from tofdenoise.callbacks.run_outputs import write_test_outputs
    from tofdenoise.records import learned_verdict, set_entry

    m = {"psnr_db": 40.0, "mae_mm": 2.0, "mse_mm2": 9.0, "ssim": 0.99}
    model = SimpleNamespace(
        test_results={
            "synthetic": set_entry(m, m, {"images": 2, "skipped_images": 0, "valid_px": 10}),
            "real": set_entry(m, m, {"images": 1, "skipped_images": 1, "valid_px": 5}),
        },
        test_per_image={},
        learned_record=lambda: learned_verdict(10, 2.0, 9.0),
        _trainer=SimpleNamespace(
            datamodule=SimpleNamespace(skipped_samples={"real": ["scene_0001", "scene_0002"], "train": ["x"]})
        ),
    )
    write_test_outputs(model, tmp_path)
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["real"]["skipped_images"] == 3 and data["real"]["images"] == 1
    assert data["synthetic"]["skipped_images"] == 0  # skipped training samples are not test images
    assert model.test_results["real"]["skipped_images"] == 1  # the module's own record is left as it was


def test_reference_validity_changes_only_the_scoring_mask(tmp_path):
    """The real set's network input is the frame as captured: invalidating part of the reference shrinks the
    scoring mask (common ROI of input and reference) but leaves the input, and the network input, unchanged."""
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set
    from tofdenoise.physics.calibration import default_calibration
    from tofdenoise.training.module import DepthRestorer

    simulate_capture_set(tmp_path / "set", scenes=1, frames=4, height=24, width=32, seed=3)
    scene = tmp_path / "set" / "scene_0000"
    calib = default_calibration()
    before = load_real_scene(scene, calib)
    block = np.zeros((24, 32), bool)
    block[4:12, 6:20] = True
    for path in (scene / "hiexp").glob("depth_mm_*.png"):  # no high-exposure frame is valid in the block
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        depth[block] = 0
        cv2.imwrite(str(path), depth)
    build_reference(scene, force=True)
    after = load_real_scene(scene, calib)
    mask_before, mask_after = before["mask"] > 0, after["mask"] > 0
    assert mask_before[block].mean() > 0.5 and not mask_after[block].any()
    np.testing.assert_array_equal(mask_after, mask_before & ~block)
    for key in ("noisy", "amplitude"):
        np.testing.assert_array_equal(after[key], before[key])
    input_valid = cv2.imread(str(scene / "input_depth_mm.png"), cv2.IMREAD_UNCHANGED) > 0
    assert np.all(after["noisy"][block & input_valid] > 0)  # fed although not scored
    assert np.all(after["noisy"][~input_valid] == 0) and np.all(after["amplitude"][~input_valid] == 0)
    assert np.all(after["clean"][~mask_after] == 0) and np.all(after["sigma"][~mask_after] == 0)

    def batch(item):
        return {k: torch.from_numpy(item[k])[None, None] for k in ("noisy", "clean", "sigma", "mask", "amplitude")}

    model = DepthRestorer(
        backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, conditioning={"use_signal_channel": True}
    )
    torch.testing.assert_close(model.network_input(batch(after)), model.network_input(batch(before)), rtol=0, atol=0)


def test_scenes_simulated_in_parallel_are_byte_identical_and_resume(tmp_path):
    """``workers=2`` (two spawned processes) writes the same files, byte for byte, as one process: each scene draws
    from its own generator. Complete scenes are skipped on a re-run, and a bad worker count is refused."""
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    settings = {"scenes": 3, "frames": 3, "height": 16, "width": 24, "seed": 5, "mixed_pixels": 2}
    seen = []
    one = simulate_capture_set(tmp_path / "one", **settings)
    two = simulate_capture_set(tmp_path / "two", **settings, workers=2, progress=lambda i, n, info: seen.append(i))
    assert (one.scenes_written, two.scenes_written) == (3, 3) and sorted(seen) == [0, 1, 2]
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    assert len(files) > 3 * 8
    assert files == sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*") if p.is_file())
    assert [f for f in files if (tmp_path / "one" / f).read_bytes() != (tmp_path / "two" / f).read_bytes()] == []
    again = simulate_capture_set(tmp_path / "two", **settings, workers=2)
    assert (again.scenes_written, again.scenes_skipped) == (0, 3)
    with pytest.raises(ValueError, match="--workers must be an integer >= 1, got 0"):
        simulate_capture_set(tmp_path / "bad", **settings, workers=0)
