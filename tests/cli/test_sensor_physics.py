"""`tofdenoise sensor` physics sub-commands: show-calib, sigma, calibrate, validate."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from tofdenoise.cli import sensor_physics
from tofdenoise.physics.calibration import default_calibration, load_calibration, save_calibration
from tofdenoise.physics.uncertainty import sigma_depth_mm


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="tofdenoise sensor")
    sensor_physics.add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_show_calib_json_field_names(capsys):
    assert run(["show-calib", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert list(data) == [
        "num_taps",
        "modulation_frequency_hz",
        "tap_response",
        "dark_mean_e",
        "dark_std_e",
        "signal_min_e",
        "signal_max_e",
        "full_well_e",
        "adc_gain_e_per_dn",
        "range_sigma_mm",
        "signal_at_1m_e",
        "vignetting_cos_power",
    ]
    assert list(data["tap_response"]) == ["c0", "cos", "sin"]
    assert data == default_calibration().to_dict()
    assert isinstance(data["range_sigma_mm"], list) and len(data["range_sigma_mm"]) == 3


def test_show_calib_file_and_text(tmp_path, capsys):
    p = save_calibration(default_calibration().replace(num_taps=6, range_sigma_mm=None), tmp_path / "c.json")
    assert run(["show-calib", "--sensor", str(p), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["num_taps"] == 6 and data["range_sigma_mm"] is None
    assert run(["show-calib", "--sensor", str(p)]) == 0
    assert "unambiguous range" in capsys.readouterr().out


def test_sigma_pairs_elementwise(capsys):
    assert run(["sigma", "--depth-mm", "500", "1000", "0", "--signal-e", "20000", "5000", "100"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["depth_mm"] for r in rows] == [500.0, 1000.0, 0.0]
    assert [r["signal_e"] for r in rows] == [20000.0, 5000.0, 100.0]
    calib = default_calibration()
    assert rows[0]["sigma_mm"] == pytest.approx(float(sigma_depth_mm(500.0, 20000.0, calib)), rel=1e-12)
    assert rows[1]["sigma_mm"] == pytest.approx(float(sigma_depth_mm(1000.0, 5000.0, calib)), rel=1e-12)
    assert rows[2]["sigma_mm"] is None  # invalid depth


def test_sigma_broadcasts_single_value_and_rejects_mismatch(capsys):
    assert run(["sigma", "--depth-mm", "800", "--signal-e", "1000", "10000", "40000"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["depth_mm"] for r in rows] == [800.0] * 3
    s = [r["sigma_mm"] for r in rows]
    assert s[0] > s[1] > s[2]
    with pytest.raises(ValueError, match="--depth-mm has 2 values and --signal-e has 3"):
        run(["sigma", "--depth-mm", "1", "2", "--signal-e", "1", "2", "3"])


def test_sensor_dispatcher_reports_errors(capsys):
    from tofdenoise.cli.sensor import main

    assert main(["sigma", "--depth-mm", "1", "2", "--signal-e", "1", "2", "3"]) == 2
    assert "give the same number" in capsys.readouterr().err
    assert main(["show-calib", "--sensor", "/nonexistent/calib.yaml"]) == 2
    assert "not found" in capsys.readouterr().err


def test_calibrate_command_round_trip(tmp_path, capsys):
    from tofdenoise.physics.synthetic_captures import write_dark_folder, write_distances_folder, write_sweep_folder

    true = default_calibration()
    write_sweep_folder(true, tmp_path / "sweep", num_steps=16, num_frames=10)
    write_dark_folder(true, tmp_path / "dark", num_frames=50)
    write_distances_folder(true, tmp_path / "dist", [600.0, 900.0, 1200.0, 1500.0], num_frames=40)
    out = tmp_path / "calib.yaml"
    assert (
        run(
            [
                "calibrate",
                "--sweep",
                str(tmp_path / "sweep"),
                "--dark",
                str(tmp_path / "dark"),
                "--distances",
                str(tmp_path / "dist"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "wrote" in capsys.readouterr().out
    got = load_calibration(out)
    assert out.read_text().startswith("# Calibrated by tofdenoise sensor calibrate")
    np.testing.assert_allclose(got.tap_response.cos, true.tap_response.cos, atol=3e-3)
    assert got.dark_std_e == pytest.approx(true.dark_std_e, rel=0.03)
    assert got.range_sigma_mm is not None


def test_calibrate_sweep_amplitude_option_and_header(tmp_path, capsys):
    """A 3-tap camera with c(x) = 1 + 0.5 cos x + 0.08 cos 3x: the default (auto: a phase_rad sweep, one common
    amplitude) writes c3 = 0.08 and says so in the header; --sweep-amplitude per-step writes c3 = 0, warns on stderr
    and in the header with the sigma_D error it may carry."""
    from tofdenoise.physics.calibration import TapResponse
    from tofdenoise.physics.synthetic_captures import write_dark_folder, write_sweep_folder

    cam = default_calibration().replace(
        num_taps=3,
        modulation_frequency_hz=30e6,
        tap_response=TapResponse(1.0, (0.5, 0.0, 0.08), (0.0, 0.0, 0.0)),
        dark_mean_e=500.0,
        dark_std_e=20.0,
        full_well_e=200000.0,
    )
    write_sweep_folder(cam, tmp_path / "sweep", num_steps=24, num_frames=10)
    write_dark_folder(cam, tmp_path / "dark", num_frames=20)
    base = ["calibrate", "--sweep", str(tmp_path / "sweep"), "--dark", str(tmp_path / "dark")]
    assert run([*base, "--out", str(tmp_path / "auto.yaml")]) == 0
    capsys.readouterr()
    assert load_calibration(tmp_path / "auto.yaml").tap_response.cos[2] == pytest.approx(0.08, abs=2e-3)
    header = (tmp_path / "auto.yaml").read_text()
    assert "# tap response: one common amplitude over the sweep" in header and "cos 3x +0.08" in header
    assert run([*base, "--out", str(tmp_path / "step.yaml"), "--sweep-amplitude", "per-step"]) == 0
    err = capsys.readouterr().err
    assert "harmonic of c(x) at a multiple of N = 3" in err and "sigma_D is off by" in err
    assert abs(load_calibration(tmp_path / "step.yaml").tap_response.cos[2]) < 1e-6
    assert "# warning: " in (tmp_path / "step.yaml").read_text()


def test_validate_command_writes_outputs(tmp_path, capsys):
    assert run(["validate", "--out", str(tmp_path), "--quick", "--frames", "20", "--roi-px", "8"]) == 0
    out = capsys.readouterr().out
    assert "pooled" in out and "range_gaussian" in out
    data = json.loads((tmp_path / "validation.json").read_text())
    assert data["settings"]["num_frames"] == 20 and data["settings"]["roi_px"] == 8
    assert data["pooled"]["proposed"]["mape_percent"] < data["pooled"]["range_gaussian"]["mape_percent"]
    assert (tmp_path / "validation.png").stat().st_size > 10_000


def test_validate_names_the_saturated_conditions_it_leaves_out(tmp_path, capsys):
    """A 3-tap, 30 MHz camera with a 60 ke- full well (the audit's cam3_cal.yaml): its 500 mm range condition and
    550 mm range-fit condition saturate in every frame. The command printed alpha = nan and wrote NaN into
    validation.json; now the baseline is finite, the two conditions are named on stderr and in the record."""
    from tofdenoise.physics.calibration import TapResponse

    calib = default_calibration().replace(
        num_taps=3,
        modulation_frequency_hz=30e6,
        tap_response=TapResponse(1.0, (0.6, 0.05, 0.0), (0.1, 0.0, 0.0)),
        dark_mean_e=500.0,
        dark_std_e=20.0,
        full_well_e=60000.0,
    )
    sensor = save_calibration(calib, tmp_path / "cam3.yaml")
    out = tmp_path / "v"
    assert run(["validate", "--out", str(out), "--sensor", str(sensor), "--frames", "10", "--roi-px", "4"]) == 0
    printed = capsys.readouterr()
    assert "nan" not in printed.out
    assert "2 condition(s) without a pixel valid in every frame" in printed.err
    assert "range 500 mm" in printed.err and "range_fit 550 mm" in printed.err
    text = (out / "validation.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    assert all(np.isfinite(data["range_sigma_mm"]))
    assert [(c["group"], c["distance_mm"]) for c in data["left_out"]] == [("range", 500.0), ("range_fit", 550.0)]


def test_sigma_prints_strict_json_and_refuses_meaningless_depths(capsys):
    from tofdenoise.cli.sensor import main

    assert main(["sigma", "--depth-mm", "nan", "inf", "1000", "--signal-e", "10000", "10000", "inf"]) == 0
    out = capsys.readouterr().out
    assert "NaN" not in out and "Infinity" not in out
    rows = json.loads(out)  # strict JSON
    assert rows == [
        {"depth_mm": None, "signal_e": 10000.0, "sigma_mm": None},
        {"depth_mm": None, "signal_e": 10000.0, "sigma_mm": None},
        {"depth_mm": 1000.0, "signal_e": None, "sigma_mm": None},
    ]
    r = default_calibration().unambiguous_range_mm
    assert main(["sigma", "--depth-mm", str(0.99e6 * r), "--signal-e", "10000"]) == 0  # far, but allowed
    capsys.readouterr()
    assert main(["sigma", "--depth-mm", "1000", "1e12", "--signal-e", "10000"]) == 2
    err = capsys.readouterr().err
    assert "--depth-mm 1e+12 is 3.34e+08 unambiguous ranges" in err and "refused" in err


def test_unknown_preset_lists_the_presets(capsys):
    from tofdenoise.cli.sensor import main

    assert main(["show-calib", "--sensor", "defualt"]) == 2
    err = capsys.readouterr().err
    assert "'defualt': no such file and no preset of that name; presets: cam75, default" in err
    assert main(["show-calib", "--sensor", "default"]) == 0


@pytest.mark.parametrize(
    "argv", [["show-calib"], ["show-calib", "--json"], ["sigma", "--depth-mm", "1000", "--signal-e", "10000"]]
)
def test_closed_stdout_pipe_ends_quietly(argv):
    """`tofdenoise sensor show-calib | head`: the reader is gone before anything is written."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    read_end, write_end = os.pipe()
    os.close(read_end)
    src = Path(__file__).resolve().parents[2] / "src"
    try:
        proc = subprocess.run(
            [sys.executable, "-c", "import sys; from tofdenoise.cli.sensor import main; sys.exit(main())", *argv],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            env={**os.environ, "PYTHONPATH": str(src)},
        )
    finally:
        os.close(write_end)
    assert proc.returncode == 141 and proc.stderr == ""


def _snapshot(folder) -> dict:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("target", ["sweep/index.json", "dark/index.json", "sweep", "dist/index.json"])
def test_calibrate_refuses_an_out_that_would_replace_its_captures(tmp_path, capsys, target):
    """issue 23 case 2: `calibrate --sweep S --dark D --out S/index.json` overwrote the capture index, so the
    capture set could no longer be calibrated."""
    from tofdenoise.cli.sensor import main
    from tofdenoise.physics.synthetic_captures import write_dark_folder, write_distances_folder, write_sweep_folder

    true = default_calibration()
    write_sweep_folder(true, tmp_path / "sweep", num_steps=8, num_frames=4)
    write_dark_folder(true, tmp_path / "dark", num_frames=8)
    write_distances_folder(true, tmp_path / "dist", [600.0, 900.0, 1200.0], num_frames=8)
    before = _snapshot(tmp_path)
    out = tmp_path / target
    argv = ["calibrate", "--sweep", str(tmp_path / "sweep"), "--dark", str(tmp_path / "dark")]
    assert main([*argv, "--distances", str(tmp_path / "dist"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("tofdenoise sensor calibrate: error: --out")
    assert str(out) in err and "would replace" in err
    assert _snapshot(tmp_path) == before  # nothing written


def test_validate_with_captures_refuses_the_simulation_settings(tmp_path, capsys):
    """--quick / --frames / --roi-px / --seed set the simulated stacks; with --captures they were accepted and
    ignored (validation.json did not say what was measured)."""
    from tofdenoise.cli.sensor import main

    for extra in (["--quick"], ["--frames", "500"], ["--roi-px", "64"]):
        code = main(["validate", "--captures", str(tmp_path / "val"), "--out", str(tmp_path / "out"), *extra])
        err = capsys.readouterr().err
        assert code == 2 and extra[0] in err and "--captures" in err, err
        assert not (tmp_path / "out").exists()


def test_validate_refuses_an_out_whose_files_would_replace_its_inputs(tmp_path, capsys):
    from tofdenoise.cli.sensor import main

    calib = save_calibration(default_calibration(), tmp_path / "validation.json")
    before = calib.read_bytes()
    assert main(["validate", "--out", str(tmp_path), "--sensor", str(calib), "--quick", "--frames", "4"]) == 2
    err = capsys.readouterr().err
    assert f"would replace the input {calib}" in err and calib.read_bytes() == before
    assert not (tmp_path / "validation.png").exists()


def test_calibrate_out_an_existing_folder_is_one_line_before_any_work(tmp_path, capsys):
    """--out naming a folder (even one called *.yaml) was an IsADirectoryError traceback after the whole
    calibration had run; now it is one line, exit 2, and the folder is untouched."""
    from tofdenoise.cli.sensor import main
    from tofdenoise.physics.synthetic_captures import write_dark_folder, write_sweep_folder

    true = default_calibration()
    sweep = write_sweep_folder(true, tmp_path / "sweep", num_steps=8, num_frames=2)
    dark = write_dark_folder(true, tmp_path / "dark", num_frames=4)
    for name in ("folder.yaml", "plain_folder"):
        out = tmp_path / name
        out.mkdir()
        assert main(["calibrate", "--sweep", str(sweep), "--dark", str(dark), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"{out} is a folder: give a calibration file name" in err and "Traceback" not in err
        assert list(out.iterdir()) == []
