"""The one reader of run folders (``tofdenoise.records.run_folder``): strict for pages and reports, lenient for
runners, and the same rule of a finished run for all of them."""

from __future__ import annotations

import json

import pytest

from tofdenoise.records import (
    METRICS_NAME,
    RUN_INFO_NAME,
    RecordError,
    learned_verdict,
    load_metrics,
    read_record,
    read_run,
    run_finished,
    set_entry,
    unreadable_records,
    write_metrics_json,
    write_run_info,
)


def _metrics(run_dir):
    entry = set_entry({"psnr_db": 40.0, "mae_mm": 3.5, "mse_mm2": 25.0, "ssim": 0.9}, counts={"images": 2})
    write_metrics_json(run_dir / METRICS_NAME, {"synthetic": entry}, run=learned_verdict(5, 1.5, 15))


def test_a_finished_run_needs_both_records_and_the_finished_stamp(tmp_path):
    assert not run_finished(tmp_path) and read_run(tmp_path) == (None, None)
    write_run_info(tmp_path, {"run_name": "a", "started": "t0"})
    _metrics(tmp_path)
    assert not run_finished(tmp_path)  # tested, not stamped: e.g. killed while writing the records
    write_run_info(tmp_path, {"run_name": "a", "started": "t0", "finished": "t1"})
    info, metrics = read_run(tmp_path)
    assert run_finished(tmp_path) and info["finished"] == "t1" and metrics["synthetic"]["mae_mm"] == 3.5
    assert load_metrics(tmp_path / METRICS_NAME)["synthetic"]["images"] == 2


@pytest.mark.parametrize(
    "text, why", [("{broken", "cannot be read"), ("[1, 2]", r"not a JSON object \(got list\)"), ("", "cannot be read")]
)
def test_a_broken_record_is_named_by_the_strict_readers_and_none_to_the_lenient_one(tmp_path, text, why):
    write_run_info(tmp_path, {"run_name": "a", "finished": "t1"})
    _metrics(tmp_path)
    (tmp_path / RUN_INFO_NAME).write_text(text)
    with pytest.raises(RecordError, match=rf"{RUN_INFO_NAME}: .*{why}"):
        read_record(tmp_path / RUN_INFO_NAME)
    info, metrics = read_run(tmp_path)
    assert info is None and metrics is not None and not run_finished(tmp_path)
    [line] = unreadable_records([tmp_path])
    assert line.startswith(str(tmp_path / RUN_INFO_NAME))


def test_metrics_off_the_schema_are_a_record_error_naming_the_file(tmp_path):
    (tmp_path / METRICS_NAME).write_text(json.dumps({"synthetic": {"mae_mm": "three"}}))
    with pytest.raises(RecordError, match=rf"{METRICS_NAME}: the record cannot be read"):
        load_metrics(tmp_path / METRICS_NAME)
    with pytest.raises(RecordError, match="cannot be read"):
        load_metrics(tmp_path / "missing" / METRICS_NAME)
    assert read_record(tmp_path / "missing.json") is None
