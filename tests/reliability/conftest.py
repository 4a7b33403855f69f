"""The reliability probes' world: one small copy of every kind of user file, built once per session and copied for
each case, and the runner that calls a command's real entry point and records what a user would see.

``world`` (a fresh copy per test, ``World``) holds:

- ``frames/a.png`` (16-bit mm), ``frames/sub/b.npy`` (float mm) and their amplitude ``amp/a.npy``, ``amp/sub/b.npy``;
- ``model.ckpt`` (a tiny untrained DepthRestorer checkpoint) and ``calib.yaml`` (the default calibration);
- ``captures/sweep``, ``captures/dark``, ``captures/distances`` (tiny calibration captures, capture format v1);
- ``scenes/scene_000`` (a tiny capture set of one scene, reference built);
- ``pred/``, ``ref/`` (two 16-bit depth maps each, for ``tofdenoise evaluate``);
- ``runs/r1`` (a finished run's records), ``results/`` (``docs/results`` in small: three seeds of two rows and a
  hand-written discussion), ``grid/<run>`` (one finished robustness-grid run);
- ``out/``: where the probes write (empty).
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import json
import os
import resource
import shutil
import signal
import sys
import traceback
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent

#: the size limit (bytes) of a file under the simulated full disk (RLIMIT_FSIZE): every output of the probed
#: commands is larger, and writes beyond it fail with EFBIG as writes to a full disk fail with ENOSPC
FULL_DISK_FILE_LIMIT = 256


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def depth_frame(seed: int, h: int = 36, w: int = 48) -> np.ndarray:
    """A plausible depth frame in mm (800-1100) with a block of holes."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    d = np.rint(800 + 4 * x + 3 * y + rng.normal(0, 5, (h, w))).astype(np.float32)
    d[5:11, 8:16] = 0
    return d


def _records(root: Path) -> None:
    from tofdenoise.records import learned_verdict, set_entry, write_metrics_json

    raw = {"psnr_db": 31.0, "ssim": 0.95, "mse_mm2": 680.0, "mae_mm": 7.2}
    run = root / "runs" / "r1"
    write_metrics_json(
        run / "metrics.json",
        {"synthetic": set_entry({"psnr_db": 40.0, "ssim": 0.99, "mse_mm2": 80.0, "mae_mm": 2.5}, raw)},
        run=learned_verdict(1000, 2.6, 7.2),
    )
    (run / "run_info.json").write_text(json.dumps({"backbone": "unet", "noise": "hetero", "loss": "l1"}))
    # docs/results in small (tests/cli/test_reproduce.py): DVSS hetero and range, L1, seeds 0-2, a discussion
    results = root / "results"
    for seed in range(3):
        for noise, mae in (("hetero", 2.0), ("range", 2.5)):
            d = results / "cpu" / f"dvss-{noise}-l1-s{seed}"
            entry = {"psnr_db": 40.0, "mae_mm": mae + 0.1 * seed, "mse_mm2": 9.0, "ssim": 0.99}
            write_metrics_json(
                d / "metrics.json",
                {"synthetic": set_entry(entry, {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9})},
                run=learned_verdict(1000, mae, 7.0),
            )
            (d / "run_info.json").write_text(json.dumps({"started": "2026-11-22T10:00:00+0000"}))
    (results / "discussion.md").write_text("## Discussion\n\nWritten by hand.\n")
    # one finished run of the robustness grid (tofdenoise grid --table-only reads it)
    grid = root / "grid" / GRID_RUN
    write_metrics_json(
        grid / "metrics.json",
        {"synthetic": set_entry({"psnr_db": 40.0, "ssim": 0.99, "mse_mm2": 80.0, "mae_mm": 2.5}, raw)},
        run=learned_verdict(1000, 2.6, 7.2),
    )
    (grid / "run_info.json").write_text(json.dumps({"finished": True}))


#: the one robustness-grid run of the world (probes.GRID_RUN)
GRID_RUN = "unet-default-hetero-l1-s0"


