"""The long-schedule study: validation curves read from the records, paired gaps along training, the figure."""

from __future__ import annotations

import pytest

from tofdenoise.experiments.schedule import (
    curves_figure_png,
    gap_table,
    read_val_curve,
    schedule_curves,
)


def _write_curve(folder, points, extra_rows=()):
    (folder / "csv").mkdir(parents=True)
    lines = ["epoch,step,train/loss,val/mae_mm"]
    lines += [f"{i},{step},0.5," for i, step in enumerate(extra_rows)]  # training rows: no validation value
    lines += [f"{i},{step},,{mae}" for i, (step, mae) in enumerate(points)]
    (folder / "csv" / "metrics.csv").write_text("\n".join(lines) + "\n")


def _study(dest, seed=0):
    # validation every 2 epochs of 45 steps, 100 epochs: steps 89, 179, ..., 4499
    steps = list(range(89, 4500, 90))
    hetero = [(s, 2.0) for s in steps]
    rng = [(s, 2.5 if s < 2000 else 2.1) for s in steps]  # the gap to range closes from 0.5 to 0.1
    fixed = [(s, 3.0) for s in steps]
    for noise, pts in (("hetero", hetero), ("range", rng), ("fixed", fixed)):
        _write_curve(dest / f"dvss-{noise}-l1-e100-s{seed}", pts, extra_rows=(10, 20))


def test_the_gap_is_read_at_the_short_schedules_end_and_at_the_long_ones(tmp_path):
    _study(tmp_path)
    curves = schedule_curves(tmp_path, [0, 1])  # seed 1 has no records: no curves
    assert sorted((c.noise, c.seed) for c in curves) == [("fixed", 0), ("hetero", 0), ("range", 0)]
    rows = gap_table(curves, epochs=100)
    assert rows == [
        {"seed": 0, "baseline": "fixed", "short_step": 449, "short_gap_mm": 1.0, "end_step": 4499, "end_gap_mm": 1.0},
        {
            "seed": 0,
            "baseline": "range",
            "short_step": 449,
            "short_gap_mm": pytest.approx(0.5),
            "end_step": 4499,
            "end_gap_mm": pytest.approx(0.1),
        },
    ]


def test_a_curve_with_a_bad_value_is_an_error_naming_the_file(tmp_path):
    _write_curve(tmp_path / "r", [(89, 2.0), (179, float("nan"))])
    with pytest.raises(ValueError, match=r"r/csv/metrics.csv: val/mae_mm at step 179 is nan"):
        read_val_curve(tmp_path / "r" / "csv" / "metrics.csv")
    assert read_val_curve(tmp_path / "missing.csv") == ()


def test_the_figure_is_a_png_and_the_same_curves_give_the_same_bytes(tmp_path):
    _study(tmp_path)
    curves = schedule_curves(tmp_path, [0])
    png = curves_figure_png(curves)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png == curves_figure_png(curves)


def test_the_gpu_short_page_shows_the_gaps_and_the_figure(tmp_path):
    from tofdenoise.experiments.reproduce import write_schedule_figure
    from tofdenoise.paths import REPO_ROOT
    from tofdenoise.reporting.results_page import results_markdown

    (tmp_path / "cpu").mkdir()
    _study(tmp_path / "gpu-short")
    for run in (tmp_path / "gpu-short").iterdir():  # committed records, so that the profile has finished runs
        for name in ("metrics.json", "run_info.json"):
            (run / name).write_bytes((REPO_ROOT / "docs/results/gpu-short/dvss-fixed-l1-s0" / name).read_bytes())
    write_schedule_figure(tmp_path / "gpu-short", [0])
    page = results_markdown(tmp_path)
    assert "| 0 | range | +0.500 (449) | +0.100 (4499) |" in page
    assert "| 0 | fixed | +1.000 (449) | +1.000 (4499) |" in page
    assert "](results/gpu-short/schedule/curves.png)" in page
