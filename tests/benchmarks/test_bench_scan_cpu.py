"""The CPU scan benchmark's training-step part runs once per C allocator setting, each in a fresh process (glibc's
``mallopt`` is process-wide), with the run's own settings passed on."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmark code, not the package
import bench_scan_cpu  # noqa: E402


def test_step_part_runs_each_allocator_in_its_own_process(monkeypatch, capsys):
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append(cmd)
        allocator = cmd[cmd.index("--step-allocator") + 1]
        rc = 0 if allocator == "keep" else 1
        return SimpleNamespace(returncode=rc, stdout=f"# header\n| table of {allocator} |\n", stderr="boom\nlast line")

    monkeypatch.setattr(subprocess, "run", fake_run)
    args = SimpleNamespace(step_allocator="both", threads=2, rounds=4, quick=True, baseline="abc123")
    bench_scan_cpu.bench_step(args)
    assert [c[c.index("--step-allocator") + 1] for c in calls] == ["keep", "default"]
    for cmd in calls:
        assert cmd[0] == sys.executable and cmd[cmd.index("--only") + 1] == "step"
        assert cmd[cmd.index("--threads") + 1] == "2" and cmd[cmd.index("--rounds") + 1] == "4"
        assert "--quick" in cmd and cmd[cmd.index("--baseline") + 1] == "abc123"
    out = capsys.readouterr().out
    assert "| table of keep |" in out and "| table of default |" in out and "# header" not in out
    assert "step part (default) failed: ['last line']" in out


def test_step_allocator_option_is_parsed(monkeypatch):
    seen = {}
    monkeypatch.setattr(bench_scan_cpu, "bench_step", lambda args: seen.setdefault("allocator", args.step_allocator))
    monkeypatch.setattr("tofdenoise.models.scan.cpu.cpu_kernel_available", lambda: True)
    threads = str(torch.get_num_threads())  # main() sets torch's threads: leave the test process's as they are
    assert bench_scan_cpu.main(["--only", "step", "--step-allocator", "default", "--threads", threads]) == 0
    assert seen == {"allocator": "default"}
