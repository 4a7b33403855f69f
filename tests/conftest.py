"""Shared test set-up: offline wandb, deterministic seeds, GPU tests skipped without CUDA, caches in the test's
temporary folders."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# Without a GPU the Triton scan kernels are tested in Triton's interpreter (CPU tensors); the switch must be set
# before tofdenoise.models.scan.triton is imported. With a GPU they are compiled and run on it.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from tofdenoise.wandb_env import quiet_wandb  # noqa: E402

quiet_wandb(offline=True)  # WANDB_MODE=offline, quiet (subprocesses inherit it)
os.environ.setdefault("HYDRA_FULL_ERROR", "1")


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except Exception:  # pragma: no cover
        has_cuda = False
    if has_cuda:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def _seed_everything():
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)
    yield


@pytest.fixture(autouse=True)
def _wandb_dirs(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.getbasetemp() / "wandb-home"
    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(base))
    # the help cache of Lightning's verbs (tofdenoise.cli.help_cache) stays out of the user's home
    monkeypatch.setenv("TOFDENOISE_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "tofdenoise-cache"))
    yield


def save_restorer_checkpoint(path, **hparams):
    """A DepthRestorer checkpoint (untrained tiny U-Net unless ``hparams`` say otherwise) in Lightning's format."""
    import lightning
    import torch

    from tofdenoise.training.learned_guard import LEARNED_RECORD_KEY
    from tofdenoise.training.module import DepthRestorer

    kwargs = {"backbone": "unet", "backbone_kwargs": {"width": 8, "stages": 2}, **hparams}
    torch.manual_seed(0)
    model = DepthRestorer(**kwargs)
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": dict(model.hparams),
            "pytorch-lightning_version": lightning.__version__,
            "epoch": 0,
            "global_step": 0,
            LEARNED_RECORD_KEY: {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None},
        },
        path,
    )
    return path


@pytest.fixture(scope="session")
def restorer_ckpt(tmp_path_factory):
    """Path of a tiny untrained DepthRestorer checkpoint (depth only)."""
    return save_restorer_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt")


@pytest.fixture(scope="session")
def make_restorer_ckpt():
    """``save_restorer_checkpoint(path, **hparams)``: writes a tiny DepthRestorer checkpoint."""
    return save_restorer_checkpoint


