"""metrics.json / per-image CSV writers: schema, strict JSON, atomicity, round trips."""

from __future__ import annotations

import json
import math

import pytest
import torch

from tofdenoise.records import (
    RUN_KEYS,
    classical_verdict,
    learned_status,
    learned_verdict,
    metric_sets,
    read_metrics_json,
    read_per_image_csv,
    run_fields,
    set_entry,
    write_metrics_json,
    write_per_image_csv,
)
from tofdenoise.training.metrics import DepthMetrics


def _metric(offset_mm: float) -> DepthMetrics:
    ref = torch.full((2, 1, 8, 8), 1000.0)
    pred = ref + torch.tensor([offset_mm, 2 * offset_mm]).view(2, 1, 1, 1)
    m = DepthMetrics()
    m.update(pred, ref, torch.ones_like(ref), index=torch.tensor([3, 1]))
    return m


def test_metrics_json_schema_from_depth_metrics(tmp_path):
    restored, raw = _metric(1.0), _metric(10.0)
    entry = set_entry(restored.compute(), raw.compute(), counts=restored.counts())
    path = write_metrics_json(tmp_path / "run" / "metrics.json", {"synthetic": entry}, run=learned_verdict(5, 1.5, 15))
    data = json.loads(path.read_text())
    syn = data["synthetic"]
    assert set(syn) >= {"psnr_db", "mae_mm", "mse_mm2", "ssim", "raw", "mae_mm_pooled", "images"}
    assert syn["mae_mm"] == pytest.approx(1.5)
    assert syn["raw"]["mae_mm"] == pytest.approx(15.0)
    assert syn["raw"]["mse_mm2"] == pytest.approx((100 + 400) / 2)
    assert syn["images"] == 2
    assert read_metrics_json(path) == data
    assert not [p for p in path.parent.iterdir() if p.name != "metrics.json"]  # no temp files left


def test_nan_and_inf_are_strict_json(tmp_path):
    entry = set_entry(
        {"psnr_db": math.inf, "mae_mm": 0.0, "mse_mm2": 0.0, "ssim": 1.0},
        {"psnr_db": float("nan"), "mae_mm": float("nan"), "mse_mm2": float("nan"), "ssim": None},
    )
    path = write_metrics_json(tmp_path / "m.json", {"synthetic": entry}, run=learned_verdict(0, None, None))
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    assert data["synthetic"]["psnr_db"] == "inf"
    assert data["synthetic"]["raw"]["mae_mm"] is None


