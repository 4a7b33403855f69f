"""tofdenoise report on run folders fabricated in the documented layout."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from tofdenoise.cli.report import main
from tofdenoise.records import learned_verdict, set_entry, write_metrics_json
from tofdenoise.reporting import find_runs, load_run, results_table, table_markdown

RAW = {"psnr_db": 31.68, "ssim": 0.95, "mse_mm2": 680.0, "mae_mm": 7.21}


def _m(psnr, ssim, mse, mae):
    return {"psnr_db": psnr, "ssim": ssim, "mse_mm2": mse, "mae_mm": mae}


def _csv(path: Path, epochs: int, mae0: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["epoch,step,train/loss,val/mae_mm,val/raw/mae_mm,val/psnr_db"]
    for e in range(epochs):
        lines.append(f"{e},{e * 10 + 4},{1.0 / (e + 1):.4f},,,")
        lines.append(f"{e},{e * 10 + 9},,{mae0 / (e + 1):.3f},7.2,{30 + e:.2f}")
    path.write_text("\n".join(lines) + "\n")


def _panel(path: Path, value: int) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((10, 12, 3), value, np.uint8))
    return path.read_bytes()


@pytest.fixture
def runs(tmp_path):
    root = tmp_path / "runs"
    a = root / "dvss-hetero-full"
    write_metrics_json(
        a / "metrics.json",
        {
            "synthetic": set_entry(_m(40.85, 0.9987, 82.30, 2.54), RAW),
            "real": set_entry(_m(35.42, 0.99, 120.0, 4.87), _m(31.0, 0.97, 300.0, 7.0)),
        },
        run=learned_verdict(1000, 2.6, 7.2),
    )
    (a / "run_info.json").write_text(
        json.dumps({"backbone": "dvss", "noise": "hetero", "loss": "full", "run_name": "dvss-hetero-full"})
    )
    _csv(a / "csv" / "version_0" / "metrics.csv", 3, 9.0)
    _panel(a / "panels" / "epoch_999.png", 10)
    latest = _panel(a / "panels" / "epoch_1000.png", 200)  # numeric, not name order

    b = root / "sweep" / "0_unet"
    write_metrics_json(
        b / "metrics.json",
        {"synthetic": set_entry(_m(39.19, 0.9969, 120.52, 4.88), RAW)},
        run=learned_verdict(1000, 4.9, 7.2),
    )
    (b / ".hydra").mkdir(parents=True)
    (b / ".hydra" / "config.yaml").write_text(
        "backbone:\n  name: unet\n  kwargs: {}\nnoise:\n  name: range\nloss:\n  name: l1\n"
        "run_name: ${backbone.name}-${noise.name}-${loss.name}\n"
    )  # Hydra saves interpolations unresolved
    _csv(b / "csv" / "metrics.csv", 2, 12.0)

    bad = root / "broken"
    bad.mkdir()
    (bad / "metrics.json").write_text('{"synthetic": {"psnr_db": 1}}')
    return root, latest


def test_find_and_load_runs(runs):
    root, _ = runs
    found = find_runs([root])
    assert [p.name for p in found] == ["broken", "dvss-hetero-full", "0_unet"]
    a = load_run(found[1])
    assert (a.method, a.noise, a.loss, a.name) == ("dvss", "hetero", "full", "dvss-hetero-full")
    assert a.panel is not None and a.panel.name == "epoch_1000.png"
    b = load_run(found[2])
    assert (b.method, b.noise, b.loss, b.name) == ("unet", "range", "l1", "unet-range-l1")
    assert b.panel is None and len(b.curves) == 4
    with pytest.raises(ValueError, match="broken"):
        load_run(found[0])


def test_table_has_one_raw_row_per_distinct_raw_result_and_bold_best(runs):
    root, _ = runs
    loaded = [load_run(p) for p in find_runs([root])[1:]]
    sets, rows = results_table(loaded)
    assert sets == ["synthetic", "real"]
    assert [r["kind"] for r in rows] == ["raw", "run", "run"]  # same synthetic raw result -> one raw row
    md = table_markdown(sets, rows).splitlines()
    assert md[0].startswith("| Method | Noise | Loss | Learned | Synthetic PSNR (dB)↑")
    dvss = next(line for line in md if line.startswith("| dvss"))
    unet = next(line for line in md if line.startswith("| unet"))
    assert "**40.85**" in dvss and "**2.54**" in dvss and "**0.9987**" in dvss
    assert "39.19" in unet and "**" not in unet
    assert unet.rstrip(" |").endswith("–")  # no real set for this run
    assert "| Raw input | hetero, range | – | – | 31.68 | 0.9500 | 680.00 | 7.21 | 31.00 |" in "\n".join(md)
    assert "| dvss | hetero | full | yes | **40.85** |" in dvss
    # a different raw result (other test data) gets its own raw row, and runs on other test data are never compared:
    # a bold value is the best of the runs scored on the same data (one network on an easier set won every column)
    loaded[1].metrics["synthetic"]["raw"]["mae_mm"] = 9.0
    sets, rows = results_table(loaded)
    assert [r["kind"] for r in rows] == ["raw", "raw", "run", "run"]
    assert [r["data"] for r in rows if r["kind"] == "run"] == [0, 1]
    assert "**" not in table_markdown(sets, rows)
    # two folders of one run name (one network tested twice, on two test sets) are told apart by their data
    import dataclasses

    twin = dataclasses.replace(loaded[1], name=loaded[0].name)
    sets, rows = results_table([loaded[0], twin])
    assert [r["data"] for r in rows if r["kind"] == "run"] == [0, 1] and "**" not in table_markdown(sets, rows)
    loaded[1].metrics["synthetic"]["raw"]["mae_mm"] = loaded[0].metrics["synthetic"]["raw"]["mae_mm"]
    assert "**40.85**" in table_markdown(*results_table(loaded))


def test_report_html_is_self_contained(runs, tmp_path, capsys):
    root, latest_panel = runs
    out = tmp_path / "report" / "report.html"
    assert main([str(root), "--out", str(out), "--title", "My runs"]) == 0
    captured = capsys.readouterr()
    assert "| dvss | hetero | full | yes | **40.85** |" in captured.out
    assert "broken" in captured.err and "left out" in captured.err
    page = out.read_text()
    assert page.startswith("<!DOCTYPE html>") and "<title>My runs</title>" in page
    assert not re.search(r"(src|href)=\"(?!data:)", page)
    assert "<script" not in page and "<link" not in page and "http" not in page
    uris = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    # comparison plot + learning curves of 2 runs + 1 sample panel
    assert len(uris) == 4
    decoded = [base64.b64decode(u) for u in uris]
    assert latest_panel in decoded
    for blob in decoded:
        img = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.size > 0
    assert "Runs left out" in page and "broken" in page


def test_no_runs_is_an_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "--out", str(tmp_path / "r.html")]) == 2
    assert "no run with a valid metrics.json" in capsys.readouterr().err
    assert main([str(tmp_path / "missing"), "--out", str(tmp_path / "r.html")]) == 2
    assert not (tmp_path / "r.html").exists()


def _guarded_run(root: Path, name: str, mae: float, steps: int, best, raw=7.5) -> Path:
    """A run folder whose metrics.json carries the learned guard's fields, as the training writes them."""
    from tofdenoise.records import learned_verdict

    d = root / name
    write_metrics_json(
        d / "metrics.json",
        {"synthetic": set_entry(_m(40.0 - mae, 0.99, mae * mae, mae), RAW)},
        run=learned_verdict(steps, best, raw),
    )
    (d / "run_info.json").write_text(json.dumps({"backbone": name, "noise": "hetero", "loss": "l1", "run_name": name}))
    return d