@pytest.fixture(scope="session")
def world_template(tmp_path_factory) -> Path:
    """The world, built once (a few seconds); each test gets a copy (``world``)."""
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set
    from tofdenoise.data_modules.real_captures import build_reference
    from tofdenoise.physics.calibration import default_calibration, save_calibration
    from tofdenoise.physics.synthetic_captures import write_dark_folder, write_distances_folder, write_sweep_folder

    save_ckpt = _load("_root_conftest_for_probes", REPO / "tests" / "conftest.py").save_restorer_checkpoint
    root = tmp_path_factory.mktemp("probe-world")
    (root / "frames" / "sub").mkdir(parents=True)
    (root / "amp" / "sub").mkdir(parents=True)
    assert cv2.imwrite(str(root / "frames" / "a.png"), depth_frame(0).astype(np.uint16))
    np.save(root / "frames" / "sub" / "b.npy", np.where(depth_frame(1) > 0, depth_frame(1), np.nan))
    for rel in ("a", "sub/b"):
        np.save(root / "amp" / f"{rel}.npy", np.random.default_rng(3).uniform(100, 3000, (36, 48)).astype(np.float32))
    save_ckpt(root / "model.ckpt")
    calib = default_calibration()
    save_calibration(calib, root / "calib.yaml")
    caps = root / "captures"
    write_sweep_folder(calib, caps / "sweep", num_steps=8, num_frames=4, shape=(4, 4))
    write_dark_folder(calib, caps / "dark", num_frames=8, shape=(4, 4))
    write_distances_folder(calib, caps / "distances", np.arange(600.0, 1500.0, 200.0), num_frames=8, shape=(4, 4))
    simulate_capture_set(root / "scenes", scenes=1, frames=4, height=16, width=24, seed=0)
    for scene in sorted((root / "scenes").iterdir()):
        if scene.is_dir():
            build_reference(scene)
    for folder in ("pred", "ref"):
        (root / folder).mkdir()
        for i in range(2):
            d = depth_frame(10 + i) + (0 if folder == "ref" else 3)
            assert cv2.imwrite(
                str(root / folder / f"s{i}.png"), np.where(depth_frame(10 + i) > 0, d, 0).astype(np.uint16)
            )
    _records(root)
    (root / "out").mkdir()
    return root


@dataclass
class World:
    """A copy of the world: ``world / "frames"`` is a path in it."""

    root: Path

    def __truediv__(self, rel: str) -> Path:
        return self.root / rel

    def snapshot(self) -> dict[str, str]:
        """sha256 of every file, by path relative to the root (the input tree's checksums)."""
        return {
            p.relative_to(self.root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(self.root.rglob("*"))
            if p.is_file()
        }


@pytest.fixture
def world(world_template, tmp_path) -> World:
    root = tmp_path / "w"
    shutil.copytree(world_template, root)
    return World(root)


@dataclass
class Outcome:
    """What a user saw: the exit status, stdout, stderr, and the traceback of an exception that escaped the
    command (None when it ended with an exit status)."""

    status: int | None
    out: str
    err: str
    escaped: str | None = None


@contextmanager
def file_size_limit(limit: int):
    """Writes past ``limit`` bytes of a file fail with EFBIG, as writes to a full disk fail with ENOSPC (SIGXFSZ,
    whose default action kills the process, is ignored meanwhile)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def call_entry(script: str, argv: list[str], monkeypatch, full_disk: bool | int = False) -> Outcome:
    """Run console script ``script`` (``tofdenoise``, the only one) in this process through its installed entry point
    with ``argv`` (``<verb> ...``; the dispatcher hands the Hydra and LightningCLI verbs their ``sys.argv``).
    HYDRA_FULL_ERROR is unset, as for a user. ``full_disk``: writes past FULL_DISK_FILE_LIMIT bytes of a file fail
    (a number: past that many bytes)."""
    from importlib import import_module
    from importlib.metadata import entry_points

    (ep,) = [e for e in entry_points(group="console_scripts") if e.name == script]
    module, func = ep.value.split(":")
    main = getattr(import_module(module), func)
    monkeypatch.setattr(sys, "argv", [script, *argv])
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    out, err = io.StringIO(), io.StringIO()
    status, escaped = None, None
    size = FULL_DISK_FILE_LIMIT if full_disk is True else int(full_disk)
    limit = file_size_limit(size) if full_disk else _nothing()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            with limit:
                result = main(argv)
            status = 0 if result is None else int(result)
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            if not isinstance(exc.code, (int, type(None))):
                err.write(f"{exc.code}\n")
        except BaseException:  # what the user would see as a traceback
            escaped = traceback.format_exc()
    _release_locks()
    return Outcome(status, out.getvalue(), err.getvalue(), escaped)


@contextmanager
def _nothing():
    yield


def _release_locks() -> None:
    from tofdenoise.run_lock import release_all

    release_all()


@pytest.fixture
def call(monkeypatch):
    """``call(script, argv, full_disk=False) -> Outcome``: the real entry point, in this process."""

    def run(script: str, argv: list[str], full_disk: bool | int = False) -> Outcome:
        return call_entry(script, [str(a) for a in argv], monkeypatch, full_disk)

    return run


def script_env() -> dict[str, str]:
    """The environment of a console script run as a separate process (offline wandb, no full Hydra errors)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "WANDB_MODE": "offline"}
    env.pop("HYDRA_FULL_ERROR", None)
    return env
