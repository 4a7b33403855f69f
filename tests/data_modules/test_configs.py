"""configs/data/*.yaml and configs/noise/*.yaml instantiate the datamodule the way the Hydra entry point does."""

from __future__ import annotations

import hydra
import pytest
from hydra.errors import InstantiationException
from omegaconf import OmegaConf

from tofdenoise.config import compose_config
from tofdenoise.paths import CONFIG_DIR
from tofdenoise.physics.noise_models import available_noise_models


def compose(tmp_path, data: str, noise: str, **overrides):
    """The real train.yaml composition (its data.noise / data.sensor interpolations included) with data overrides."""
    return compose_config(
        [
            f"data={data}",
            f"noise={noise}",
            f"paths.run_dir={tmp_path}/run",
            f"++data.cache_dir={tmp_path}/cache",
            *(f"data.{k}={v}" for k, v in overrides.items()),
        ]
    )


def test_noise_configs_match_the_physics_registry():
    names = sorted(p.stem for p in (CONFIG_DIR / "noise").glob("*.yaml"))
    assert names == sorted(available_noise_models())
    for name in names:
        node = OmegaConf.load(CONFIG_DIR / "noise" / f"{name}.yaml")
        assert node.name == name and OmegaConf.to_container(node.kwargs) == {}


@pytest.mark.parametrize("noise", ["hetero", "fixed"])
def test_procedural_config_instantiates_and_loads(tmp_path, noise):
    cfg = compose(tmp_path, "procedural", noise, num_samples=5, height=32, width=40, crop_size=16)
    dm = hydra.utils.instantiate(cfg.data, _convert_="all")
    assert type(dm).__name__ == "ToFDataModule" and dm.noise_name == noise
    assert dm.hparams.noise_kwargs == OmegaConf.to_container(cfg.noise.kwargs)
    assert isinstance(dm.hparams.sensor, dict) and dm.calib.num_taps == cfg.sensor.num_taps
    dm.prepare_data()
    dm.setup("fit")
    assert next(iter(dm.train_dataloader()))["noisy"].shape[-2:] == (16, 16)


def test_dataset_configs_ask_for_root(tmp_path, monkeypatch):
    monkeypatch.delenv("TOF_FLYINGTHINGS3D_ROOT", raising=False)
    monkeypatch.delenv("TOFDENOISE_DATA_ROOT", raising=False)
    for data in ("flyingthings3d", "folder"):
        cfg = compose(tmp_path, data, "hetero")
        assert OmegaConf.load(CONFIG_DIR / "data" / f"{data}.yaml")._target_ == "tofdenoise.data_modules.ToFDataModule"
        with pytest.raises(
            InstantiationException, match=rf"ValueError\('the {data} source needs its dataset folder: set data\.root="
        ) as err:
            hydra.utils.instantiate(cfg.data, _convert_="all")
        assert isinstance(err.value.__cause__, ValueError)


@pytest.mark.parametrize("data", ["procedural", "folder", "flyingthings3d"])
def test_documented_real_dir_override_needs_no_plus(tmp_path, data):
    """docs/data.md writes `data.real_dir=SCENES_DIR`: Hydra accepts it because every data config declares it."""
    from tofdenoise.config import compose_config

    cfg = compose_config([f"data={data}", f"paths.run_dir={tmp_path}", f"data.real_dir={tmp_path}/scenes"])
    assert cfg.data.real_dir == f"{tmp_path}/scenes"
    assert compose_config([f"data={data}", f"paths.run_dir={tmp_path}"]).data.real_dir is None