@pytest.fixture(scope="session")
def write_exr():
    """``write_exr(path, depth)``: the EXR writer of the reader's tests (tests/data_modules/test_exr.py; ZIP
    compression, one FLOAT channel 'Z')."""
    import importlib.util
    from pathlib import Path

    import numpy as np

    spec = importlib.util.spec_from_file_location("_exr_writer", Path(__file__).parent / "data_modules" / "test_exr.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    def write(path, depth) -> None:
        module.write_exr(path, {"Z": np.asarray(depth, dtype=np.float32)}, 3)

    return write


#: image size of the ToF-FlyingThings3D fixture
FT3D_SHAPE = (24, 32)


def _write_ft3d(
    root: Path, train: list[str], test: list[str], gt_dir: str = "gt_depth_rgb", seed: int = 0, shape=FT3D_SHAPE
) -> dict:
    """Write tokens in the published layout; returns {token: (gt_half_scale, conf, amplitude)}."""
    import cv2
    import numpy as np
    import scipy.io

    H, W = shape
    rng = np.random.default_rng(seed)
    (root / gt_dir).mkdir(parents=True, exist_ok=True)
    (root / "nToF").mkdir(parents=True, exist_ok=True)
    (root / "train_list.txt").write_text("\n".join(train) + "\n")
    (root / "test_list.txt").write_text("\n".join(test) + "\n")
    out = {}
    for token in train + test:
        gt = rng.uniform(300, 1500, size=(H, W)).astype(np.float32)  # half scale: x2 -> 600..3000 mm
        gt[0, :3] = 0.0  # no return
        conf = np.ones((H, W), np.uint8)
        conf[5, 5] = 0
        amp = rng.integers(1, 255, size=(H, W), dtype=np.uint8)
        scipy.io.savemat(root / gt_dir / f"{token}_gt_depth.mat", {"gt_depth": gt})
        scipy.io.savemat(root / gt_dir / f"{token}_gt_conf.mat", {"conf": conf})
        cv2.imwrite(str(root / "nToF" / f"{token}_noisy_intensity.png"), amp)
        # the dataset's own noisy depth must never be read: make it garbage
        (root / "nToF" / f"{token}_noisy_depth.mat").write_bytes(b"garbage")
        cv2.imwrite(str(root / gt_dir / f"{token}_rgb.png"), np.zeros((H, W, 3), np.uint8))
        out[token] = (gt, conf, amp)
    return out


@pytest.fixture
def write_ft3d():
    """``write_ft3d(root, train_tokens, test_tokens, gt_dir=..., seed=...)``: a tiny ToF-FlyingThings3D in its
    published layout (.mat v5, PNG, list files) of ``FT3D_SHAPE`` images; returns {token: (gt, conf, amplitude)}."""
    return _write_ft3d


@pytest.fixture
def lock_holder():
    """A context manager factory: ``with lock_holder(run_dir, "other fit") as pid:`` runs another process that
    holds ``run_dir``'s run lock (``tofdenoise.run_lock``) until the block ends, then releases it."""
    import contextlib
    import subprocess
    import sys

    @contextlib.contextmanager
    def hold(run_dir, command: str = "other"):
        script = (
            "import sys; from tofdenoise.run_lock import RunLock; RunLock(sys.argv[1], command=sys.argv[2]).acquire(); "
            "print('ready', flush=True); sys.stdin.read()"
        )
        holder = subprocess.Popen(
            [sys.executable, "-c", script, str(run_dir), command],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert holder.stdout.readline().strip() == "ready"
            yield holder.pid
        finally:
            holder.stdin.close()
            holder.wait(timeout=30)

    return hold


@pytest.fixture(scope="session")
def recording_files():
    """The recording writers of tests/inference/recording_files.py (``write_kinect_mkv``, ``write_bag``,
    ``kinect_calibration_json``); skips when the ``recordings`` extra (PyAV, rosbags) is not installed."""
    import importlib.util

    pytest.importorskip("av")
    pytest.importorskip("rosbags")
    path = Path(__file__).parent / "inference" / "recording_files.py"
    spec = importlib.util.spec_from_file_location("_recording_files", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: small networks per backbone so that fit + test run in seconds on a CPU
TINY_BACKBONE_KWARGS: dict[str, list[str]] = {
    "unet": ["backbone.kwargs.width=8", "backbone.kwargs.stages=2"],
    "dvss": [
        "backbone.kwargs.width=8",
        "backbone.kwargs.enc_blocks=[1]",
        "backbone.kwargs.bottleneck_blocks=1",
        "backbone.kwargs.d_state=4",
    ],
    "restormer": [
        "backbone.kwargs.width=8",
        "backbone.kwargs.blocks=[1,1,1,1]",
        "backbone.kwargs.heads=[1,1,2,2]",
        "backbone.kwargs.refinement_blocks=1",
    ],
    "deeptof": ["backbone.kwargs.channels=[8,8,16,16]"],
    "tofkpn": ["backbone.kwargs.channels=[8,8,16,16]"],
    "rcf": [
        "backbone.kwargs.width=8",
        "backbone.kwargs.hidden=8",
        "backbone.kwargs.steps=2",
        "backbone.kwargs.global_levels=2",
    ],
}
for _variant in ("dvss_no_local", "dvss_no_dwconv", "dvss_se"):
    TINY_BACKBONE_KWARGS[_variant] = TINY_BACKBONE_KWARGS["dvss"]


def tiny_overrides(run_dir, cache_dir, backbone: str = "unet", num_samples: int = 10, **data) -> list[str]:
    """Overrides of a tiny smoke run: ``num_samples`` procedural scenes of 32 x 48 (``data.source_kwargs``, the
    source's own settings); ``data`` updates the other ``data.<key>``."""
    scenes = {"num_samples": num_samples, "height": 32, "width": 48}
    sizes = {"crop_size": 32, "batch_size": 2, **data}
    return (
        [
            f"backbone={backbone}",
            f"paths.run_dir={run_dir}",
            f"++data.cache_dir={cache_dir}",
            "experiment=smoke",
            "trainer.enable_progress_bar=false",
            "trainer.enable_model_summary=false",
        ]
        + [f"data.source_kwargs.{k}={v}" for k, v in scenes.items()]
        + [f"data.{k}={v}" for k, v in sizes.items()]
        + TINY_BACKBONE_KWARGS[backbone]
    )


@pytest.fixture(scope="session")
def tiny():
    """:func:`tiny_overrides`, the overrides of a tiny smoke run (entry-point, resume and reliability tests)."""
    return tiny_overrides
