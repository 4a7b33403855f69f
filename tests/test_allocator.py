"""keep_freed_memory: a freed large tensor's pages are reused by the next allocation (page faults counted in a fresh
interpreter), the environment it exports, and the opt-out."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tofdenoise import allocator

pytestmark = pytest.mark.skipif(allocator._glibc() is None, reason="glibc's mallopt only")

# Runs a small "frame" (a convolution and two elementwise ops on 64 MiB tensors, above glibc's largest dynamic mmap
# threshold) six times; prints the minor page faults of the last four.
_PROBE = """
import json, os, resource, sys
import torch
from tofdenoise.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else False
torch.set_num_threads(1)
x = torch.rand(1, 16, 1024, 1024)
conv = torch.nn.Conv2d(16, 16, 3, padding=1)
def frame():
    with torch.no_grad():
        return float((torch.sigmoid(conv(x) * 2.0) + x)[0, 0, 0, 0])
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
frame(); frame()
before = faults()
for _ in range(4):
    frame()
print(json.dumps({"applied": applied, "faults": faults() - before,
                  "env": {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")}}))
"""
TENSOR_PAGES = (64 << 20) // 4096


def _probe(mode: str, extra_env: dict[str, str] | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env.pop(allocator.ENV, None)
    env.update(extra_env or {})
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, env=env, timeout=120, check=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_freed_pages_are_reused_after_keep_freed_memory():
    plain = _probe("plain")
    kept = _probe("keep")
    assert plain["applied"] is False and kept["applied"] is True
    # glibc's default maps every frame's tensors afresh and unmaps them when freed: their pages fault in every frame
    # (measured: 24 tensors' worth in the four frames)
    assert plain["faults"] >= 16 * TENSOR_PAGES
    # kept: the frames after the first two reuse the heap's pages. Where a freed block is split by a later allocation
    # the heap grows once more, by at most one frame's four fresh tensors in all (measured on the 2-core CI machine:
    # none in most runs, one tensor's worth now and then, three once in a full test run), against the 24 tensors'
    # worth (at least 16) of glibc's default
    assert kept["faults"] <= 4 * TENSOR_PAGES
    assert kept["env"] == allocator.malloc_environment()


def test_default_leaves_the_allocator_and_the_environment_alone():
    probe = _probe("keep", {allocator.ENV: "default"})
    assert probe["applied"] is False
    assert probe["faults"] >= 16 * TENSOR_PAGES
    assert probe["env"] == {}


def test_a_bad_setting_is_named():
    with pytest.raises(ValueError, match="TOFDENOISE_MALLOC='fast'.*'keep'.*'default'"):
        allocator.keep_freed_memory({allocator.ENV: "fast"})


def test_a_users_own_malloc_variable_wins(monkeypatch):
    monkeypatch.setattr(allocator, "_applied", False)
    monkeypatch.setattr(allocator, "_glibc", lambda: type("Libc", (), {"mallopt": staticmethod(lambda p, v: 1)})())
    env = {"MALLOC_TOP_PAD_": "0"}
    assert allocator.keep_freed_memory(env) is True
    assert env["MALLOC_TOP_PAD_"] == "0"
    assert env["MALLOC_MMAP_THRESHOLD_"] == str(allocator.MMAP_THRESHOLD_BYTES)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux's /proc")
def test_peak_rss_of_a_subprocess_is_its_own_not_its_parents():
    """A parent holding 300 MiB starts a small interpreter: the child's peak is well under the parent's size
    (``ru_maxrss`` would report at least the parent's resident set at the fork), and the parent's own peak
    covers what it touched."""
    ballast = bytearray(300 << 20)
    ballast[::4096] = b"x" * len(ballast[::4096])  # touch every page
    code = "from tofdenoise.allocator import peak_rss_bytes; print(peak_rss_bytes())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    child = int(done.stdout.strip().splitlines()[-1])
    assert 1 << 20 < child < 200 << 20
    assert allocator.peak_rss_bytes() > 300 << 20
    del ballast
