"""The qualitative figures (Fig. 7 / Fig. 8): their runs, scene choice, rendering, and the check that they show
what the tables scored."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tofdenoise.experiments.figures import (
    FIGURES,
    FigureMismatch,
    FigureSpec,
    check_against_records,
    encode_png_palette,
    figure_rows,
    figure_specs,
    pick_indices,
    render_figure,
)
from tofdenoise.experiments.tables import table_specs
from tofdenoise.models.tiling import TilingSettings
from tofdenoise.reporting.results_page import results_markdown


def test_pick_indices_are_evenly_spaced_and_not_chosen_by_result():
    assert pick_indices(48, 3) == [0, 24, 47]
    assert pick_indices(24, 5) == [0, 6, 12, 17, 23]
    assert pick_indices(2, 5) == [0, 1]
    assert pick_indices(7, 1) == [0]
    with pytest.raises(ValueError, match="empty"):
        pick_indices(0, 3)


def test_columns_are_the_tables_runs():
    """A figure trains nothing of its own: each column is the folder (and the overrides) of a table's run."""
    assert [label for label, _ in figure_rows(FIGURES["fig7"])] == [
        "DVSS-Range",
        "DeepToF",
        "ToF-KPN",
        "RCF",
        "Ours",
    ]
    common = ("experiment=reproduce_cpu", "++data.sensor=/r/calibration.yaml")
    tables = {s.name: s for t in ("1", "3") for s in table_specs(t, [1], common)}
    for key, names in (
        ("fig7", ["dvss-range-l1-s1", "deeptof-hetero-l1-s1", "tofkpn-hetero-l1-s1", "rcf-hetero-l1-s1"]),
        ("fig8", ["deeptof-hetero-l1-s1", "tofkpn-hetero-l1-s1", "rcf-hetero-l1-s1"]),
    ):
        specs = figure_specs(FIGURES[key], 1, common)
        assert [s.name for s in specs] == [*names, "dvss-hetero-full-s1"]
        for s in specs:
            assert s.overrides == tables[s.name].overrides
    bad = FigureSpec("x", "x", "synthetic", (("Raw", "1", "raw"),), 1, "Input", "GT")
    with pytest.raises(ValueError, match="must be a trained row"):
        figure_rows(bad)


class _Offset:
    """A restorer that returns the clean depth + ``offset_mm`` (its MAE over any mask is ``offset_mm``)."""

    def __init__(self, offset_mm: float):
        self.offset_mm = offset_mm
        self.hparams = type("H", (), {"d_max_mm": 1000.0})()
        self.tiling = TilingSettings(eval_tile_px=512)
        self.device = torch.device("cpu")

    def restore_mm(self, batch, tile=None):
        return batch["clean"] + self.offset_mm


def _item(index: int, hole: bool) -> dict:
    clean = torch.full((1, 12, 16), 800.0) + torch.arange(16.0)
    mask = torch.ones(1, 12, 16)
    if hole:
        mask[:, :4, :4] = 0  # a hole: its pixels do not count
    noisy = clean + 3.0
    noisy[mask == 0] = 0.0
    return {
        "noisy": noisy,
        "clean": clean * mask,
        "mask": mask,
        "amplitude": torch.ones(1, 12, 16),
        "index": index,
        "name": f"scene_{index:03d}",
    }


def test_render_figure_shows_every_column_and_records_hand_computed_maes():
    dataset = [_item(i, hole=i % 2 == 1) for i in range(4)]
    spec = FigureSpec("figx", "Fig. X", "synthetic", (), 2, "Input", "GT")
    models = {"A": _Offset(2.0), "B": _Offset(0.5)}
    image, record = render_figure(spec, models, dataset, [0, 3])
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    assert record["columns"] == ["A", "B"] and [s["name"] for s in record["scenes"]] == ["scene_000", "scene_003"]
    for scene in record["scenes"]:  # scene_003 has a hole: the MAE is over its valid pixels only
        assert scene["mae_mm"] == pytest.approx({"Input": 3.0, "A": 2.0, "B": 0.5}, abs=1e-9)
    one_scene, _ = render_figure(spec, models, dataset, [0])
    assert one_scene.shape[1] == image.shape[1] and one_scene.shape[0] < image.shape[0] / 1.8


def _record(mae_input: float, mae_a: float) -> dict:
    return {
        "test_set": "synthetic",
        "input": "Input",
        "scenes": [{"index": 0, "name": "scene_000", "mae_mm": {"Input": mae_input, "A": mae_a}}],
    }


def _per_image(run_dir: Path, mae: float, raw_mae: float) -> Path:
    (run_dir / "per_image").mkdir(parents=True)
    path = run_dir / "per_image" / "synthetic.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["index", "name", "valid_px", "mae_mm", "raw_mae_mm"])
        w.writerow([0, "scene_000", 100, mae, raw_mae])
    return path


