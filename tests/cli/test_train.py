"""tofdenoise train (Hydra): fit + test end to end, outputs of a run, bad input, resume after SIGKILL."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from tofdenoise.cli.train import run
from tofdenoise.config import compose_config
from tofdenoise.models import trainable_backbones
from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.records import (
    RUN_KEYS,
    code_commit,
    code_digest,
    host_machine,
    learned_status,
    metric_sets,
    read_metrics_json,
    read_per_image_csv,
)
from tofdenoise.training.metrics import METRIC_KEYS

REPO = Path(__file__).resolve().parents[2]


def _check_metrics_json(path: Path, sets=("synthetic", "simulated")) -> dict:
    data = read_metrics_json(path)  # validates the schema
    assert sorted(metric_sets(data)) == sorted(sets)
    assert set(data) - set(sets) == set(RUN_KEYS)  # the learned guard's run-level fields
    for s in sets:
        for k in METRIC_KEYS:
            assert isinstance(data[s][k], float), (s, k)
            assert isinstance(data[s]["raw"][k], float), (s, "raw", k)
        assert data[s]["images"] >= 1
    return data


@pytest.mark.parametrize("backbone", trainable_backbones())
def test_fast_dev_run_fit_and_test_every_backbone(backbone, tmp_path, data_cache, tiny):
    cfg = compose_config(tiny(tmp_path, data_cache, backbone) + ["+trainer.fast_dev_run=true", "logger=csv"])
    result = run(cfg)
    assert result["best_ckpt"] is None  # fast_dev_run writes no checkpoint: the weights in memory are tested
    data = _check_metrics_json(tmp_path / "metrics.json")
    assert data["synthetic"]["images"] == 1  # fast_dev_run: one test batch of eval_batch_size 1
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert {"backbone": backbone, "noise": "hetero", "loss": "full"}.items() <= info.items()
    assert info["run_name"] == f"{backbone}-hetero-full" and info["global_step"] == 1
    # what the datamodule prepared (ToFDataModule.summary): split sizes, training and evaluation noise
    prepared = info["prepared_data"]
    assert prepared["noise"] == "hetero" and prepared["eval_noise"] == "hetero" and prepared["sizes"]["test"] >= 1
    assert not (tmp_path / "checkpoints" / "best.ckpt").exists()


def test_smoke_run_writes_every_output(tmp_path, data_cache, tiny, own_camera_file):
    own, calib_file = own_camera_file(tmp_path)  # data.sensor=<file> overrides the sensor group
    cfg = compose_config(tiny(tmp_path, data_cache) + ["trainer.max_epochs=3", f"++data.sensor={calib_file}"])
    result = run(cfg)
    ck = tmp_path / "checkpoints"
    assert sorted(p.name for p in ck.iterdir()) == ["best.ckpt", "last.ckpt"]
    assert result["best_ckpt"] == str(ck / "best.ckpt")
    data = _check_metrics_json(tmp_path / "metrics.json")
    rows = read_per_image_csv(tmp_path / "per_image" / "synthetic.csv")
    assert len(rows) == data["synthetic"]["images"] == 2  # 10 scenes split 6:2:2
    assert all(r["name"] for r in rows)
    mean_mae = sum(r["mae_mm"] for r in rows) / len(rows)
    assert mean_mae == pytest.approx(data["synthetic"]["mae_mm"], rel=1e-9)
    assert sum(r["raw_mae_mm"] for r in rows) / len(rows) == pytest.approx(data["synthetic"]["raw"]["mae_mm"])
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["global_step"] == 3 * 3 and info["best_ckpt"] == str(ck / "best.ckpt")
    # learning curves in CSV; best.ckpt = the epoch with the lowest val/mae_mm
    with open(tmp_path / "csv" / "metrics.csv") as fh:
        logged = list(csv.DictReader(fh))
    val = [(int(r["epoch"]), float(r["val/mae_mm"])) for r in logged if r.get("val/mae_mm")]
    assert [e for e, _ in val] == [0, 1, 2]
    assert any(r.get("train/lr") for r in logged) and any(r.get("val/raw/mae_mm") for r in logged)
    best_epoch = min(val, key=lambda t: t[1])[0]
    assert torch.load(ck / "best.ckpt", weights_only=True)["epoch"] == best_epoch
    assert torch.load(ck / "last.ckpt", weights_only=True)["epoch"] == 2
    # the offline wandb run lives in the run folder, with its id kept for resumes
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    run_id = (tmp_path / "wandb_run_id.txt").read_text().strip()
    assert len(runs) == 1 and runs[0].name.endswith(run_id)
    # config.yaml records the camera the run used, not the sensor group's default that data.sensor replaced
    saved = OmegaConf.load(tmp_path / "config.yaml")
    assert saved.data.sensor == str(calib_file)
    assert SensorCalibration.from_dict(OmegaConf.to_container(saved.sensor)).fingerprint() == own.fingerprint()
    assert len(list((tmp_path / "panels").glob("epoch_*.png"))) == 3  # one sample panel per validation


def _cli(args: list[str], **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "WANDB_MODE": "offline"}
    return subprocess.run(
        [sys.executable, "-m", "tofdenoise.cli.train", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=300,
        **kw,
    )


def test_command_line_rejects_unknown_names_with_the_valid_ones(tmp_path):
    proc = _cli(["backbone=nope", f"paths.run_dir={tmp_path}"])
    assert proc.returncode != 0
    assert "backbone/nope" in proc.stderr and "dvss" in proc.stderr and "unet" in proc.stderr
    assert not (tmp_path / "checkpoints").exists()


def test_resume_after_sigkill_reaches_the_same_number_of_steps(tmp_path, data_cache, tiny):
    """Kill a run mid-epoch once last.ckpt exists, run the same command again (ckpt_path=last is the default: an
    interrupted run resumes from last.ckpt): same optimiser steps as an uninterrupted run of the same config."""
    steps_per_epoch, epochs = 12, 2  # 40 scenes -> 24 training samples, batch 2
    common = tiny("RUN", data_cache, num_samples=40) + [
        f"trainer.max_epochs={epochs}",
        "callbacks.model_checkpoint.every_n_train_steps=2",
        "logger=csv",
    ]

    def args(run_dir: Path, extra=()) -> list[str]:
        return [a.replace("RUN", str(run_dir)) for a in common] + list(extra)

    killed = tmp_path / "killed"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tofdenoise.cli.train", *args(killed)],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    last = killed / "checkpoints" / "last.ckpt"
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            if last.exists():
                try:
                    step = torch.load(last, weights_only=True)["global_step"]
                except Exception:  # being written: try again
                    step = -1
                if 4 <= step < steps_per_epoch * epochs - 4:
                    os.kill(proc.pid, signal.SIGKILL)
                    break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and time.time() >= deadline:
            proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    proc.stderr.close()
    at_kill = torch.load(last, weights_only=True)
    assert 0 < at_kill["global_step"] < steps_per_epoch * epochs
    assert not (killed / "metrics.json").exists()

    resumed = _cli(args(killed))  # the same command line
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "Restoring states from the checkpoint path" in resumed.stderr + resumed.stdout

    fresh = tmp_path / "fresh"
    cfg = compose_config(args(fresh))
    run(cfg)
    info_resumed = json.loads((killed / "run_info.json").read_text())
    info_fresh = json.loads((fresh / "run_info.json").read_text())
    assert info_resumed["global_step"] == info_fresh["global_step"] == steps_per_epoch * epochs
    # training cost: each trained image counted once (the batches redone after the kill replace the lost ones)
    assert info_resumed["train_images"] == info_fresh["train_images"] == 2 * steps_per_epoch * epochs
    for info in (info_resumed, info_fresh):
        assert info["train_seconds"] > 0 and info["peak_gpu_memory_gib"] is None and info["peak_rss_gib"] > 0.1
        assert info["train_images_per_second"] == pytest.approx(info["train_images"] / info["train_seconds"], rel=1e-3)
    end_resumed = torch.load(killed / "checkpoints" / "last.ckpt", weights_only=True)
    end_fresh = torch.load(fresh / "checkpoints" / "last.ckpt", weights_only=True)
    assert end_resumed["epoch"] == end_fresh["epoch"] == epochs - 1
    # the cosine schedule continued where it stopped: same final learning rate and scheduler step count
    assert end_resumed["lr_schedulers"][0]["last_epoch"] == end_fresh["lr_schedulers"][0]["last_epoch"]
    assert end_resumed["optimizer_states"][0]["param_groups"][0]["lr"] == pytest.approx(
        end_fresh["optimizer_states"][0]["param_groups"][0]["lr"]
    )
    _check_metrics_json(killed / "metrics.json")

    # the CSV log went on across the kill: every optimiser step and every epoch's validation exactly once,
    # the same rows as the uninterrupted run
    def log_rows(run_dir: Path) -> list[tuple[str, str, tuple[str, ...]]]:
        with open(run_dir / "csv" / "metrics.csv", newline="") as fh:
            return [
                (r["epoch"], r["step"], tuple(sorted(k for k, v in r.items() if v and k not in ("epoch", "step"))))
                for r in csv.DictReader(fh)
            ]

    rows_killed = log_rows(killed)
    train_steps = [int(s) for _, s, keys in rows_killed if "train/loss_step" in keys]
    assert train_steps == list(range(steps_per_epoch * epochs))
    assert sum("val/mae_mm" in keys for _, _, keys in rows_killed) == epochs
    assert rows_killed == log_rows(fresh)


def test_a_second_training_of_the_same_run_folder_is_refused_before_it_touches_it(tmp_path, data_cache, tiny):
    """issue 23 case 3: two trainings started with the same paths.run_dir both exited 0 and the folder ended
    holding only the second. The second is refused (exit 2, one line naming the lock and its holder) before it
    writes anything. The first is given far more epochs than the test needs, so it is surely still running when
    the second starts (a short first run could finish first on an idle machine), and is stopped afterwards."""
    run_dir = tmp_path / "run"
    first_args = tiny(run_dir, data_cache, num_samples=40) + ["trainer.max_epochs=10000", "logger=csv", "seed=0"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    first = subprocess.Popen(
        [sys.executable, "-m", "tofdenoise.cli.train", *first_args],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.time() + 120
        while not (run_dir / ".hydra" / "overrides.yaml").exists() and first.poll() is None:
            assert time.time() < deadline, "the first training did not start"
            time.sleep(0.05)
        assert first.poll() is None, first.stderr.read()[-3000:]
        hydra_before = {p.name: p.read_bytes() for p in (run_dir / ".hydra").iterdir()}
        second = _cli(tiny(run_dir, data_cache, num_samples=40) + ["trainer.max_epochs=1", "seed=1"])
        assert first.poll() is None  # the first was running during the whole attempt
        assert second.returncode == 2, second.stderr[-2000:]
        line = second.stderr.strip().splitlines()[-1]
        assert line.startswith("tofdenoise train: error: run folder") and str(run_dir / "run.lock") in line
        assert f"pid {first.pid} " in line
        # nothing of the second reached the first's folder
        assert {p.name: p.read_bytes() for p in (run_dir / ".hydra").iterdir()} == hydra_before
        assert "seed=0" in (run_dir / ".hydra" / "overrides.yaml").read_text()
    finally:
        first.terminate()
        first.communicate(timeout=120)


def _val_csv(run_dir: Path) -> list[tuple[int, float, float]]:
    with open(run_dir / "csv" / "metrics.csv") as fh:
        return [
            (int(r["epoch"]), float(r["val/mae_mm"]), float(r["val/raw/mae_mm"]))
            for r in csv.DictReader(fh)
            if r.get("val/mae_mm")
        ]


def test_ddp_two_cpu_processes(tmp_path, data_cache, tiny):
    """trainer=ddp with two CPU processes (Lightning re-launches the Hydra command for rank 1), on 3
    validation and 5 test images: the DistributedSampler pads each to an even count by repeating image 0.
    val/mae_mm (logged, picks best.ckpt), the learned fields, metrics.json (means, pooled MAE, counts) and the
    per-image CSV equal a single-process evaluation of the same checkpoints over the unique images. Before
    the fix the repeated image was counted twice (test images 6, wrong means)."""
    data = ["++data.split_ratios=[6,3,5]"]  # 14 scenes -> 6 train, 3 val, 5 test
    run_dir = tmp_path / "ddp"
    args = (
        tiny(run_dir, data_cache, num_samples=14)
        + data
        + [
            "trainer=ddp",
            "trainer.accelerator=cpu",
            "trainer.devices=2",
            "trainer.precision=32-true",
            "trainer.sync_batchnorm=false",
            "trainer.max_epochs=2",
            "logger=csv",
        ]
    )
    proc = _cli(args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ddp = _check_metrics_json(run_dir / "metrics.json")
    info = json.loads((run_dir / "run_info.json").read_text())
    # 6 training samples, batch 2 per process, 2 processes -> 1 step per epoch (drop_last)
    assert info["global_step"] == 2 * 1 == ddp["trained_steps"]
    assert ddp["synthetic"]["images"] == 5 and ddp["synthetic"]["skipped_images"] == 0
    rows = read_per_image_csv(run_dir / "per_image" / "synthetic.csv")
    assert [r["index"] for r in rows] == [0, 1, 2, 3, 4]
    assert ddp["synthetic"]["mae_mm"] == pytest.approx(sum(r["mae_mm"] for r in rows) / 5, rel=1e-12)
    assert ddp["synthetic"]["raw"]["mae_mm"] == pytest.approx(sum(r["raw_mae_mm"] for r in rows) / 5, rel=1e-12)
    assert ddp["synthetic"]["valid_px"] == sum(r["valid_px"] for r in rows)

    # test: one process, the same best.ckpt, the same 5 images
    single_dir = tmp_path / "single"
    run(
        compose_config(
            tiny(single_dir, data_cache, num_samples=14)
            + data
            + ["train=false", f"ckpt_path={run_dir / 'checkpoints' / 'best.ckpt'}", "logger=csv"]
        )
    )
    single = read_metrics_json(single_dir / "metrics.json")
    assert ddp["synthetic"] == single["synthetic"]  # every mean, pooled value and count, raw block included
    assert rows == read_per_image_csv(single_dir / "per_image" / "synthetic.csv")

    # validation: one process, the weights of the last epoch (last.ckpt), the same 3 images
    from hydra.utils import instantiate
    from lightning.pytorch import Trainer

    from tofdenoise.training.module import DepthRestorer

    cfg = compose_config(tiny(single_dir, data_cache, num_samples=14) + data)
    model = DepthRestorer.load_from_checkpoint(run_dir / "checkpoints" / "last.ckpt")
    trainer = Trainer(
        accelerator="cpu",
        devices=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    (val,) = trainer.validate(model, datamodule=instantiate(cfg.data, _convert_="all"))
    logged = _val_csv(run_dir)
    assert [e for e, _, _ in logged] == [0, 1]
    assert logged[-1][1] == pytest.approx(val["val/mae_mm"], rel=1e-6)  # logged as float32
    assert logged[-1][2] == pytest.approx(val["val/raw/mae_mm"], rel=1e-6)
    assert ddp["raw_val_mae_mm"] == pytest.approx(val["val/raw/mae_mm"], rel=1e-6)
    assert ddp["best_val_mae_mm"] == pytest.approx(min(m for _, m, _ in logged), rel=1e-6)


def _summary_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("WARNING: ")]


def test_max_epochs_0_is_recorded_as_not_trained(tmp_path, data_cache, tiny, capsys):
    """No training at all: metrics.json says learned false / not trained, the summary says so."""
    run(compose_config(tiny(tmp_path, data_cache) + ["trainer.max_epochs=0", "logger=csv"]))
    data = _check_metrics_json(tmp_path / "metrics.json")
    assert data["learned"] is False and data["trained_steps"] == 0 and learned_status(data) == "not trained"
    assert data["learned_reason"].startswith("not trained: 0 optimiser steps")
    warnings = _summary_lines(capsys.readouterr().out)
    assert warnings and all(w.startswith("WARNING: the network was not trained") for w in warnings)


def test_a_run_that_does_not_learn_is_flagged_and_a_test_of_its_checkpoint_too(tmp_path, data_cache, tiny, capsys):
    """One epoch at a learning rate far too small to move the weights: the best val MAE stays at the raw MAE,
    so learned is false with the numbers in the reason; testing the saved best.ckpt alone (train=false) takes
    the record from the checkpoint and says the same."""
    run_dir = tmp_path / "tiny-lr"
    run(
        compose_config(
            tiny(run_dir, data_cache)
            + [
                "trainer.max_epochs=1",
                "logger=csv",
                "++model.optim.lr=1e-12",
                "++model.optim.lr_min=0",
                "++model.optim.warmup_steps=0",
            ]
        )
    )
    data = _check_metrics_json(run_dir / "metrics.json")
    ((epoch, val_mae, raw_mae),) = _val_csv(run_dir)
    assert data["trained_steps"] == 3 == json.loads((run_dir / "run_info.json").read_text())["global_step"]
    assert data["best_val_mae_mm"] == pytest.approx(val_mae, rel=1e-6)
    assert data["raw_val_mae_mm"] == pytest.approx(raw_mae, rel=1e-6)
    assert data["best_val_mae_mm"] > 0.95 * data["raw_val_mae_mm"]
    assert data["learned"] is False and learned_status(data) == "did not learn"
    assert f"best val MAE {val_mae:.2f} mm vs raw {raw_mae:.2f} mm" in data["learned_reason"]
    warnings = _summary_lines(capsys.readouterr().out)
    assert warnings and warnings[-1] == f"WARNING: the network {data['learned_reason']}; treat this run as failed"

    test_dir = tmp_path / "test-only"
    run(
        compose_config(
            tiny(test_dir, data_cache)
            + [
                "train=false",
                f"ckpt_path={run_dir / 'checkpoints' / 'best.ckpt'}",
                "logger=csv",
                "++model.learned_margin=0.5",
            ]
        )
    )
    again = read_metrics_json(test_dir / "metrics.json")
    # best.ckpt is the last step here: the same record; the margin is the configured one
    assert {k: again[k] for k in ("trained_steps", "best_val_mae_mm", "raw_val_mae_mm", "learned")} == {
        k: data[k] for k in ("trained_steps", "best_val_mae_mm", "raw_val_mae_mm", "learned")
    }
    assert again["learned_margin"] == 0.5 and "50% below raw" in again["learned_reason"]
    assert _summary_lines(capsys.readouterr().out)[-1].startswith("WARNING: the network did not learn")


@pytest.mark.parametrize("backbone", ["unet", "tofkpn"])
def test_signal_channel_from_the_config_alone(backbone, tmp_path, data_cache, tiny):
    """`model.conditioning.use_signal_channel=true` is the only switch: the backbone configs leave in_channels to
    the module."""
    from tofdenoise.training.module import DepthRestorer

    cfg = compose_config(
        tiny(tmp_path, data_cache, backbone)
        + ["+trainer.fast_dev_run=true", "logger=csv", "++model.conditioning.use_signal_channel=true"]
    )
    assert "in_channels" not in cfg.backbone.kwargs
    run(cfg)
    data = _check_metrics_json(tmp_path / "metrics.json")
    assert data["synthetic"]["images"] == 1
    module = DepthRestorer(
        backbone=backbone, backbone_kwargs=dict(cfg.backbone.kwargs), conditioning={"use_signal_channel": True}
    )
    first_conv = next(m for m in module.backbone.modules() if isinstance(m, torch.nn.Conv2d))
    assert first_conv.in_channels == 2


#: intra-op threads of the reproducibility tests: a convolution's reductions are split by thread, so the count is
#: part of what makes two runs identical (docs/training.md, "Determinism")
DETERMINISM_THREADS = 2


@pytest.fixture
def fixed_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(DETERMINISM_THREADS)
    yield
    torch.set_num_threads(before)


def _tensors(state, prefix=""):
    """Every tensor of a nested state (an optimiser's), keyed by its path."""
    if isinstance(state, torch.Tensor):
        yield prefix, state
    elif isinstance(state, dict):
        for k, v in state.items():
            yield from _tensors(v, f"{prefix}/{k}")
    elif isinstance(state, (list, tuple)):
        for i, v in enumerate(state):
            yield from _tensors(v, f"{prefix}/{i}")


@pytest.mark.parametrize("backbone", ["unet", pytest.param("dvss", marks=pytest.mark.slow)])
def test_two_identical_runs_give_identical_metrics(backbone, tmp_path, tiny, fixed_threads):
    """Issue item 6 and issue 39: CPU training is bit-reproducible for a given machine and thread count: the same
    config twice gives byte-identical metrics and per-image values, weights, optimiser state and logged losses,
    also when the first run builds the data cache and the second reads it (cache building must not move any random
    stream). DVSS (slow) runs its native CPU scan kernel, threaded over its own blocks."""
    cache = tmp_path / "cache"  # empty: the first run builds it
    outs = []
    for name in ("a", "b"):
        cfg = compose_config(tiny(tmp_path / name, cache, backbone) + ["trainer.max_epochs=2", "logger=csv"])
        run(cfg)
        outs.append(tmp_path / name)
    a, b = (json.loads((d / "metrics.json").read_text()) for d in outs)
    assert a == b and a["trained_steps"] > 0
    assert (outs[0] / "per_image" / "synthetic.csv").read_text() == (
        outs[1] / "per_image" / "synthetic.csv"
    ).read_text()
    ca, cb = (torch.load(d / "checkpoints" / "last.ckpt", weights_only=True) for d in outs)
    ta, tb = ca["state_dict"], cb["state_dict"]
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)
    oa, ob = dict(_tensors(ca["optimizer_states"])), dict(_tensors(cb["optimizer_states"]))
    assert oa and oa.keys() == ob.keys() and all(torch.equal(oa[k], ob[k]) for k in oa)
    losses = []
    for d in outs:
        with open(d / "csv" / "metrics.csv") as fh:
            losses.append([{k: v for k, v in row.items() if k.startswith("train/")} for row in csv.DictReader(fh)])
    assert losses[0] == losses[1] and losses[0]


