"""SensorCalibration / TapResponse: field names, validation errors, round trips, resolve."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
import yaml

from tofdenoise.paths import CONFIG_DIR, REPO_ROOT
from tofdenoise.physics.calibration import (
    FIELDS,
    OPTIONAL_FIELDS,
    CalibrationError,
    SensorCalibration,
    TapResponse,
    default_calibration,
    load_calibration,
    resolve_calibration,
    save_calibration,
)


def test_paths_point_at_repo():
    assert (REPO_ROOT / "pyproject.toml").is_file()
    assert CONFIG_DIR == REPO_ROOT / "configs"
    assert (CONFIG_DIR / "sensor" / "default.yaml").is_file()


def test_default_calibration_is_physically_sensible():
    c = default_calibration()
    assert c.num_taps >= 3
    assert c.tap_response.contrast < 1.0  # modulation contrast below 1
    assert c.dark_std_e > 0 and c.dark_mean_e > 0  # dark/ambient floor
    assert c.unambiguous_range_mm > 2500.0
    assert (
        c.signal_max_e * (c.tap_response.c0 + sum(abs(v) for v in c.tap_response.cos)) + c.dark_mean_e < c.full_well_e
    )
    assert c.range_sigma_mm is not None and len(c.range_sigma_mm) == 3


def test_unambiguous_range_closed_form():
    c = default_calibration().replace(modulation_frequency_hz=60e6)
    assert c.unambiguous_range_mm == pytest.approx(299792458.0 / (2 * 60e6) * 1000.0, rel=1e-12)
    assert c.phase_per_mm * c.unambiguous_range_mm == pytest.approx(2 * math.pi)


def test_tap_response_value_and_derivative_numpy_torch():
    tr = TapResponse(c0=1.0, cos=(0.5, 0.02, 0.01), sin=(0.1, 0.0, -0.02))
    x = np.linspace(-3, 9, 101)
    expected = (
        1.0 + 0.5 * np.cos(x) + 0.1 * np.sin(x) + 0.02 * np.cos(2 * x) + 0.01 * np.cos(3 * x) - 0.02 * np.sin(3 * x)
    )
    np.testing.assert_allclose(tr.value(x), expected, rtol=1e-12)
    h = 1e-6
    np.testing.assert_allclose(tr.derivative(x), (tr.value(x + h) - tr.value(x - h)) / (2 * h), atol=1e-7)
    xt = torch.tensor(x, dtype=torch.float64)
    assert isinstance(tr.value(xt), torch.Tensor)
    np.testing.assert_allclose(tr.derivative(xt).numpy(), tr.derivative(x), rtol=1e-12)
    # tap_matrices reproduce c(psi - theta_n)
    R, G, theta, _ = tr.tap_matrices(5)
    psi = np.array([0.3, 2.0, 5.5])
    h_feat = np.concatenate([np.cos(np.outer(psi, [1, 2, 3])), np.sin(np.outer(psi, [1, 2, 3]))], axis=1)
    np.testing.assert_allclose(h_feat @ R + 1.0, tr.value(psi[:, None] - theta[None, :]), rtol=1e-12)
    np.testing.assert_allclose(h_feat @ G, tr.derivative(psi[:, None] - theta[None, :]), atol=1e-12)


def test_to_dict_field_names_and_roundtrip(tmp_path):
    c = default_calibration()
    d = c.to_dict()
    # the optional fields appear only when set (calibrations written before them keep their fingerprints)
    assert tuple(d) == tuple(f for f in FIELDS if f in d)
    assert set(FIELDS) - set(d) <= set(OPTIONAL_FIELDS)
    assert "signal_at_1m_e" in d and "fixed_pattern" not in d
    assert set(d["tap_response"]) == {"c0", "cos", "sin"}
    for suffix in (".yaml", ".json", ".yml"):
        p = save_calibration(c, tmp_path / f"calib{suffix}")
        back = load_calibration(p)
        assert back == c
        assert back.fingerprint() == c.fingerprint()
    assert json.loads((tmp_path / "calib.json").read_text())["num_taps"] == c.num_taps
    assert c.replace(dark_std_e=10.0).fingerprint() != c.fingerprint()
    assert len(c.fingerprint()) == 64


@pytest.mark.parametrize(
    "field,value,needle",
    [
        ("num_taps", 2, "num_taps"),
        ("num_taps", 3.5, "num_taps"),
        ("modulation_frequency_hz", -1.0, "modulation_frequency_hz"),
        ("dark_std_e", 0.0, "dark_std_e"),
        ("dark_mean_e", -5.0, "dark_mean_e"),
        ("signal_max_e", 10.0, "signal_max_e"),
        ("full_well_e", "lots", "full_well_e"),
        ("adc_gain_e_per_dn", 0.0, "adc_gain_e_per_dn"),
        ("range_sigma_mm", [1.0, 2.0], "range_sigma_mm"),
        ("tap_response", {"c0": 1.0, "cos": [2.0], "sin": [0.0]}, "tap_response"),
        ("tap_response", {"c0": 1.0, "cos": [0.5], "sin": [0.0, 0.1]}, "tap_response"),
        ("tap_response", {"c0": 1.0, "cos": [0.5]}, "tap_response.sin"),
    ],
)
def test_out_of_range_fields_name_the_field(tmp_path, field, value, needle):
    d = default_calibration().to_dict()
    d[field] = value
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(CalibrationError, match=needle) as info:
        load_calibration(p)
    assert str(p) in str(info.value)


def test_missing_and_unknown_fields():
    d = default_calibration().to_dict()
    del d["dark_mean_e"]
    with pytest.raises(CalibrationError, match="dark_mean_e"):
        SensorCalibration.from_dict(d, source="x")
    d = default_calibration().to_dict()
    d["dark_meen_e"] = 1.0
    with pytest.raises(CalibrationError, match="dark_meen_e"):
        SensorCalibration.from_dict(d)
    d = default_calibration().to_dict()
    d["_target_"] = "ignored"  # Hydra-style private keys are ignored
    del d["range_sigma_mm"], d["adc_gain_e_per_dn"]  # optional fields
    c = SensorCalibration.from_dict(d)
    assert c.range_sigma_mm is None and c.adc_gain_e_per_dn is None


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_calibration(tmp_path / "nope.yaml")
    with pytest.raises(CalibrationError, match="suffix|end in"):
        load_calibration(tmp_path / "calib.txt")
    p = tmp_path / "broken.json"
    p.write_text("{not json")
    with pytest.raises(CalibrationError, match="broken.json"):
        load_calibration(p)


def test_resolve_calibration_specs(tmp_path):
    from omegaconf import OmegaConf

    c = default_calibration()
    assert resolve_calibration(None) == c
    assert resolve_calibration(c) is c
    assert resolve_calibration(c.to_dict()) == c
    assert resolve_calibration(OmegaConf.create(c.to_dict())) == c
    assert resolve_calibration("default") == c
    p = save_calibration(c.replace(num_taps=5), tmp_path / "five.json")
    assert resolve_calibration(str(p)).num_taps == 5
    with pytest.raises(CalibrationError):
        resolve_calibration(3.0)


def test_a_range_baseline_that_is_not_positive_is_refused_naming_the_field():
    c = default_calibration()
    with pytest.raises(CalibrationError, match=r"field 'range_sigma_mm' \[-3.0, 0.0, 0.0\] gives sigma\(D\)"):
        c.replace(range_sigma_mm=[-3, 0, 0])
    with pytest.raises(CalibrationError, match="<= 0 at D = 1416 mm"):  # positive near, negative far (sqrt(2e6))
        c.replace(range_sigma_mm=[2.0, 0.0, -1e-6])
    assert c.replace(range_sigma_mm=[0.5, 0.001, 0.0]).range_sigma_mm == (0.5, 0.001, 0.0)


def test_a_calibration_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "latin1.yaml"
    text = (CONFIG_DIR / "sensor" / "default.yaml").read_text(encoding="utf-8")
    path.write_bytes(("# caméra\n" + text).encode("latin-1", errors="replace"))
    with pytest.raises(CalibrationError, match=rf"{re.escape(str(path))}: not UTF-8 text \(byte 0xe9"):
        load_calibration(path)


def test_a_misspelt_field_is_named_with_the_closest_valid_one():
    """A typo is an unknown field and a missing one: both are named, the unknown one with the field it was meant
    to be (issue 41: only the missing field was named), also inside tap_response and fixed_pattern."""
    from tofdenoise.physics.calibration import CalibrationError, SensorCalibration, default_calibration

    d = default_calibration().to_dict()
    d["dark_stdev_e"] = d.pop("dark_std_e")
    with pytest.raises(CalibrationError) as info:
        SensorCalibration.from_dict(d, source="cam.yaml")
    assert str(info.value).startswith(
        "cam.yaml: unknown field 'dark_stdev_e' (did you mean 'dark_std_e'?); missing field(s) ['dark_std_e']"
    )
    d = default_calibration().to_dict()
    d["tap_response"]["cosine"] = d["tap_response"].pop("cos")
    with pytest.raises(
        CalibrationError, match=r"unknown field 'tap_response.cosine' \(did you mean 'tap_response.cos'"
    ):
        SensorCalibration.from_dict(d, source="cam.yaml")
    d = default_calibration().to_dict()
    d["fixed_pattern"] = {"prnu_": 0.01}
    with pytest.raises(
        CalibrationError, match=r"unknown field 'fixed_pattern.prnu_' \(did you mean 'fixed_pattern.prnu'"
    ):
        SensorCalibration.from_dict(d, source="cam.yaml")
