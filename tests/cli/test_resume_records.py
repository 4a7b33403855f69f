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
from tofdenoise.experiments.train_job import RunConfigMismatchError
from tofdenoise.output_guard import OutputPathError
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
    """Lightning fails while restoring (another network width): the records are only rewritten after a load. With
    the folder's config.yaml in place the resume is refused before (another config); without it (a folder whose
    config is not recorded) Lightning's restore is what fails, and run_info.json and metrics.json stay."""
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    before = _snapshot(run_dir)
    overrides = ["logger=csv", "ckpt_path=last", "reuse_finished=false", "backbone.kwargs.width=16"]
    cfg = compose_config(tiny(run_dir, finished_run[1]) + overrides)
    with pytest.raises(RunConfigMismatchError, match=r"backbone.kwargs.width: 8 there, 16 now"):
        run(cfg)
    assert _snapshot(run_dir) == before
    (run_dir / "config.yaml").unlink()
    kept = {name: before[name] for name in ("run_info.json", "metrics.json")}
    with pytest.raises(Exception, match="another architecture"):
        run(cfg)
    assert {name: (run_dir / name).read_bytes() for name in kept} == kept


def test_test_only_run_that_cannot_load_leaves_the_records(finished_run, tmp_path, tiny):
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    before = _snapshot(run_dir)
    cfg = compose_config(tiny(run_dir, finished_run[1]) + ["train=false", "logger=csv", "backbone.kwargs.width=16"])
    with pytest.raises(RunConfigMismatchError, match=r"a test with this config \(train=false\)"):
        run(cfg)
    assert _snapshot(run_dir) == before
    best = run_dir / "checkpoints" / "best.ckpt"
    os.truncate(best, best.stat().st_size // 3)
    cfg = compose_config(tiny(run_dir, finished_run[1]) + ["train=false", "logger=csv", "trainer.max_epochs=1"])
    with pytest.raises(CheckpointFileError, match=rf"checkpoint {best} is not a complete checkpoint"):
        run(cfg)
    assert _snapshot(run_dir) == before


def test_a_test_of_the_fitted_run_keeps_the_fits_record(finished_run, tmp_path, tiny):
    """``train=false`` in the folder of a finished run tests its own best.ckpt and keeps the fit's record (steps,
    training cost, start, config); another checkpoint, another config or an interrupted fit there is refused with
    the records untouched (they were replaced by a test-only record: 0 steps, no training cost)."""
    good = _copy_run(finished_run[0], tmp_path / "good")
    fit = json.loads((good / "run_info.json").read_text())
    config = (good / "config.yaml").read_bytes()
    same = ["train=false", "logger=csv", "trainer.max_epochs=1"]
    run(compose_config(tiny(good, finished_run[1]) + same))
    info = json.loads((good / "run_info.json").read_text())
    assert info["best_ckpt"] == str(good / "checkpoints" / "best.ckpt") and "finished" in info and "tested" in info
    for key in ("started", "global_step", "train_seconds", "commit", "machine"):
        assert info[key] == fit[key], key
    assert (good / "config.yaml").read_bytes() == config and (good / "metrics.json").is_file()
    before = _snapshot(good)
    other = finished_run[0] / "checkpoints" / "last.ckpt"
    cfg = compose_config(tiny(good, finished_run[1]) + [*same, f"ckpt_path={other}"])
    with pytest.raises(OutputPathError, match="a test of another checkpoint"):
        run(cfg)
    assert _snapshot(good) == before
    interrupted = _copy_run(finished_run[0], tmp_path / "interrupted")
    info = json.loads((interrupted / "run_info.json").read_text())
    for key in ("finished", "global_step", "train_seconds"):
        info.pop(key, None)
    (interrupted / "run_info.json").write_text(json.dumps(info))
    (interrupted / "metrics.json").unlink()
    cfg = compose_config(tiny(interrupted, finished_run[1]) + same)
    with pytest.raises(OutputPathError, match="whose fit has not ended"):
        run(cfg)
    # a folder without a training run takes a test of any checkpoint, its records its own
    fresh = tmp_path / "fresh"
    best = finished_run[0] / "checkpoints" / "best.ckpt"
    run(compose_config(tiny(fresh, finished_run[1]) + ["train=false", "logger=csv", f"ckpt_path={best}"]))
    info = json.loads((fresh / "run_info.json").read_text())
    assert info["best_ckpt"] == str(best) and info["global_step"] == 0 and "tested" not in info


def test_resumed_run_rewrites_its_records_after_loading(finished_run, tmp_path, tiny):
    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    old = json.loads((run_dir / "run_info.json").read_text())
    cfg = compose_config(
        tiny(run_dir, finished_run[1])
        + ["trainer.max_epochs=1", "logger=csv", "ckpt_path=last", "reuse_finished=false"]
    )
    run(cfg)
    info = json.loads((run_dir / "run_info.json").read_text())
    assert info["started"] == old["started"] and "resumed" in info and "finished" in info
    assert info["global_step"] == old["global_step"]  # resumed at its end: nothing left to train
    # a copied folder tests, and records, its own best.ckpt (Lightning kept the original folder's path)
    assert old["best_ckpt"] == str(finished_run[0] / "checkpoints" / "best.ckpt")
    assert info["best_ckpt"] == str(run_dir / "checkpoints" / "best.ckpt")


def test_a_resume_with_another_config_is_refused_and_a_fresh_start_replaces_the_run(
    finished_run, tmp_path, tiny, monkeypatch
):
    """Resumed with another config, the folder's optimiser and schedule came back with the earlier settings and the
    records named the new config as the whole run's: refused, naming the settings, records untouched. A fresh start
    (ckpt_path=null) replaces the earlier run: its results and checkpoints are removed when training starts, so that
    an interrupted new run never shows the earlier run's scores under its labels, nor resumes its last.ckpt."""
    from tofdenoise.callbacks.checkpointing import BestAndLastCheckpoint

    run_dir = _copy_run(finished_run[0], tmp_path / "run")
    before = _snapshot(run_dir)
    resume = ["logger=csv", "reuse_finished=false", "ckpt_path=last", "loss=l1", "trainer.max_epochs=1"]
    with pytest.raises(RunConfigMismatchError, match=r"resume from its checkpoint(.|\n)*'full' there"):
        run(compose_config(tiny(run_dir, finished_run[1]) + resume))
    assert _snapshot(run_dir) == before
    seen: dict[str, bool] = {}
    original = BestAndLastCheckpoint.on_train_start

    def on_train_start(self, trainer, pl_module):  # the checkpoint callbacks run after RunOutputs
        original(self, trainer, pl_module)
        for name in ("metrics.json", "per_image", "checkpoints/last.ckpt", "checkpoints/best.ckpt"):
            seen[name] = (run_dir / name).exists()

    monkeypatch.setattr(BestAndLastCheckpoint, "on_train_start", on_train_start)
    fresh = ["logger=csv", "reuse_finished=false", "ckpt_path=null", "loss=l1", "trainer.max_epochs=1"]
    run(compose_config(tiny(run_dir, finished_run[1]) + fresh))
    assert seen == dict.fromkeys(("metrics.json", "per_image", "checkpoints/last.ckpt", "checkpoints/best.ckpt"), False)
    info = json.loads((run_dir / "run_info.json").read_text())
    assert info["loss"] == "l1" and "resumed" not in info and "finished" in info


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
