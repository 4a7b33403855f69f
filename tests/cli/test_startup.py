"""Commands that start fast (issue 42): ``tofdenoise --help``, ``tofdenoise <verb> --help`` and a refused argument
import none of the heavy libraries before the arguments are checked.

Each command runs in a fresh interpreter, and the test reads which top-level packages it imported (``sys.modules``)
rather than its wall time, which a loaded machine would make meaningless; ``benchmarks/bench_startup.py`` measures
the time (docs/benchmarks.md, "Start-up").
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: what a help text or a refusal must not import: the training stack, the config composer, array and image libraries
HEAVY = (
    "torch",
    "lightning",
    "pytorch_lightning",
    "torchmetrics",
    "hydra",
    "omegaconf",
    "numpy",
    "scipy",
    "cv2",
    "PIL",
    "matplotlib",
    "onnx",
    "onnxruntime",
    "wandb",
)

#: runs ``tofdenoise`` with the arguments, then prints its exit status and the heavy packages it imported
CHILD = f"""
import json, sys
from tofdenoise.cli.main import main
try:
    status = main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
heavy = sorted({{m.partition(".")[0] for m in sys.modules}} & set({HEAVY!r}))
print("\\n" + json.dumps({{"status": status, "heavy": heavy}}), file=sys.stderr)
"""


def _run(args: list[str], cwd: Path, extra_env: dict[str, str] | None = None, timeout: float = 120) -> dict:
    """``tofdenoise <args>`` in a fresh interpreter (the environment plus ``extra_env``): its exit status, the heavy
    packages it imported, its stdout and its stderr."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}
    env.pop("HYDRA_FULL_ERROR", None)  # Hydra's one-paragraph error, as a user sees it
    env.update(extra_env or {})
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stderr.strip().splitlines()[-1])
    return {**result, "stdout": proc.stdout, "stderr": proc.stderr}


def _imported(args: list[str], cwd: Path) -> tuple[int, list[str], str]:
    """(exit status, heavy packages imported, stderr) of ``tofdenoise <args>`` in a fresh interpreter."""
    result = _run(args, cwd)
    return result["status"], result["heavy"], result["stderr"]


HELP = [
    ["--help"],
    ["train", "--help"],
    ["classic", "--help"],
    ["denoise", "--help"],
    ["export", "--help"],
    ["evaluate", "--help"],
    ["report", "--help"],
    ["grid", "--help"],
    ["reproduce", "--help"],
    ["sensor", "--help"],
    ["sensor", "sigma", "--help"],
    ["sensor", "realset", "--help"],
]

REFUSED = [
    (["denoise", "missing.npy", "--ckpt", "nope.ckpt", "--out", "out"], "input not found: missing.npy"),
    (["denoise", "--bogus"], "the following arguments are required"),
    (["denoise", "frames", "--ckpt", "nope.ckpt", "--out", "out"], "checkpoint file not found: nope.ckpt"),
    (["denoise", "frames", "--onnx", "nope.onnx", "--out", "out"], "ONNX model nope.onnx does not exist"),
    (["denoise", "frames", "--ckpt", "a.ckpt", "--out", "out", "--tile", "8"], "--tile must be >= 32"),
    (["export", "nope.ckpt", "--onnx", "x.onnx"], "checkpoint file not found: nope.ckpt"),
    (["evaluate", "--out", "x.json"], "give --pred DIR --ref DIR"),
    (["evaluate", "--pred", "p", "--ckpt", "a.ckpt", "--out", "x.json"], "not both"),
    (["report", "runs", "--out", "r.html", "--bogus"], "unrecognized arguments: --bogus"),
    (["grid", "robustness", "--out", "runs", "--losses", "nope"], "invalid choice: 'nope'"),
    (["reproduce", "--table", "9"], "invalid choice: '9'"),
    (["reproduce"], "give --table 1|2|3"),
    (["sensor", "bogus"], "invalid choice: 'bogus'"),
    (["sensor", "sigma", "--depth-mm", "1000"], "the following arguments are required"),
    (["nope"], "unknown verb 'nope'"),
]


@pytest.mark.parametrize("args", HELP, ids=lambda a: " ".join(a))
def test_help_imports_nothing_heavy(args, tmp_path):
    status, heavy, err = _imported(args, tmp_path)
    assert status == 0, err[-2000:]
    assert heavy == [], f"tofdenoise {' '.join(args)} imported {heavy}"


@pytest.mark.parametrize(("args", "message"), REFUSED, ids=lambda a: " ".join(a) if isinstance(a, list) else "")
def test_a_refused_argument_is_one_line_before_anything_heavy_is_imported(args, message, tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "a.ckpt").write_bytes(b"not read: the argument is refused first")
    status, heavy, err = _imported(args, tmp_path)
    assert status == 2, err[-2000:]
    assert message in err and "Traceback" not in err
    assert heavy == [], f"tofdenoise {' '.join(args)} imported {heavy}"


def test_a_bad_hydra_override_imports_no_training_stack(tmp_path):
    """A Hydra verb composes its config to refuse an override (Hydra and omegaconf): no torch, no Lightning."""
    training = {"torch", "lightning", "torchmetrics", "numpy", "scipy", "cv2", "matplotlib", "onnxruntime"}
    status, heavy, err = _imported(["train", "backbone=nope"], tmp_path)
    assert status == 1, err[-2000:]  # Hydra's own exit status for a config it cannot compose
    assert "Could not find 'backbone/nope'" in err
    assert not training & set(heavy), f"tofdenoise train backbone=nope imported {sorted(training & set(heavy))}"


def test_train_help_lists_the_config_groups_and_the_installed_launchers(capsys):
    """``tofdenoise train --help`` is read from configs/ (Hydra's own help composes the config once per option of
    every group: seconds); it names every group's options and the launchers of the ``launchers`` extra."""
    from tofdenoise.cli.main import main

    assert main(["train", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: tofdenoise train ")
    groups = {line.split()[0]: line.split(None, 1)[1] for line in out.splitlines() if line.startswith("  ")}
    assert "unet" in groups["backbone"] and "recipe" in groups["hparams_search"] and "cli" not in groups
    assert groups["hydra/launcher"].startswith("basic, joblib, submitit_local, submitit_slurm")


def test_lightning_help_is_built_once_then_read_without_torch(tmp_path):
    """``tofdenoise fit --help`` builds LightningCLI's text (torch and Lightning imported) and stores it; the next call
    prints the same text and imports nothing heavy; with the cache off every call builds it again."""
    env = {"TOFDENOISE_CACHE_DIR": str(tmp_path / "cache")}
    first = _run(["fit", "--help"], tmp_path, env, timeout=300)
    second = _run(["fit", "--help"], tmp_path, env, timeout=300)
    assert first["status"] == second["status"] == 0
    assert "lightning" in first["heavy"] and second["heavy"] == []
    assert second["stdout"] == first["stdout"]
    assert first["stdout"].startswith("usage: tofdenoise [options] fit") and "--trainer.max_epochs" in first["stdout"]
    assert len(list((tmp_path / "cache" / "cli-help").glob("fit-*.txt"))) == 1
    # another argument besides --help is never answered from the cache
    other = _run(["fit", "--print_config", "--help"], tmp_path, env, timeout=300)
    assert "lightning" in other["heavy"]
