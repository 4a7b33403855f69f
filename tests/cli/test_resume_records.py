"""A resume that cannot load its checkpoint rewrites nothing of the run; a broken checkpoint gets one clear line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

from tofdenoise.cli.train import run
from tofdenoise.config import compose_config
from tofdenoise.training.checkpoint_file import CheckpointFileError, check_checkpoint_file

REPO = Path(__file__).resolve().parents[2]
RECORDS = ("run_info.json", "config.yaml", "metrics.json")


@pytest.fixture
def finished_run(tmp_path, data_cache, tiny):
    run_dir = tmp_path / "finished"
    cfg = compose_config(tiny(run_dir, data_cache) + ["trainer.max_epochs=1", "logger=csv"])
    run(cfg)
    info = json.loads((run_dir / "run_info.json").read_text())
    assert {"finished", "global_step", "best_ckpt"} <= set(info)
    return run_dir, data_cache


def _copy_run(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _snapshot(run_dir: Path) -> dict[str, bytes]:
    return {name: (run_dir / name).read_bytes() for name in RECORDS}


def test_truncated_last_ckpt_is_named_and_the_finished_run_is_untouched(finished_run, tmp_path, tiny):
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    last = run_dir / "checkpoints" / "last.ckpt"
    os.truncate(last, last.stat().st_size // 2)
    before = _snapshot(run_dir)
    cfg = compose_config(
        tiny(run_dir, finished_run[1])
        + ["trainer.max_epochs=2", "logger=csv", "ckpt_path=last", "reuse_finished=false"]
    )
    with pytest.raises(CheckpointFileError) as err:
        run(cfg)
    msg = str(err.value)
    assert str(last) in msg and "truncated" in msg and "best.ckpt" in msg and f"delete {last}" in msg
    assert _snapshot(run_dir) == before
    # the console script: exit status 2 and one line, no traceback
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            "from tofdenoise.cli.train import main; main()",
            *tiny(run_dir, finished_run[1]),
            "logger=csv",
            "ckpt_path=last",
            "reuse_finished=false",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO / "src")},
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith("tofdenoise train: error: checkpoint ")
    assert "Traceback" not in proc.stderr
    assert _snapshot(run_dir) == before


def test_checkpoint_that_does_not_fit_the_model_leaves_the_records(finished_run, tmp_path, tiny):
    """Lightning fails while restoring (another network width): the records are only rewritten after a load."""
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    before = _snapshot(run_dir)
    cfg = compose_config(
        tiny(run_dir, finished_run[1])
        + ["trainer.max_epochs=2", "logger=csv", "ckpt_path=last", "reuse_finished=false", "backbone.kwargs.width=16"]
    )
    with pytest.raises(Exception, match="another architecture"):
        run(cfg)
    assert _snapshot(run_dir) == before


def test_test_only_run_that_cannot_load_leaves_the_records(finished_run, tmp_path, tiny):
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    before = _snapshot(run_dir)
    cfg = compose_config(tiny(run_dir, finished_run[1]) + ["train=false", "logger=csv", "backbone.kwargs.width=16"])
    with pytest.raises(Exception, match="another architecture"):
        run(cfg)
    assert _snapshot(run_dir) == before
    best = run_dir / "checkpoints" / "best.ckpt"
    os.truncate(best, best.stat().st_size // 3)
    cfg = compose_config(tiny(run_dir, finished_run[1]) + ["train=false", "logger=csv"])
    with pytest.raises(CheckpointFileError, match=rf"checkpoint {best} is not a complete checkpoint"):
        run(cfg)
    assert _snapshot(run_dir) == before
    # a test-only run that loads writes its records (after loading) and new metrics
    good = _copy_run(finished_run[0], tmp_path / "good")
    run(compose_config(tiny(good, finished_run[1]) + ["train=false", "logger=csv"]))
    info = json.loads((good / "run_info.json").read_text())
    assert info["best_ckpt"] == str(good / "checkpoints" / "best.ckpt") and "finished" in info
    assert (good / "config.yaml").is_file() and (good / "metrics.json").is_file()


def test_resumed_run_rewrites_its_records_after_loading(finished_run, tmp_path, tiny):
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    old = json.loads((run_dir / "run_info.json").read_text())
    cfg = compose_config(
        tiny(run_dir, finished_run[1])
        + ["trainer.max_epochs=2", "logger=csv", "ckpt_path=last", "reuse_finished=false"]
    )
    run(cfg)
    info = json.loads((run_dir / "run_info.json").read_text())
    assert info["started"] == old["started"] and "resumed" in info and "finished" in info
    assert info["global_step"] == 2 * old["global_step"]
    assert "max_epochs: 2" in (run_dir / "config.yaml").read_text()


def test_check_checkpoint_file_damaged_and_foreign_files(tmp_path):
    good = tmp_path / "good.ckpt"
    torch.save({"state_dict": {"w": torch.arange(1000.0)}, "epoch": 0}, good)
    assert check_checkpoint_file(good) == good
    # flip bytes inside the stored tensor: the zip directory is intact, the member's CRC is not
    data = bytearray(good.read_bytes())
    with zipfile.ZipFile(good) as zf:
        info = next(i for i in zf.infolist() if i.filename.endswith("/data/0"))
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra) + 64
    data[start : start + 16] = bytes(16)
    bad = tmp_path / "last.ckpt"
    bad.write_bytes(bytes(data))
    with pytest.raises(CheckpointFileError, match=r"last\.ckpt is a damaged checkpoint .*CRC"):
        check_checkpoint_file(bad)
    plain = tmp_path / "weights.pt"
    torch.save({"w": torch.zeros(3)}, plain)
    with pytest.raises(CheckpointFileError, match="no 'state_dict'"):
        check_checkpoint_file(plain)
    text = tmp_path / "notes.ckpt"
    text.write_text("hello")
    with pytest.raises(CheckpointFileError, match=r"notes\.ckpt is not a complete checkpoint .*delete"):
        check_checkpoint_file(text)
