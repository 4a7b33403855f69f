"""The dynamic-range study: its runs, and hetero's paired gains computed by hand from records."""

from __future__ import annotations

import math

import pytest

from tofdenoise.experiments.dynrange import gain_figure_png, gains
from tofdenoise.experiments.tables import TABLES, table_specs
from tofdenoise.records import learned_verdict, read_metrics_json, set_entry, write_metrics_json
from tofdenoise.reporting.results_page import gains_markdown


def test_study_runs_share_the_physical_world_with_table_3_and_start_with_unet():
    specs = table_specs("dynrange", [0, 1, 2])
    names = [s.name for s in specs]
    assert len(names) == len(set(names)) == 3 * (5 * 3 + 4 * 3)  # U-Net: 4 worlds + x4; DVSS: 4 worlds
    assert names[0] == "unet-fixed-l1-dr16-s0" and all(n.startswith("unet") for n in names[:45])
    table3 = {s.name for s in table_specs("3", [0, 1, 2])}
    assert {"dvss-hetero-l1-s0", "dvss-range-l1-s1", "dvss-fixed-l1-s2", "unet-range-l1-s0"} <= table3 & set(names)
    by_name = {s.name: s for s in specs}
    assert by_name["unet-hetero-l1-dr64-s1"].overrides[-2:] == (
        "++data.signal_route=linear",
        "++data.signal_dynamic_range=64",
    )
    assert by_name["unet-fixed-l1-x4-s0"].overrides[-1] == "trainer.max_epochs=48"
    assert not any("signal" in o for o in by_name["dvss-hetero-l1-s0"].overrides)  # the default world


def _write_record(folder, name: str, syn: float, real: float | None = None) -> None:
    """A run's metrics.json in the real schema, through the project's own writer (what the study reads back)."""

    def block(mae: float) -> dict:
        return {"psnr_db": 40.0, "ssim": 0.99, "mse_mm2": mae * mae, "mae_mm": mae}

    results = {"synthetic": set_entry(block(syn), raw=block(9.0))}
    if real is not None:
        results["real"] = set_entry(block(real), raw=block(12.0))
    write_metrics_json(folder / name / "metrics.json", results, run=learned_verdict(10, 1.0, 9.0))


def test_gains_are_paired_by_seed_and_count_only_complete_seeds(tmp_path):
    for name, syn, real in [
        # seeds 0 and 1 complete for U-Net at dr16; seed 2 lacks the range run
        ("unet-fixed-l1-dr16-s0", 5.0, 7.0),
        ("unet-range-l1-dr16-s0", 4.5, 6.5),
        ("unet-hetero-l1-dr16-s0", 4.0, 6.0),
        ("unet-fixed-l1-dr16-s1", 6.0, 7.5),
        ("unet-range-l1-dr16-s1", 4.0, 6.4),
        ("unet-hetero-l1-dr16-s1", 4.2, 6.2),
        ("unet-fixed-l1-dr16-s2", 9.0, None),
        ("unet-hetero-l1-dr16-s2", 1.0, None),
    ]:
        _write_record(tmp_path, name, syn, real)
    records = {p.parent.name: read_metrics_json(p) for p in tmp_path.glob("*/metrics.json")}
    items = gains(records.get, [0, 1, 2])
    assert len(items) == 1
    g = items[0]
    assert (g.backbone, g.tag, g.n) == ("unet", "dr16", 2)
    assert g.hetero_mae == pytest.approx(4.1)
    assert g.over_fixed[0] == pytest.approx((1.0 + 1.8) / 2) and g.over_fixed[1] == pytest.approx(math.sqrt(0.32))
    assert g.over_range[0] == pytest.approx((0.5 - 0.2) / 2)
    assert g.real_over_fixed[0] == pytest.approx((1.0 + 1.3) / 2)
    table = "\n".join(gains_markdown(items))
    assert "| U-Net | a_max/a_min = 16 | 2 | 4.100 | +1.400 ± 0.566 | +0.150 ± 0.495 |" in table
    png = gain_figure_png(items)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png == gain_figure_png(items)  # no timestamp in the file


def test_every_study_row_is_one_of_its_worlds():
    keys = [r.key for r in TABLES["dynrange"]]
    assert len(keys) == len(set(keys)) == 27
    assert {r.noise for r in TABLES["dynrange"]} == {"fixed", "range", "hetero"}
    assert {r.loss for r in TABLES["dynrange"]} == {"l1"}


def test_the_gain_figure_leaves_out_a_seed_of_two_protocols(tmp_path):
    """``write_dynrange_figure`` reads the records as the page's gain table does: a seed whose three runs of one
    world are of two protocols (one of them without the simulator-noised split) is no gain."""
    import json

    from tofdenoise.experiments.reproduce import write_dynrange_figure
    from tofdenoise.reporting.results_page import DYNRANGE_FIGURE

    for name, syn in [("unet-fixed-l1-s0", 5.0), ("unet-range-l1-s0", 4.5), ("unet-hetero-l1-s0", 4.0)]:
        _write_record(tmp_path, name, syn)
        (tmp_path / name / "run_info.json").write_text(json.dumps({"started": "x", "finished": "y"}))
    write_dynrange_figure(tmp_path)  # all three of the earlier protocol: one seed, one gain
    assert (tmp_path / DYNRANGE_FIGURE).is_file()
    (tmp_path / DYNRANGE_FIGURE).unlink()
    path = tmp_path / "unet-hetero-l1-s0" / "metrics.json"
    data = json.loads(path.read_text())
    data["simulated"] = data["synthetic"]  # hetero rerun under the current protocol, the Gaussians not
    path.write_text(json.dumps(data))
    write_dynrange_figure(tmp_path)
    assert not (tmp_path / DYNRANGE_FIGURE).exists()


def test_the_page_alone_redraws_a_study_figure_from_the_records_as_they_are(tmp_path):
    """``reproduce --page-only`` redraws the gain figure: a Table 3 record the study shares, replaced by hand after
    the figure was drawn, moves the figure too; with no gain left the figure goes."""
    import json
    import shutil

    from tofdenoise.cli.reproduce import main
    from tofdenoise.experiments.reproduce import comparable_metrics, load_records
    from tofdenoise.reporting.results_page import DYNRANGE_FIGURE

    dest = tmp_path / "results" / "cpu"
    for name, syn in [("unet-fixed-l1-s0", 5.0), ("unet-range-l1-s0", 4.5), ("unet-hetero-l1-s0", 4.0)]:
        _write_record(dest, name, syn)
        (dest / name / "run_info.json").write_text(json.dumps({"started": "x", "finished": "y"}))
    figure, page = dest / DYNRANGE_FIGURE, tmp_path / "results.md"
    figure.parent.mkdir(parents=True)
    figure.write_bytes(b"a figure of the records before")
    assert main(["--page-only", "--results", str(dest.parent), "--page", str(page)]) == 0
    items = gains(comparable_metrics(["dynrange"], [0], load_records(dest)), [0])
    assert [round(g.over_fixed[0], 6) for g in items] == [1.0]
    assert figure.read_bytes() == gain_figure_png(items)
    assert "](results/cpu/dynrange/gains.png)" in page.read_text()
    shutil.rmtree(dest / "unet-range-l1-s0")
    assert main(["--page-only", "--results", str(dest.parent), "--page", str(page)]) == 0
    assert not figure.exists() and "results/cpu/dynrange/gains.png" not in page.read_text()
