"""LightningCLI predict on a folder of frames (no noise synthesis) writes what tofdenoise denoise writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.cli.denoise import main as denoise_main
from tofdenoise.inference.predict import FramesDataModule
from tofdenoise.inference.predict import main as predict_main


def test_lightningcli_predict_equals_the_command(tmp_path, restorer_ckpt):
    src = tmp_path / "frames"
    (src / "sub").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for rel in ("a", "sub/b"):
        d = rng.uniform(600, 1400, (30, 44)).round().astype(np.uint16)
        d[4:9, 3:12] = 0
        cv2.imwrite(str(src / f"{rel}.png"), d)
    np.save(src / "sub" / "c.npy", np.where(rng.random((30, 44)) < 0.1, np.nan, 1000.0).astype(np.float32))
    amp = tmp_path / "amp"
    amp.mkdir()
    for stem in ("a", "b", "c"):
        np.save(amp / f"{stem}.npy", rng.uniform(10, 900, (30, 44)).astype(np.float32))
    cli_out, lit_out = tmp_path / "cli", tmp_path / "lit"
    assert (
        denoise_main(
            [
                str(src),
                "--ckpt",
                str(restorer_ckpt),
                "--out",
                str(cli_out),
                "--npy",
                "--quiet",
                "--amplitude",
                str(amp),
                "--sensor",
                "default",
            ]
        )
        == 0
    )
    predict_main(
        [
            "predict",
            "--ckpt_path",
            str(restorer_ckpt),
            "--data.inputs",
            f"[{src}]",
            "--data.amplitude",
            str(amp),
            "--data.sensor",
            "default",
            "--trainer.callbacks",
            "tofdenoise.inference.FramesPredictionWriter",
            "--trainer.callbacks.out_dir",
            str(lit_out),
            "--trainer.callbacks.npy",
            "true",
            "--trainer.accelerator",
            "cpu",
            "--trainer.enable_progress_bar",
            "false",
        ]
    )
    cli_files = sorted(p.relative_to(cli_out).as_posix() for p in cli_out.rglob("*") if p.is_file())
    lit_files = sorted(p.relative_to(lit_out).as_posix() for p in lit_out.rglob("*") if p.is_file())
    assert (
        cli_files
        == lit_files
        == [
            "a.npy",
            "a.png",
            "a_sigma_mm.npy",
            "sub/b.npy",
            "sub/b.png",
            "sub/b_sigma_mm.npy",
            "sub/c.npy",
            "sub/c.png",
            "sub/c_sigma_mm.npy",
        ]
    )
    for rel in cli_files:
        a, b = cli_out / rel, lit_out / rel
        if rel.endswith(".npy"):
            np.testing.assert_array_equal(np.load(a), np.load(b), err_msg=rel)
        else:
            assert a.read_bytes() == b.read_bytes(), rel


def test_frames_datamodule_errors(tmp_path):
    with pytest.raises(ValueError, match="no depth frame"):
        FramesDataModule(inputs=[str(tmp_path)])
    with pytest.raises(ValueError, match="sensor needs amplitude"):
        FramesDataModule(inputs=[str(tmp_path)], sensor="default")
    with pytest.raises(TypeError, match="calib"):  # the calibration is ``sensor`` in every command (issue 24)
        FramesDataModule(inputs=[str(tmp_path)], calib="default")