def test_check_against_records(tmp_path):
    run = tmp_path / "a-s0"
    path = _per_image(run, mae=1.2345, raw_mae=4.0)
    check_against_records(_record(4.0, 1.2349), {"A": run})  # within 1e-3 mm
    with pytest.raises(FigureMismatch, match=r"A's prediction has MAE 1\.2400 mm.*mae_mm = 1\.2345") as err:
        check_against_records(_record(4.0, 1.24), {"A": run})
    assert str(path) in str(err.value)
    with pytest.raises(FigureMismatch, match=r"the figure's input has MAE 4\.0100 mm"):
        check_against_records(_record(4.01, 1.2345), {"A": run})
    other = _record(4.0, 1.2345)
    other["scenes"][0]["name"] = "scene_999"
    with pytest.raises(FigureMismatch, match="no row for scene 'scene_999'"):
        check_against_records(other, {"A": run})
    with pytest.raises(FigureMismatch, match="missing"):
        check_against_records(_record(4.0, 1.2345), {"A": tmp_path / "never-ran"})


def test_palette_png_is_exact_for_few_colours_and_rejects_other_images():
    from PIL import Image

    rng = np.random.default_rng(0)
    palette = rng.integers(0, 256, size=(40, 3), dtype=np.uint8)
    image = palette[rng.integers(0, 40, size=(30, 50))]
    data = encode_png_palette(image)
    decoded = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    np.testing.assert_array_equal(decoded, image)
    with pytest.raises(ValueError, match="expected uint8"):
        encode_png_palette(image.astype(np.float32))


def test_page_section_from_a_figure_record(tmp_path):
    results = tmp_path / "results"
    fig = results / "cpu" / "fig8"
    fig.mkdir(parents=True)
    record = {
        "figure": "fig8",
        "title": "Fig. 8: results on the real set",
        "test_set": "real",
        "input": "Raw",
        "reference": "Reference",
        "columns": ["RCF", "Ours"],
        "note": "A note.",
        "scenes": [{"index": 3, "name": "scene_0003", "mae_mm": {"Raw": 5.0, "RCF": 1.5, "Ours": 1.25}}],
        "seed": 0,
        "runs": {"RCF": "rcf-hetero-l1-s0", "Ours": "dvss-hetero-full-s0"},
    }
    (fig / "figure.json").write_text(json.dumps(record))
    page = results_markdown(results)
    assert "| scene (MAE, mm) | Raw | RCF | Ours |" in page
    assert "| scene_0003 (index 3) | 5.00 | 1.50 | 1.25 |" in page
    assert "RCF = `rcf-hetero-l1-s0`, Ours = `dvss-hetero-full-s0`" in page and "A note." in page
    assert "A note. Written before figure records named their commit and machine." in page
    record["provenance"] = {"written": "2026-11-28T17:00:00+0000", "commit": "cd" * 20, "machine": {"cpu": "AMD EPYC"}}
    (fig / "figure.json").write_text(json.dumps(record))
    assert "A note. Written 2026-11-28, commit cdcdcdc, on AMD EPYC." in results_markdown(results)
    assert "results/cpu/fig8/figure.png" not in page  # no image written
    assert "Not run yet (`make reproduce FIGURE=7`)" in page


def test_committed_figures_show_the_committed_records():
    """Each committed figure's per-scene MAE equals its runs' committed per-image records: a run re-recorded
    later without re-rendering its figure fails here."""
    from tofdenoise.paths import REPO_ROOT

    results = REPO_ROOT / "docs" / "results"
    # the new world's figures are committed once their runs exist (docs/results/discussion.md); every committed one
    # is checked (the end-to-end test above renders and checks one from a tiny run whatever is committed)
    # a column whose run trained again after the figure was drawn is not compared, and the page says it is out of
    # date (the figure needs every column's checkpoint to be drawn again)
    from tofdenoise.experiments.figures import stale_columns

    page = (REPO_ROOT / "docs" / "results.md").read_text()
    figures = sorted(results.glob("*/fig[78]/figure.json"))
    for path in figures:
        record = json.loads(path.read_text())
        profile_dir = path.parent.parent
        assert list(record["runs"]) == record["columns"] and len(record["scenes"]) == FIGURES[record["figure"]].scenes
        run_dirs = {label: profile_dir / name for label, name in record["runs"].items()}
        stale = stale_columns(record, run_dirs)
        for label in stale:
            assert f"**Out of date:** {label} (`{record['runs'][label]}`)" in page
        assert len(stale) < len(run_dirs)  # a figure all of whose runs trained again is drawn again
        check_against_records(record, run_dirs, skip=stale)


def test_a_column_whose_run_trained_again_after_the_figure_is_stale(tmp_path):
    """A run trained again (its run_info ``started`` after the figure's ``provenance.written``) no longer holds the
    predictions the figure shows: that column is stale; a run trained before the figure, or without a readable
    run_info.json, is not."""
    from tofdenoise.experiments.figures import stale_columns

    runs = {"A": tmp_path / "a", "B": tmp_path / "b", "C": tmp_path / "c"}
    for label, started in (("A", "2026-11-28T10:00:00+0000"), ("B", "2026-11-29T02:26:00+0000")):
        runs[label].mkdir()
        (runs[label] / "run_info.json").write_text(json.dumps({"started": started}))
    record = {"provenance": {"written": "2026-11-28T16:31:17+0000"}}
    assert stale_columns(record, runs) == ["B"]
    assert stale_columns({"provenance": None}, runs) == []
