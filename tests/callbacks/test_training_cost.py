"""TrainingCost: training time without validation, summed over a resume; images; peak memory."""

from __future__ import annotations

import pytest
import torch

import tofdenoise.callbacks.training_cost as training_cost
from tofdenoise.callbacks.training_cost import TrainingCost, peak_rss_gib


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class _Module:
    device = torch.device("cpu")


class _Trainer:
    world_size = 1


def _batch(n: int) -> dict:
    return {"noisy": torch.zeros(n, 1, 4, 4)}


def test_time_excludes_validation_and_a_resume_adds_to_the_checkpointed_state(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(training_cost.time, "perf_counter", clock)
    trainer, module = _Trainer(), _Module()
    cost = TrainingCost()
    # epoch 0: 0 -> 10 s with a validation from 5 to 7 s; three batches of 4
    cost.on_train_epoch_start(trainer, module)
    for i in range(3):
        cost.on_train_batch_start(trainer, module, _batch(4), i)
    clock.now = 5.0
    cost.on_validation_start(trainer, module)
    clock.now = 7.0
    cost.on_validation_end(trainer, module)
    clock.now = 10.0
    cost.on_train_epoch_end(trainer, module)
    assert cost.seconds == pytest.approx(8.0) and cost.images == 12
    # epoch 1: a checkpoint at 13 s, during a validation that started at 12 s (1 s of it so far)
    cost.on_train_epoch_start(trainer, module)
    cost.on_train_batch_start(trainer, module, _batch(2), 0)
    clock.now = 12.0
    cost.on_validation_start(trainer, module)
    clock.now = 13.0
    state = cost.state_dict()
    assert state["seconds"] == pytest.approx(10.0) and state["images"] == 14  # 8 + (13 - 10 - 1)
    # killed; the resumed attempt starts from the checkpoint: the stop (13 -> 100 s) is not counted
    resumed = TrainingCost()
    resumed.load_state_dict(state)
    clock.now = 100.0
    resumed.on_train_epoch_start(trainer, module)
    resumed.on_train_batch_start(trainer, module, _batch(2), 1)
    clock.now = 104.0
    resumed.on_train_epoch_end(trainer, module)
    resumed.on_train_end(trainer, module)
    summary = resumed.summary()
    assert summary["train_seconds"] == pytest.approx(14.0) and summary["train_images"] == 16
    assert summary["train_images_per_second"] == pytest.approx(16 / 14, rel=1e-3)
    assert summary["peak_gpu_memory_gib"] is None and summary["peak_rss_gib"] == pytest.approx(peak_rss_gib(), rel=0.05)


def test_ddp_counts_every_process_and_an_empty_run_has_no_rate():
    cost = TrainingCost()
    cost.on_train_epoch_start(type("T", (), {"world_size": 4})(), _Module())
    cost.on_train_batch_start(None, _Module(), _batch(3), 0)
    assert cost.summary()["train_images"] == 12  # 3 per process x 4 processes
    assert TrainingCost().summary()["train_images_per_second"] is None


def test_peak_rss_is_this_process_in_gib():
    big = torch.ones(64 * 1024 * 1024, dtype=torch.uint8)  # 64 MiB touched
    big += 1
    assert 0.06 < peak_rss_gib() < 24.0


def test_the_recorded_rate_is_computed_from_the_recorded_seconds():
    """A short run's seconds are rounded to 1 ms in run_info.json; the rate must agree with them, not with the
    unrounded time (0.44104 s -> 0.441 s: 0.01 % apart, beyond a reader's images / seconds check)."""
    cost = TrainingCost()
    cost.seconds, cost.images = 0.44104, 48
    summary = cost.summary()
    assert summary["train_seconds"] == 0.441
    assert summary["train_images_per_second"] == pytest.approx(48 / 0.441, rel=1e-5)  # rate rounded to 1e-3
