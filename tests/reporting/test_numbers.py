"""One set of metric columns, one number formatter and one reader of stored numbers (reporting.numbers), shared by
tofdenoise report's table, the results page, the robustness table and the paper's tables."""

from __future__ import annotations

import math

from tofdenoise.experiments.tables import TABLE_COLUMNS, column_metric, column_source, metric_value
from tofdenoise.records import METRIC_KEYS, json_number
from tofdenoise.reporting.numbers import METRIC_COLUMNS, format_number, read_number


def test_metric_columns_are_the_schema_metrics():
    assert sorted(c.key for c in METRIC_COLUMNS) == sorted(METRIC_KEYS)


def test_table_columns_name_a_set_and_a_metric():
    assert column_source("mae_mm") == ("synthetic", "mae_mm")
    assert column_source("real_psnr_db") == ("real", "psnr_db")
    assert column_metric("real_mae_mm").decimals == 2 and column_metric("ssim").decimals == 4
    for cols in TABLE_COLUMNS.values():
        for c in cols:
            column_source(c)  # every column of every table names a metric


def test_format_number():
    assert format_number(1.23456, 2) == "1.23"
    assert format_number(12.0, 0) == "12"
    assert format_number(None) == "-" and format_number(math.nan) == "-"
    assert format_number(None, 2, "–") == "–"
    assert format_number(math.inf) == "inf" and format_number(-math.inf) == "-inf"


def test_read_number_reads_what_json_number_writes():
    for v in (1.5, math.inf, -math.inf, 3):
        assert read_number(json_number(v)) == v
    assert read_number(json_number(math.nan)) is None
    assert read_number("not a number") is None
    metrics = {"synthetic": {"mae_mm": 2.0, "psnr_db": "inf", "raw": {"mae_mm": 7.0}}}
    assert metric_value(metrics, "mae_mm") == 2.0 and metric_value(metrics, "psnr_db") == math.inf
    assert metric_value(metrics, "mae_mm", raw=True) == 7.0 and math.isnan(metric_value(metrics, "real_mae_mm"))