def test_run_info_names_the_commit_and_the_machine_that_made_it(tmp_path, tiny):
    """Issue 39: run_info.json carries the commit of the checkout the package runs from, with its dirty flag, and
    the machine it trained on (CPU, threads, torch, accelerator)."""
    cfg = compose_config(tiny(tmp_path, tmp_path / "cache") + ["+trainer.fast_dev_run=true", "logger=csv"])
    run(cfg)
    info = json.loads((tmp_path / "run_info.json").read_text())
    expected = code_commit()
    assert {k: info.get(k) for k in expected} == expected
    if expected["commit"] is not None:  # the tests run from a git checkout
        assert len(info["commit"]) == 40 and isinstance(info["commit_dirty"], bool)
    assert info["code_digest"] == code_digest()  # the code by its content, whatever git says
    machine = info["machine"]
    assert machine == {**host_machine(), **{k: machine[k] for k in ("torch", "torch_threads", "accelerator", "gpu")}}
    assert machine["torch"] == torch.__version__ and machine["torch_threads"] == torch.get_num_threads()
    assert machine["accelerator"] == "cpu" and machine["gpu"] is None


def test_a_bad_data_setting_is_one_line_naming_the_key_before_any_training(tmp_path):
    """An empty capture set (data.real_dir) or a signal route that cannot apply is reported in one line with exit
    status 2, before the trainer starts and before the run folder gets any file of a run."""
    empty = tmp_path / "empty_set"
    empty.mkdir()
    run_dir = tmp_path / "run"
    proc = _cli([f"++data.real_dir={empty}", f"paths.run_dir={run_dir}", "logger=csv"])
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith("tofdenoise train: error: data: capture set ") and "data.real_dir" in lines[-1]
    assert "Traceback" not in proc.stderr
    assert not (run_dir / "checkpoints").exists() and not (run_dir / "run_info.json").exists()
    proc = _cli(["++data.signal_route=photons", f"paths.run_dir={run_dir}", "logger=csv"])
    assert proc.returncode == 2 and "error: data: unknown data.signal_route 'photons'" in proc.stderr


@pytest.mark.parametrize(
    "override, message",
    [
        # validate_config: a name or a folder (was a traceback with exit 1)
        ("++backbone.name=nope", "config backbone.name: unknown backbone 'nope'; valid names: "),
        ("++data.source_kwargs.colour=1", "config data.source_kwargs.colour: not a setting of the procedural source"),
        ("++data.real_dir=/nonexistent/captures", "config data.real_dir: real capture folder /nonexistent/captures"),
        # a settings group of the model (was Hydra's wrapped error with exit 1)
        ("++model.optim.learning_rate=1", "model.optim.learning_rate: unknown setting; valid: lr, weight_decay"),
        ("++model.conditioning.centering=median", "model: conditioning.centering: unknown mode 'median'"),
    ],
)
def test_a_bad_setting_is_one_line_with_exit_2(tmp_path, override, message):
    run_dir = tmp_path / "run"
    proc = _cli([override, f"paths.run_dir={run_dir}", "logger=csv"])
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith(f"tofdenoise train: error: {message}"), lines[-1]
    assert "Traceback" not in proc.stderr
    assert not (run_dir / "checkpoints").exists()