def test_bad_schema_is_rejected_with_the_key_named(tmp_path):
    with pytest.raises(KeyError, match="ssim"):
        set_entry({"psnr_db": 1.0, "mae_mm": 1.0, "mse_mm2": 1.0})
    bad = tmp_path / "bad.json"
    fields = learned_verdict(5, 1.0, 2.0)
    bad.write_text(json.dumps({"synthetic": {"psnr_db": 1, "mae_mm": 1, "mse_mm2": "x", "ssim": 1}, **fields}))
    with pytest.raises(ValueError, match=r"synthetic\.mse_mm2"):
        read_metrics_json(bad)
    # every record carries the learned guard's verdict: a file without it is refused, the fields named
    bad.write_text(json.dumps({"synthetic": {"psnr_db": 1, "mae_mm": 1, "mse_mm2": 1, "ssim": 1}, "learned": True}))
    with pytest.raises(ValueError, match=r"bad.json: lacks the run-level field\(s\) \['trained_steps'"):
        read_metrics_json(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad.json"):
        read_metrics_json(bad)


def test_per_image_csv_with_raw_and_names_round_trip(tmp_path):
    restored, raw = _metric(1.0), _metric(10.0)
    path = write_per_image_csv(
        tmp_path / "csv" / "test_synthetic.csv",
        restored.per_image_rows(),
        raw_rows=raw.per_image_rows(),
        names={1: "scene_b", 3: "scene_d"},
    )
    rows = read_per_image_csv(path)
    assert [r["index"] for r in rows] == [1, 3]
    assert [r["name"] for r in rows] == ["scene_b", "scene_d"]
    assert rows[0]["mae_mm"] == pytest.approx(2.0) and rows[1]["mae_mm"] == pytest.approx(1.0)
    assert rows[0]["raw_mae_mm"] == pytest.approx(20.0)
    assert rows[1]["psnr_db"] == pytest.approx(60.0)
    assert rows[0]["valid_px"] == 64


def test_per_image_csv_requires_matching_raw_rows(tmp_path):
    rows = _metric(1.0).per_image_rows()
    with pytest.raises(ValueError, match="no raw row for image index"):
        write_per_image_csv(tmp_path / "x.csv", rows, raw_rows=rows[:1])


# ------------------------------------------------------------------------------------------ learned guard
@pytest.mark.parametrize(
    "steps, best, raw, margin, learned, status",
    [
        (100, 9.5, 10.0, 0.05, True, "learned"),  # exactly (1 - 0.05) x 10 = 9.5: on the boundary counts
        (100, 9.51, 10.0, 0.05, False, "did not learn"),
        (100, 7.68, 7.79, 0.05, False, "did not learn"),  # the DVSS run of issue 9: 7.68 > 7.4005
        (100, 2.24, 7.79, 0.05, True, "learned"),
        (100, 7.0, 7.79, 0.10, True, "learned"),  # 7.0 <= 0.9 x 7.79 = 7.011
        (100, 7.02, 7.79, 0.10, False, "did not learn"),
        (100, 8.0, 7.79, 0.0, False, "did not learn"),  # margin 0: only "not worse than raw" is asked
        (100, 7.79, 7.79, 0.0, True, "learned"),
        (0, 1.0, 7.79, 0.05, False, "not trained"),  # no optimiser step: never learned, whatever the MAEs
        (None, None, None, 0.05, False, "not trained"),
        (5, None, 7.79, 0.05, False, "not verified"),  # no validation ran
        (5, 2.0, float("nan"), 0.05, False, "not verified"),
    ],
)
def test_learned_verdict_hand_computed_cases(steps, best, raw, margin, learned, status):
    v = learned_verdict(steps, best, raw, margin)
    assert v["learned"] is learned
    assert learned_status(v) == status
    assert v["learned_reason"].startswith(status)
    assert v["trained_steps"] == (steps or 0) and v["learned_margin"] == margin
    assert set(v) == set(RUN_KEYS)


def test_learned_verdict_reason_in_plain_words():
    v = learned_verdict(89, 7.68, 7.79)
    assert v["learned_reason"] == "did not learn: best val MAE 7.68 mm vs raw 7.79 mm (needs <= 7.40 mm, 5% below raw)"
    assert learned_verdict(0, None, None)["learned_reason"].startswith("not trained: 0 optimiser steps")
    v = learned_verdict(10, torch.tensor(2.0), torch.tensor(8.0))  # tensors (a checkpoint's best score) are fine
    assert v["best_val_mae_mm"] == 2.0 and v["learned"] is True
    with pytest.raises(ValueError, match="margin"):
        learned_verdict(1, 1.0, 2.0, margin=1.0)


def test_metrics_json_carries_the_run_fields(tmp_path):
    path = tmp_path / "metrics.json"
    entry = set_entry(_metric(1.0).compute(), _metric(4.0).compute())
    write_metrics_json(path, {"synthetic": entry}, run=learned_verdict(0, None, None))
    data = json.loads(path.read_text())
    assert data["learned"] is False and data["trained_steps"] == 0 and data["best_val_mae_mm"] is None
    assert list(metric_sets(data)) == ["synthetic"]
    assert run_fields(data) == learned_verdict(0, None, None)
    assert read_metrics_json(path) == data
    with pytest.raises(KeyError, match="unknown run-level"):
        write_metrics_json(path, {"synthetic": entry}, run={"learnt": True})
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**data, "learned": "no"}))
    with pytest.raises(ValueError, match="'learned' must be bool"):
        read_metrics_json(bad)
    bad.write_text(json.dumps({"learned": False}))  # run fields alone: no test set
    with pytest.raises(ValueError, match="non-empty"):
        read_metrics_json(bad)


def test_classical_verdict_is_its_own_status_not_a_failure(tmp_path):
    v = classical_verdict(4.1, 7.2)
    assert set(v) == set(RUN_KEYS) and v["method_kind"] == "classical"
    assert v["trained_steps"] == 0 and v["learned"] is False and learned_status(v) == "classical"
    assert v["best_val_mae_mm"] == 4.1 and v["raw_val_mae_mm"] == 7.2
    assert v["learned_reason"] == (
        "classical method: no trainable parameters, nothing learned; parameters tuned on "
        "the validation split: val MAE 4.10 mm vs raw 7.20 mm (below 6.84 mm, 5% below raw)"
    )
    assert "NOT below 6.84 mm" in classical_verdict(7.0, 7.2)["learned_reason"]
    assert "no validation result" in classical_verdict(None, 7.2)["learned_reason"]
    assert learned_verdict(0, None, None)["method_kind"] == "network"
    # the same 0 steps without method_kind are an untrained network (files written before the field existed)
    old = {k: x for k, x in v.items() if k != "method_kind"}
    assert learned_status(old) == "not trained"
    path = tmp_path / "metrics.json"
    entry = set_entry(_metric(1.0).compute(), _metric(4.0).compute())
    write_metrics_json(path, {"synthetic": entry}, run=v)
    assert run_fields(read_metrics_json(path)) == v
    bad = json.loads(path.read_text())
    bad["method_kind"] = "magic"
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"metrics.json: 'method_kind' must be one of \['network', 'classical'\]"):
        read_metrics_json(path)
