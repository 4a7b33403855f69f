"""The `folder` source: list file, formats, invalid pixels, bad input, empty samples."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.data_modules.sources.folder import FolderSource

H, W = 20, 24


def write_folder(root, n=6, rng=None):
    rng = rng or np.random.default_rng(0)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    (root / "amp").mkdir(exist_ok=True)
    lines = []
    for i in range(n):
        depth = rng.uniform(500, 2000, size=(H, W))
        amp = rng.uniform(10, 1000, size=(H, W)).astype(np.float32)
        if i % 2:
            cv2.imwrite(str(root / "depth" / f"d{i}.png"), np.rint(depth).astype(np.uint16))
            name = f"depth/d{i}.png"
        else:
            np.save(root / "depth" / f"d{i}.npy", depth.astype(np.float32))
            name = f"depth/d{i}.npy"
        np.save(root / "amp" / f"a{i}.npy", amp)
        lines.append(f"{name} amp/a{i}.npy")
    (root / "list.txt").write_text("# depth amplitude\n" + "\n".join(lines) + "\n")
    return lines


def test_reads_png_and_npy_with_ids_from_list(tmp_path):
    write_folder(tmp_path)
    src = FolderSource(tmp_path)
    assert src.sample_ids() == [f"depth/d{i}" for i in range(6)]
    src.check()
    s = src.load("depth/d1")
    assert s.depth_mm.dtype == np.float32 and s.valid.all()
    assert np.all(s.depth_mm == np.rint(s.depth_mm))  # 16-bit PNG in mm


def test_nan_inf_negative_zero_depth_are_invalid(tmp_path):
    (tmp_path / "d").mkdir()
    depth = np.full((H, W), 1000.0, np.float32)
    depth[0, 0], depth[0, 1], depth[0, 2], depth[0, 3], depth[0, 4] = np.nan, np.inf, -5.0, 0.0, -np.inf
    np.save(tmp_path / "d" / "x.npy", depth)
    np.save(tmp_path / "d" / "a.npy", np.ones((H, W), np.float32))
    (tmp_path / "list.txt").write_text("d/x.npy d/a.npy\n")
    s = FolderSource(tmp_path).load("d/x")
    assert not s.valid[0, :5].any() and s.valid.sum() == H * W - 5
    assert np.all(np.isfinite(s.depth_mm)) and np.all(s.depth_mm[~s.valid] == 0)


def test_missing_sample_is_an_error_at_prepare_time(tmp_path):
    from tofdenoise.data_modules import ToFDataModule

    write_folder(tmp_path)
    with open(tmp_path / "list.txt", "a") as handle:
        handle.write("depth/ghost.png amp/ghost.npy\n")
    dm = ToFDataModule(
        source="folder", source_kwargs={"root": str(tmp_path)}, cache_dir=str(tmp_path / "c"), crop_size=8
    )
    with pytest.raises(FileNotFoundError, match=r"2 listed file\(s\) missing(.|\n)*ghost.png"):
        dm.prepare_data()


def test_shape_mismatch_and_bad_list_line(tmp_path):
    write_folder(tmp_path, n=2)
    np.save(tmp_path / "amp" / "a0.npy", np.ones((H + 1, W), np.float32))
    with pytest.raises(ValueError, match=r"a0.npy has shape \(21, 24\); expected \(20, 24\)"):
        FolderSource(tmp_path).load("depth/d0")
    (tmp_path / "list.txt").write_text("only_one_column.png\n")
    with pytest.raises(ValueError, match="entry 1: expected '<depth> <amplitude> \\[<mask>\\]'"):
        FolderSource(tmp_path).sample_ids()


def test_sample_without_valid_pixel_is_skipped_with_warning(tmp_path):
    from tofdenoise.data_modules import ToFDataModule

    write_folder(tmp_path, n=10)
    np.save(tmp_path / "depth" / "d4.npy", np.full((H, W), np.nan, np.float32))
    dm = ToFDataModule(
        source="folder", source_kwargs={"root": str(tmp_path)}, cache_dir=str(tmp_path / "c"), crop_size=8, seed=0
    )
    with pytest.warns(UserWarning, match="1 sample\\(s\\) with no valid pixel skipped: depth/d4"):
        dm.prepare_data()
    skipped_split = next(iter(dm.skipped_samples))
    assert dm.skipped_samples == {skipped_split: ["depth/d4"]}
    assert all("depth/d4" not in ids for ids in dm.splits.values())
    assert sum(len(v) for v in dm.splits.values()) == 9
    assert dm.summary()["skipped"] == {skipped_split: 1}


def test_depth_in_metres_is_refused_naming_the_file_and_the_setting(tmp_path):
    """A map in metres read as millimetres (median about 1 mm) trained on sigma_D of a 1 mm scene and noise larger
    than the depth, exit 0; now the first such file stops the data preparation, and depth_unit_mm=1000 reads it."""
    from tofdenoise.data_modules import ToFDataModule

    write_folder(tmp_path, n=4)
    metres = np.random.default_rng(1).uniform(0.5, 2.0, size=(H, W)).astype(np.float32)
    np.save(tmp_path / "depth" / "d2.npy", metres)
    refused = r"d2.npy: median valid depth 1\.\d+ mm is implausible(.|\n)*depth_unit_mm=1000"
    with pytest.raises(ValueError, match=refused):
        FolderSource(tmp_path).load("depth/d2")
    dm = ToFDataModule(
        source="folder", source_kwargs={"root": str(tmp_path)}, cache_dir=str(tmp_path / "c"), crop_size=8, seed=0
    )
    with pytest.raises(ValueError, match="d2.npy"):
        dm.prepare_data()
    sample = FolderSource(tmp_path, depth_unit_mm=1000).load("depth/d2")
    np.testing.assert_allclose(sample.depth_mm, metres * 1000, rtol=1e-6)
