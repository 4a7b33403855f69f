"""The resumable CSV log: rows after the checkpoint are dropped, everything before is kept, columns line up."""

from __future__ import annotations

import csv

from tofdenoise.callbacks.csv_log import KeepingExperimentWriter, drop_rows_from_step


def _write(path, header, rows):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def _read(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_drop_rows_from_step_keeps_earlier_and_stepless_rows(tmp_path):
    path = tmp_path / "metrics.csv"
    _write(path, ["step", "loss"], [[0, 1.0], [1, 0.9], [2, 0.8], [2, ""], ["", 7.0], [3, 0.7]])
    header, dropped = drop_rows_from_step(path, 2)
    assert header == ["step", "loss"] and dropped == 3
    assert [(r["step"], r["loss"]) for r in _read(path)] == [("0", "1.0"), ("1", "0.9"), ("", "7.0")]
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.csv"]  # atomic: no temporary file left
    assert drop_rows_from_step(tmp_path / "missing.csv", 0) == ([], 0)


def test_writer_keeps_the_file_and_lines_up_with_its_header(tmp_path):
    # a header in a non-sorted order: Lightning appends in sorted key order, so the file is re-sorted first
    _write(tmp_path / "metrics.csv", ["val/mae_mm", "step", "epoch"], [[3.5, 2, 0]])
    writer = KeepingExperimentWriter(str(tmp_path))  # Lightning's writer would delete metrics.csv here
    with open(tmp_path / "metrics.csv") as fh:
        assert fh.readline().strip() == "epoch,step,val/mae_mm"
    writer.log_metrics({"val/mae_mm": 3.0, "epoch": 1}, step=5)
    writer.save()
    assert _read(tmp_path / "metrics.csv") == [
        {"val/mae_mm": "3.5", "step": "2", "epoch": "0"},
        {"val/mae_mm": "3.0", "step": "5", "epoch": "1"},
    ]
    writer.log_metrics({"train/loss": 0.5}, step=6)  # a new column extends the header, old rows kept
    writer.save()
    rows = _read(tmp_path / "metrics.csv")
    assert [r["step"] for r in rows] == ["2", "5", "6"] and rows[2]["train/loss"] == "0.5"
    assert writer.drop_from_step(5) == 2
    assert [r["step"] for r in _read(tmp_path / "metrics.csv")] == ["2"]