def test_report_flags_runs_that_did_not_learn_or_were_not_trained(tmp_path, capsys):
    """A run whose best val MAE is not 5 % below raw is NOT LEARNED, a max_epochs=0 run NOT TRAINED (never
    presented as trained): a visible column in Markdown and HTML, red rows, and no bold 'best' value even
    when its numbers are the best of the table."""
    root = tmp_path / "runs"
    _guarded_run(root, "good", 3.0, 900, 2.9)  # 2.9 <= 0.95 x 7.5 = 7.125: learned
    _guarded_run(root, "fair", 4.0, 900, 7.1)  # 7.1 <= 7.125: learned, just
    _guarded_run(root, "flat", 2.0, 900, 7.4)  # 7.4 > 7.125: did not learn (its test MAE looks best)
    _guarded_run(root, "zero", 1.0, 0, None, None)  # trainer.max_epochs=0
    _guarded_run(root, "noval", 2.5, 10, None)  # trained, but no validation result
    out = tmp_path / "r.html"
    assert main([str(root), "--out", str(out)]) == 0
    md = capsys.readouterr().out.splitlines()
    line = {n: next(row for row in md if row.startswith(f"| {n} ")) for n in ("good", "flat", "zero", "noval")}
    assert line["good"].startswith("| good | hetero | l1 | yes | **37.00** |")
    assert next(row for row in md if row.startswith("| fair ")).startswith("| fair | hetero | l1 | yes | 36.00 |")
    assert line["flat"].startswith("| flat | hetero | l1 | NOT LEARNED | 38.00 |")
    assert line["zero"].startswith("| zero | hetero | l1 | NOT TRAINED | 39.00 |")
    assert line["noval"].startswith("| noval | hetero | l1 | unverified | 37.50 |")
    for n in ("flat", "zero", "noval"):
        assert "**" not in line[n]
    assert "**3.00** |" in line["good"]  # the best MAE among the runs that learned
    page = out.read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r'<tr class="[^"]*" title="(\w+)">.*?</tr>', page)}
    assert 'class="run flagged"' in rows["flat"] and ">NOT LEARNED</td>" in rows["flat"]
    assert 'class="run flagged"' in rows["zero"] and ">NOT TRAINED</td>" in rows["zero"]
    assert 'class="run"' in rows["good"] and ">yes</td>" in rows["good"] and "<b>" in rows["good"]
    assert "<b>" not in rows["flat"] + rows["zero"]
    assert "did not learn: best val MAE 7.40 mm vs raw 7.50 mm (needs &lt;= 7.12 mm" in page
    assert "not trained: 0 optimiser steps" in page
    run = load_run(root / "flat")
    assert sorted(run.metrics) == ["synthetic"] and run.learned["learned"] is False


