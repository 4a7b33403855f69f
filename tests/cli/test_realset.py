"""The stand-in real set (docs/camera-tutorial.md): a second simulated camera, calibrated from its own captures;
training with that calibration and testing on that camera's capture set (`tofdenoise.data_modules.realset`, run by
`tofdenoise sensor realset`, `make realset` and `tofdenoise reproduce`)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from tofdenoise.cli.sensor import build_parser, main
from tofdenoise.data_modules.realset import REALSET_CAMERA, REALSET_SEED, build_realset
from tofdenoise.physics.calibration import default_calibration, load_calibration, resolve_calibration

REPO = Path(__file__).resolve().parents[2]


def test_the_realset_camera_is_not_the_training_camera():
    """frequency, contrast, harmonics, dark level and ADC gain all differ from configs/sensor/default.yaml."""
    cam, default = resolve_calibration(REALSET_CAMERA), default_calibration()
    assert cam.modulation_frequency_hz != default.modulation_frequency_hz
    assert abs(cam.tap_response.contrast - default.tap_response.contrast) > 0.02

    def harmonics(c):
        tr = c.tap_response
        return {k + 1 for k, (a, b) in enumerate(zip(tr.cos, tr.sin)) if k > 0 and (a or b)}

    assert harmonics(cam) and harmonics(cam) != harmonics(default)
    assert cam.dark_mean_e != default.dark_mean_e and cam.adc_gain_e_per_dn != default.adc_gain_e_per_dn
    # the capture set's scenes are not the training scenes (procedural seed != the default data.seed 0)
    assert REALSET_SEED != 0
    # `make realset` runs this command
    makefile = (REPO / "Makefile").read_text()
    recipe = re.search(r"^realset:.*\n((?:\t.*\n)+)", makefile, re.M)
    assert recipe and "tofdenoise sensor realset --out $(REALSET_DIR)" in recipe.group(1)
    # the command's defaults are the library's (said in its help)
    (sub,) = [a for a in build_parser()._actions if a.dest == "command"]
    realset_help = sub.choices["realset"].format_help()
    assert f"preset {REALSET_CAMERA}" in realset_help and f"default {REALSET_SEED}" in realset_help


def make_realset(out: Path) -> None:
    assert (
        main(["realset", "--out", str(out), "--scenes", "2", "--frames", "4", "--height", "32", "--width", "48"]) == 0
    )


def realset_overrides(out: Path) -> list[str]:
    return [f"++data.sensor={out / 'calibration.yaml'}", f"++data.real_dir={out / 'captures'}"]


def test_realset_command_writes_calibration_and_captures(tmp_path, capsys, data_cache, tiny):
    """Steps a)-c) at tiny sizes, resumable; the training config reads that calibration and capture set."""
    from hydra.utils import instantiate

    from tofdenoise.config import compose_config

    out = tmp_path / "realset"
    make_realset(out)
    printed = capsys.readouterr().out
    for step in ("a) calibration captures", "b) calibration from", "c) capture set", "d) noise-validation captures"):
        assert step in printed  # each step is announced before it runs
    calib = load_calibration(out / "calibration.yaml")
    true = resolve_calibration(REALSET_CAMERA)
    assert calib.modulation_frequency_hz == true.modulation_frequency_hz
    assert calib.fingerprint() != true.fingerprint()  # estimated from captures, not copied
    assert abs(calib.dark_mean_e - true.dark_mean_e) < 0.01 * true.dark_mean_e
    scenes = sorted(p.name for p in (out / "captures").iterdir() if p.is_dir())
    assert scenes == ["scene_0000", "scene_0001"]
    assert json.loads((out / "captures" / "scene_0000" / "scene.json").read_text())["mixed_pixels"] == 3
    # the Fig. 6 conditions as that camera records them (tofdenoise sensor validate --captures)
    assert json.loads((out / "validation" / "index.json").read_text())["kind"] == "validation"
    # resumable: the calibration is kept, the completed scenes are skipped
    make_realset(out)
    again = capsys.readouterr().out
    assert "steps a) and b) skipped" in again and "0 scene(s) written, 2 already complete" in again
    assert "d) noise-validation" not in again
    # the library function the command calls: the same resumption, the steps it ran
    logged = []
    summary = build_realset(out, scenes=2, frames=4, height=32, width=48, log=logged.append)
    assert summary.steps == ("c",) and summary.capture_set.scenes_skipped == 2
    assert summary.calibration == out / "calibration.yaml" and any("steps a) and b) skipped" in x for x in logged)
    # step d)'s configuration: the datamodule synthesises training data with that calibration and adds the real set
    cfg = compose_config(tiny(tmp_path / "run", data_cache) + realset_overrides(out))
    dm = instantiate(cfg.data, _convert_="all")
    assert dm.calib.fingerprint() == calib.fingerprint()
    assert dm.make_source().max_depth_mm == 0.8 * calib.unambiguous_range_mm  # the second camera's range
    dm.prepare_data()
    dm.setup("test")
    assert dm.test_set_names == ["synthetic", "simulated", "real"] and len(dm.datasets["real"]) == 2


@pytest.mark.slow
def test_train_with_the_realset_calibration_and_test_on_its_captures(tmp_path, data_cache, tiny):
    """Step d) (30-45 s measured on the shared 2-core machine): fit with the calibration, test on the capture set."""
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config

    out = tmp_path / "realset"
    make_realset(out)
    run_dir = tmp_path / "run"
    run(compose_config(tiny(run_dir, data_cache) + realset_overrides(out) + ["trainer.max_epochs=1", "logger=csv"]))
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["real"]["images"] == 2 and metrics["real"]["valid_px"] > 0.5 * 2 * 32 * 48
    assert np.isfinite(metrics["real"]["mae_mm"]) and metrics["real"]["raw"]["mae_mm"] > 0
    assert str(out / "calibration.yaml") in (run_dir / "config.yaml").read_text()


def test_the_default_set_is_the_papers_200_scenes_at_the_cpu_profiles_size():
    """``tofdenoise sensor realset``, ``build_realset`` and the CPU profile of ``tofdenoise reproduce`` build one set:
    200 scenes (the paper's count) of 128 x 160 (the CPU profile's training scenes), one scene per CPU core."""
    import inspect
    import os

    from tofdenoise.experiments.reproduce import REALSET_SIZES

    assert REALSET_SIZES["cpu"] == (200, 128, 160)
    defaults = {k: p.default for k, p in inspect.signature(build_realset).parameters.items()}
    assert (defaults["scenes"], defaults["height"], defaults["width"]) == REALSET_SIZES["cpu"]
    args = build_parser().parse_args(["realset", "--out", "x"])
    assert (args.scenes, args.height, args.width) == REALSET_SIZES["cpu"]
    assert args.workers == (os.cpu_count() or 1)
    assert build_parser().parse_args(["realset", "--out", "x", "--workers", "3"]).workers == 3
