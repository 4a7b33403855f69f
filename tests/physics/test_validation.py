"""Noise-model validation (Sec. IV / Fig. 6): targets, outputs, metrics, real-capture input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tofdenoise.physics.calibrate import fit_range_sigma
from tofdenoise.physics.calibration import default_calibration
from tofdenoise.physics.capture_io import CaptureFormatError, write_capture_folder
from tofdenoise.physics.simulator import simulate_frames
from tofdenoise.physics.synthetic_captures import planar_signal_e, planar_tap_stack
from tofdenoise.physics.validation import (
    RANGE_DISTANCES_MM,
    ValidationSettings,
    mape_percent,
    r2_score,
    run_validation,
    write_validation,
)


def test_metrics_hand_computed():
    meas = np.array([1.0, 2.0, 4.0])
    pred = np.array([1.1, 1.8, 4.0])
    assert mape_percent(pred, meas) == pytest.approx(100 * (0.1 + 0.1 + 0.0) / 3)
    ss_res = 0.01 + 0.04
    ss_tot = np.sum((meas - meas.mean()) ** 2)
    assert r2_score(pred, meas) == pytest.approx(1 - ss_res / ss_tot)
    assert r2_score(meas, meas) == 1.0


def test_signal_falls_with_distance():
    assert planar_signal_e(500.0, 0.9) == pytest.approx(4 * planar_signal_e(1000.0, 0.9))
    assert planar_signal_e(1500.0, 0.2, 2.0) == pytest.approx(15000.0 * 0.2 * 2.0 / 2.25)


def test_quick_validation_meets_paper_figures(tmp_path):
    calib = default_calibration()
    result = run_validation(calib, ValidationSettings.quick())
    prop, rng = result.pooled["proposed"], result.pooled["range_gaussian"]
    assert prop["mape_percent"] <= 7.7 and prop["r2"] >= 0.93
    sig = result.panels["signal"]
    assert sig["range_gaussian"]["mape_percent"] > 3 * sig["proposed"]["mape_percent"]
    assert sig["range_gaussian"]["r2"] < 0.5 < sig["proposed"]["r2"]
    assert rng["mape_percent"] > prop["mape_percent"]
    # measured std rises with distance (signal falls as 1/D^2)
    r = sorted((c for c in result.conditions if c.group == "range"), key=lambda c: c.distance_mm)
    assert [c.distance_mm for c in r] == list(RANGE_DISTANCES_MM)
    assert r[-1].measured_std_mm > 3 * r[0].measured_std_mm
    json_path, png = write_validation(result, calib, tmp_path)
    data = json.loads(json_path.read_text())
    for key in ("proposed", "range_gaussian"):
        assert set(data["pooled"][key]) >= {"mape_percent", "r2"}
    groups = [c["group"] for c in data["conditions"]]
    assert groups.count("range") == 11 and groups.count("signal") == 12 and groups.count("range_fit") == 10
    for c in data["conditions"]:
        assert {
            "distance_mm",
            "surface",
            "exposure",
            "measured_std_mm",
            "proposed_std_mm",
            "range_gaussian_std_mm",
        } <= set(c)
        assert c["num_frames"] == 50 and c["num_pixels"] == 256
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_validation_from_capture_folder(tmp_path):
    calib = default_calibration()
    g = torch.Generator().manual_seed(0)
    stacks = []
    for i, d in enumerate((600.0, 1000.0, 1400.0)):
        a = float(planar_signal_e(d, 0.9))
        stacks.append((f"r{i}", planar_tap_stack(calib, d, a, 40, (8, 8), g), {"group": "range", "distance_mm": d}))
        stacks.append(
            (f"f{i}", planar_tap_stack(calib, d + 50, a, 40, (8, 8), g), {"group": "range_fit", "distance_mm": d + 50})
        )
    # a depth + amplitude stack (cameras that only export depth/amplitude)
    fr = simulate_frames(torch.full((8, 8), 1500.0), torch.full((8, 8), 3000.0), calib, 40, generator=g)
    stacks.append(
        (
            "sd",
            fr.depth_mm.numpy(),
            {"group": "signal", "distance_mm": 1500.0, "surface": "gray", "exposure": 1.0, "amplitude_file": "sa.npy"},
        )
    )
    folder = write_capture_folder(tmp_path / "val", "validation", 4, stacks)
    np.save(folder / "sa.npy", fr.amplitude.numpy())
    result = run_validation(calib, captures_dir=folder)
    assert result.source.startswith("captures")
    assert result.range_sigma_source.startswith("least squares")
    assert result.pooled["proposed"]["n"] == 4
    assert result.pooled["proposed"]["mape_percent"] < 15.0
    # a depth stack without amplitude is rejected with the file named
    index = json.loads((folder / "index.json").read_text())
    del index["stacks"][-1]["amplitude_file"]
    (folder / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="sd.npy.*amplitude_file"):
        run_validation(calib, captures_dir=folder)
    index["stacks"][0]["group"] = "other"
    (folder / "index.json").write_text(json.dumps(index))
    with pytest.raises(CaptureFormatError, match="group"):
        run_validation(calib, captures_dir=folder)


def test_written_validation_captures_measure_what_the_simulator_measures(tmp_path):
    """write_validation_captures records every condition of the experiment; read back through the captures path,
    the measured temporal std agrees with the in-memory simulation of the same camera and random streams."""
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.validation import condition_plan, write_validation_captures

    camera = resolve_calibration("cam75")
    settings = ValidationSettings(num_frames=40, roi_px=8)
    folder = write_validation_captures(camera, tmp_path / "val", settings)
    index = json.loads((folder / "index.json").read_text())
    plan = condition_plan()
    assert index["kind"] == "validation" and index["num_taps"] == camera.num_taps
    assert [(e["group"], e["distance_mm"], e["surface"], e["exposure"]) for e in index["stacks"]] == [
        (c.group, c.distance_mm, c.surface, c.exposure) for c, _, _ in plan
    ]
    assert len(plan) == 11 + 12 + 10
    captured = run_validation(camera, captures_dir=folder)
    simulated = run_validation(camera, settings)
    got = {(c.group, c.distance_mm, c.surface, c.exposure): c.measured_std_mm for c in captured.conditions}
    want = {(c.group, c.distance_mm, c.surface, c.exposure): c.measured_std_mm for c in simulated.conditions}
    assert got.keys() == want.keys()
    for key in got:
        assert got[key] == pytest.approx(want[key], rel=0.02), key
    assert captured.pooled["proposed"]["mape_percent"] < 5.0


def test_captures_of_another_modulation_frequency_are_refused_not_reported_as_a_model_failure(tmp_path):
    """Captures whose index declares another frequency than the calibration's were decoded at the calibration's: a
    75 MHz set validated against 50 MHz gave MAPE 77 % for a model that fits it within 1 %. Refused, both named."""
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.validation import write_validation_captures

    camera = resolve_calibration("cam75")
    folder = write_validation_captures(camera, tmp_path / "val", ValidationSettings(num_frames=20, roi_px=6))
    assert json.loads((folder / "index.json").read_text())["modulation_frequency_hz"] == camera.modulation_frequency_hz
    other = resolve_calibration(None)
    assert other.modulation_frequency_hz != camera.modulation_frequency_hz
    with pytest.raises(
        ValueError, match=r"index.json: modulation_frequency_hz=7\.5e\+07 but the calibration has 5e\+07"
    ):
        run_validation(other, captures_dir=folder)
    assert run_validation(camera, captures_dir=folder).settings == {"captures": str(folder)}


def _three_tap_camera(full_well_e: float):
    """The audit's 3-tap camera (cam3_cal.yaml): 30 MHz, c(x) = 1 + 0.6 cos x + 0.05 cos 2x + 0.1 sin x,
    dark 500 e- / 20 e-. A 0.9 planar target returns a = 15000 x 0.9 (1000 / D)^2 e-; its brightest tap is
    max_n a c(psi - theta_n) + 500 e- (hand-computed below from these numbers)."""
    from tofdenoise.physics.calibration import TapResponse

    return default_calibration().replace(
        num_taps=3,
        modulation_frequency_hz=30e6,
        tap_response=TapResponse(1.0, (0.6, 0.05, 0.0), (0.1, 0.0, 0.0)),
        dark_mean_e=500.0,
        dark_std_e=20.0,
        full_well_e=full_well_e,
        adc_gain_e_per_dn=2.0,
        range_sigma_mm=None,
    )


def test_saturated_conditions_are_left_out_of_the_range_fit_named_and_the_record_is_strict_json(tmp_path):
    """Full well 60 ke-: the brightest tap at 500 mm (range panel, 84.7 ke-) and 550 mm (range-fit sequence,
    69.0 ke-) is above it in every frame, at 600 mm (57.1 ke-) and 650 mm (47.8 ke-) below it. The fit was NaN
    (alpha = [nan, nan, nan], range MAPE / R^2 nan, 48 NaN tokens in validation.json); now the 550 mm condition is
    left out of the fit as the 500 mm one is of the metrics, both named, and the fit is the least squares of the
    other nine distances."""
    calib = _three_tap_camera(60000.0)
    result = run_validation(calib, ValidationSettings(num_frames=20, roi_px=6))
    empty = {(c.group, c.distance_mm) for c in result.conditions if c.num_pixels == 0}
    assert empty == {("range", 500.0), ("range_fit", 550.0)}
    assert [(c["group"], c["distance_mm"]) for c in result.left_out] == [("range", 500.0), ("range_fit", 550.0)]
    fit = [c for c in result.conditions if c.group == "range_fit" and c.num_pixels > 0]
    assert len(fit) == 9
    want = fit_range_sigma([c.distance_mm for c in fit], [c.measured_std_mm for c in fit])
    np.testing.assert_allclose(result.range_sigma_mm, want, rtol=1e-12)
    assert "9 of 10 distances" in result.range_sigma_source and "550 mm" in result.range_sigma_source
    assert result.pooled["proposed"]["n"] == result.pooled["range_gaussian"]["n"] == 22
    for metrics in [result.pooled, *result.panels.values()]:
        for m in metrics.values():
            assert np.isfinite(m["mape_percent"]) and np.isfinite(m["r2"])
    json_path, _ = write_validation(result, calib, tmp_path)

    def refuse(token):
        raise AssertionError(f"validation.json holds {token}: not strict JSON")

    data = json.loads(json_path.read_text(), parse_constant=refuse)
    assert [c["distance_mm"] for c in data["left_out"]] == [500.0, 550.0]
    row = next(c for c in data["conditions"] if c["group"] == "range_fit" and c["distance_mm"] == 550.0)
    assert row["num_pixels"] == 0 and row["measured_std_mm"] is None and row["proposed_std_mm"] is None


def test_a_range_fit_sequence_left_with_too_few_distances_is_an_error_naming_them():
    """Full well 12.5 ke-: only 1350 and 1450 mm of the range-fit sequence stay below it (brightest tap 12.0 / 10.7
    ke-; 1250 mm: 13.4 ke-): two distances cannot fit three coefficients."""
    calib = _three_tap_camera(12500.0)
    with pytest.raises(ValueError, match=r"2 of the 10 'range_fit' conditions .* left out: 550 mm, 650 mm.*1250 mm\)"):
        run_validation(calib, ValidationSettings(num_frames=10, roi_px=4))


def test_strict_json_replaces_non_finite_numbers():
    from tofdenoise.physics.validation import strict_json

    got = strict_json({"a": [1.0, float("nan"), np.float32("inf")], "b": (np.int64(3), "x", None), "c": -np.inf})
    assert got == {"a": [1.0, None, None], "b": [3, "x", None], "c": None}
    assert json.dumps(got, allow_nan=False)