def test_classical_row_is_listed_as_classical_and_can_be_best(tmp_path, capsys):
    """A classical filter's metrics.json (0 steps, learned False, method_kind classical) is a plain row of the
    table: "classical" in the Learned column, not red, and bold where it is best."""
    from tofdenoise.records import classical_verdict

    root = tmp_path / "runs"
    _guarded_run(root, "net", 3.0, 900, 2.9)
    d = root / "bilateral"
    write_metrics_json(
        d / "metrics.json", {"synthetic": set_entry(_m(39.0, 0.995, 6.0, 2.5), RAW)}, run=classical_verdict(2.6, 7.5)
    )
    (d / "run_info.json").write_text(
        json.dumps(
            {
                "backbone": "bilateral",
                "method": "bilateral (classical)",
                "noise": "hetero",
                "loss": "none",
                "run_name": "bilateral",
            }
        )
    )
    out = tmp_path / "r.html"
    assert main([str(root), "--out", str(out)]) == 0
    md = capsys.readouterr().out
    row = next(r for r in md.splitlines() if r.startswith("| bilateral (classical) "))
    assert row.startswith("| bilateral (classical) | hetero | none | classical | **39.00** |")
    assert row.endswith("| **2.50** |")
    page = out.read_text()
    html_row = re.search(r'<tr class="([^"]*)" title="bilateral">.*?</tr>', page)
    assert html_row.group(1) == "run" and ">classical</td>" in html_row.group(0)
    assert "classical method: no trainable parameters" in page


@pytest.mark.parametrize(
    "rel",
    [
        "dvss-hetero-full/metrics.json",
        "dvss-hetero-full/run_info.json",
        "dvss-hetero-full/metrics.html",
        "report.txt",
        "dvss-hetero-full",
    ],
)
def test_out_that_would_replace_a_run_record_is_refused(runs, capsys, rel):
    root = runs[0]
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert main([str(root), "--out", str(root / rel)]) == 2
    err = capsys.readouterr().err
    assert "error: --out" in err and str(root / rel) in err
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before  # nothing replaced


def test_out_html_outside_or_new_in_the_runs_folder_is_fine(runs):
    root = runs[0]
    assert main([str(root), "--out", str(root / "report.html")]) == 0
    assert (root / "report.html").read_text().startswith("<!DOCTYPE html>")
    assert main([str(root), "--out", str(root / "report.html")]) == 0  # a report may replace itself
