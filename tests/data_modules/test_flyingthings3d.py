"""ToF-FlyingThings3D reader on a tiny fixture written in the real layout (.mat v5, PNG, list files)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tofdenoise.data_modules.sources.flyingthings3d import FlyingThings3DSource, radial_to_z

H, W = 24, 32


def test_radial_to_z_hand_values():
    f = (W / 2) / math.tan(math.radians(63.5) / 2)
    r = np.full((H, W), 1000.0, np.float32)
    z = radial_to_z(r)
    assert z[H // 2, W // 2] == pytest.approx(1000.0)  # optical axis
    u = W // 2 + 10
    assert z[H // 2, u] == pytest.approx(1000.0 / math.sqrt((10 / f) ** 2 + 1), rel=1e-6)
    assert z[0, 0] == pytest.approx(1000.0 / math.sqrt((W / 2 / f) ** 2 + (H / 2 / f) ** 2 + 1), rel=1e-6)


@pytest.mark.parametrize("gt_dir", ["gt_depth_rgb", "gt_depth_rgb_small_pt"])
def test_reader_scales_converts_and_masks(tmp_path, gt_dir, write_ft3d):
    data = write_ft3d(tmp_path, ["a_0001", "a_0002"], ["b_0001"], gt_dir=gt_dir)
    src = FlyingThings3DSource(tmp_path)
    assert src.sample_ids() == ["a_0001", "a_0002", "b_0001"]
    src.check()
    s = src.load("b_0001")
    gt, conf, amp = data["b_0001"]
    expected_valid = (gt > 0) & (conf > 0)
    np.testing.assert_array_equal(s.valid, expected_valid)
    np.testing.assert_allclose(s.depth_mm[s.valid], radial_to_z(gt * 2.0)[s.valid], rtol=1e-6)
    np.testing.assert_array_equal(s.amplitude[s.valid], amp[s.valid].astype(np.float32))
    assert s.depth_mm[s.valid].max() <= 3000 and s.depth_mm[s.valid].min() > 500


def test_missing_listed_file_fails_before_training(tmp_path, write_ft3d):
    write_ft3d(tmp_path, ["a_0001", "a_0002"], ["b_0001"])
    (tmp_path / "nToF" / "a_0002_noisy_intensity.png").unlink()
    with pytest.raises(FileNotFoundError, match="a_0002_noisy_intensity.png"):
        FlyingThings3DSource(tmp_path).check()
    from tofdenoise.data_modules import ToFDataModule

    dm = ToFDataModule(
        source="flyingthings3d",
        source_kwargs={"root": str(tmp_path)},
        cache_dir=str(tmp_path / "cache"),
        crop_size=16,
    )
    with pytest.raises(FileNotFoundError, match="1 listed file"):
        dm.prepare_data()


def test_missing_root_says_which_key_to_set(tmp_path):
    from tofdenoise.data_modules import ToFDataModule

    with pytest.raises(ValueError, match=r"set data\.source_kwargs\.root="):
        ToFDataModule(source="flyingthings3d")
    with pytest.raises(ValueError, match=r"set data\.source_kwargs\.root="):
        ToFDataModule(source="flyingthings3d", source_kwargs={"root": None})
    with pytest.raises(FileNotFoundError, match=r"absent \(set data\.source_kwargs\.root"):
        ToFDataModule(source="flyingthings3d", source_kwargs={"root": str(tmp_path / "absent")})


def test_shape_mismatch_names_both_files(tmp_path, write_ft3d):
    write_ft3d(tmp_path, ["a_0001"], ["b_0001"])
    cv2.imwrite(str(tmp_path / "nToF" / "a_0001_noisy_intensity.png"), np.ones((H, W + 1), np.uint8))
    with pytest.raises(ValueError, match=r"a_0001_noisy_intensity.png has shape \(24, 33\); expected \(24, 32\)"):
        FlyingThings3DSource(tmp_path).load("a_0001")


def test_datamodule_on_fixture(tmp_path, write_ft3d):
    from tofdenoise.data_modules import ToFDataModule

    write_ft3d(tmp_path, [f"t{i:03d}" for i in range(7)], [f"v{i:03d}" for i in range(3)])
    dm = ToFDataModule(
        source="flyingthings3d",
        source_kwargs={"root": str(tmp_path)},
        cache_dir=str(tmp_path / "cache"),
        crop_size=16,
        batch_size=2,
    )
    dm.prepare_data()
    dm.setup("fit")
    assert {k: len(v) for k, v in dm.splits.items()} == {"train": 6, "val": 2, "test": 2}
    batch = next(iter(dm.train_dataloader()))
    assert batch["noisy"].shape == (2, 1, 16, 16)
    full = next(iter(dm.val_dataloader()))
    assert full["clean"].shape == (1, 1, H, W)
    assert float(full["mask"][0, 0, 0, 0]) == 0.0 and float(full["clean"][0, 0, 0, 0]) == 0.0
