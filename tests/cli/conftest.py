"""Shared fixtures of the entry-point tests: one data cache per session and tiny run settings."""

from __future__ import annotations

import pytest

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


@pytest.fixture
def own_camera_file():
    """A factory: ``own_camera_file(folder)`` writes a camera of the user's own as a calibration file (the
    default with another dark noise), what ``++data.sensor=<file>`` points at, and returns
    ``(calibration, path)``."""
    from tofdenoise.physics.calibration import SensorCalibration, resolve_calibration, save_calibration

    def write(folder):
        own = SensorCalibration.from_dict({**resolve_calibration(None).to_dict(), "dark_std_e": 55.0})
        return own, save_calibration(own, folder / "mycam" / "calibration.yaml")

    return write


@pytest.fixture(scope="session")
def data_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("data-cache")


@pytest.fixture
def tiny():
    return tiny_overrides
