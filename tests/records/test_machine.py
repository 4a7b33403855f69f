"""The machine a record names (tofdenoise.records.provenance.host_machine / record_machine)."""

from __future__ import annotations

import os
import platform

import pytest

from tofdenoise.records import host_machine, record_machine

# two processors of a Linux /proc/cpuinfo, cut to the lines that matter (a KVM guest: the model name without its
# generation, which the family / model numbers give)
CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
flags\t\t: fpu avx512f

processor\t: 1
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 143
model name\t: Intel(R) Xeon(R) Platinum 8480+
"""


def test_host_machine_reads_the_first_processor_of_cpuinfo(tmp_path):
    path = tmp_path / "cpuinfo"
    path.write_text(CPUINFO)
    got = host_machine(path)
    assert got["cpu"] == "AMD EPYC" and got["cpu_id"] == "AuthenticAMD 25/17"
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert got["cpu_count"] == usable and got["arch"] == platform.machine() and got["system"] == platform.system()


def test_host_machine_without_cpuinfo_names_what_the_platform_tells(tmp_path):
    got = host_machine(tmp_path / "missing")
    assert got["cpu"] == (platform.processor() or None) and got["cpu_id"] is None
    assert set(got) == {"cpu", "cpu_id", "cpu_count", "arch", "system", "runs_at_once"}


def test_host_machine_says_how_many_runs_shared_it(tmp_path, monkeypatch):
    from tofdenoise.records import RUNS_AT_ONCE_ENV

    monkeypatch.delenv(RUNS_AT_ONCE_ENV, raising=False)
    assert host_machine(tmp_path / "missing")["runs_at_once"] == 1
    monkeypatch.setenv(RUNS_AT_ONCE_ENV, "3")
    assert host_machine(tmp_path / "missing")["runs_at_once"] == 3
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv(RUNS_AT_ONCE_ENV, bad)
        with pytest.raises(ValueError, match=f"TOFDENOISE_RUNS_AT_ONCE={bad!r}: expected a whole number >= 1"):
            host_machine(tmp_path / "missing")


def test_record_machine_reads_a_record_and_is_none_for_older_ones():
    machine = {"cpu": "AMD EPYC", "torch_threads": 2}
    assert record_machine({"commit": "a" * 40, "machine": machine}) == machine
    assert record_machine({"commit": "a" * 40}) is None
    assert record_machine(None) is None and record_machine({"machine": "AMD"}) is None


def test_cpu_label_names_the_model_and_its_family():
    from tofdenoise.records import cpu_label

    assert cpu_label({"cpu": "AMD EPYC", "cpu_id": "AuthenticAMD 25/17"}) == "AMD EPYC (AuthenticAMD 25/17)"
    assert cpu_label({"cpu": "AMD EPYC", "cpu_id": None}) == "AMD EPYC"
    assert cpu_label({"cpu_id": "GenuineIntel 6/143"}) == "(GenuineIntel 6/143)"
    assert cpu_label({}) == ""


def test_written_provenance_names_the_time_the_commit_and_the_machine(tmp_path):
    from datetime import datetime, timezone

    from tofdenoise.records import code_commit, record_commit, written_provenance

    path = tmp_path / "cpuinfo"
    path.write_text(CPUINFO)
    got = written_provenance(path)
    written = datetime.strptime(got["written"], "%Y-%m-%dT%H:%M:%S%z")
    assert abs((datetime.now(timezone.utc) - written).total_seconds()) < 60
    assert record_commit(got) == code_commit()["commit"] and got["commit_dirty"] == code_commit()["commit_dirty"]
    assert record_machine(got) == host_machine(path) and record_machine(got)["cpu_id"] == "AuthenticAMD 25/17"
