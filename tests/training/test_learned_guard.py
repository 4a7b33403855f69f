"""The learned guard's inputs: which record a verdict is judged on, and the checkpoint round trip."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from tofdenoise.training.learned_guard import LEARNED_RECORD_KEY, LearnedGuard, MissingGuardRecordError
from tofdenoise.training.metrics import FixedBatchCache


def _trainer(steps: int, best_score: float | None = None):
    cb = SimpleNamespace(
        best_model_score=None if best_score is None else torch.tensor(best_score), monitor="val/mae_mm"
    )
    return SimpleNamespace(global_step=steps, checkpoint_callback=cb)


def test_verdict_inputs_come_from_the_fit_then_the_checkpoint_then_nothing():
    guard = LearnedGuard()
    assert guard.inputs(None) == {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None}
    assert guard.verdict(True, 0.05, None)["learned"] is False

    loaded = LearnedGuard()
    loaded.load({LEARNED_RECORD_KEY: {"trained_steps": 40, "best_val_mae_mm": 3.0, "raw_val_mae_mm": 9.0}})
    assert loaded.inputs(None)["trained_steps"] == 40
    assert loaded.verdict(True, 0.05, None)["learned"] is True  # 3.0 <= 0.95 x 9.0

    guard.start_fit()
    guard.observe_validation(5.0, 9.0)
    guard.observe_validation(math.nan, 9.0)  # a non-finite epoch leaves the lowest MAE alone
    guard.observe_validation(4.0, 9.0)
    guard.observe_validation(6.0, 9.0)
    trainer = _trainer(12)
    assert guard.inputs(trainer) == {"trained_steps": 12, "best_val_mae_mm": 4.0, "raw_val_mae_mm": 9.0}
    guard.end_fit(trainer)
    trainer.global_step = 99  # frozen at the end of the fit
    assert guard.inputs(trainer)["trained_steps"] == 12
    # 8.56 mm is not 5 % below 9 mm
    guard2 = LearnedGuard()
    guard2.start_fit()
    guard2.observe_validation(8.56, 9.0)
    assert guard2.verdict(True, 0.05, _trainer(5))["learned"] is False


def test_live_record_falls_back_to_the_checkpoint_callback_score_and_round_trips():
    guard = LearnedGuard()
    guard.start_fit()
    ckpt: dict = {}
    guard.save(ckpt, _trainer(7, best_score=2.5))
    assert ckpt[LEARNED_RECORD_KEY] == {"trained_steps": 7, "best_val_mae_mm": 2.5, "raw_val_mae_mm": None}
    resumed = LearnedGuard()
    resumed.load(ckpt)
    assert resumed.best_val_mae_mm == 2.5 and resumed.inputs(None)["trained_steps"] == 7


def test_a_checkpoint_without_the_record_is_refused_by_name():
    with pytest.raises(MissingGuardRecordError, match=LEARNED_RECORD_KEY):
        LearnedGuard().load({"state_dict": {}})


def test_classical_filters_are_judged_on_their_tuning():
    guard = LearnedGuard()
    guard.record_tuning(2.6, 7.5)
    v = guard.verdict(False, 0.05, None)
    assert v["method_kind"] == "classical" and v["best_val_mae_mm"] == 2.6 and v["learned"] is False


def test_fixed_batch_cache_recomputes_only_when_the_batch_changes():
    calls = []
    batch = {k: torch.ones(1, 1, 4, 4) for k in ("noisy", "clean", "mask")}
    cache = FixedBatchCache()

    def compute():
        calls.append(1)
        return len(calls)

    assert cache.get(0, batch, compute) == 1
    assert cache.get(0, batch, compute) == 1  # same batch at the same position: stored value
    assert cache.get(1, batch, compute) == 2  # another position
    changed = {**batch, "noisy": batch["noisy"] * 2}
    assert cache.get(0, changed, compute) == 3
