"""Shared test set-up: offline wandb, deterministic seeds, GPU tests skipped without CUDA."""

from __future__ import annotations

import os

import pytest
import torch

# Without a GPU the Triton scan kernels are tested in Triton's interpreter (CPU tensors); the switch must be set
# before tofdenoise.models.scan_triton is imported. With a GPU they are compiled and run on it.
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
    yield


def save_restorer_checkpoint(path, **hparams):
    """A DepthRestorer checkpoint (untrained tiny U-Net unless ``hparams`` say otherwise) in Lightning's format."""
    import lightning
    import torch

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
