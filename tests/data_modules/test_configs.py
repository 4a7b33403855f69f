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
    """The real train.yaml composition (its data.noise / data.sensor interpolations included) with data overrides
    (``data.<key>=<value>``; a key with a dot such as ``source_kwargs.num_samples`` reaches into a mapping)."""
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
    sizes = {"source_kwargs.num_samples": 5, "source_kwargs.height": 32, "source_kwargs.width": 40}
    cfg = compose(tmp_path, "procedural", noise, **sizes, crop_size=16)
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
            InstantiationException,
            match=rf"ValueError\('the {data} source needs its dataset folder: set data\.source_kwargs\.root=",
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


@pytest.mark.parametrize(
    "overrides, source",
    [
        (["data=procedural"], "procedural"),
        (["data=folder"], "folder"),
        (["data=flyingthings3d"], "flyingthings3d"),
        (["experiment=smoke"], "procedural"),
        (["experiment=grid"], "procedural"),
        (["experiment=reproduce_cpu"], "procedural"),
        (["experiment=paper"], "flyingthings3d"),
    ],
)
def test_configs_give_a_source_only_its_own_settings(tmp_path, overrides, source):
    """Every data config and experiment writes the source's settings under data.source_kwargs, and only keys of the
    source it selects: experiment=paper (flyingthings3d) gets none of the procedural scene sizes."""
    from tofdenoise.data_modules.sources import DATA_SOURCES, check_source_kwargs

    cfg = compose_config([*overrides, f"paths.run_dir={tmp_path}"])
    data = OmegaConf.to_container(cfg.data, resolve=True)
    assert data["source"] == source
    check_source_kwargs(source, data["source_kwargs"])  # raises on a key the source does not take
    assert not set(DATA_SOURCES.get(source).config_keys()) & set(data)  # none of them at the top of data
    if source == "procedural":
        sizes = {k: data["source_kwargs"][k] for k in ("num_samples", "height", "width")}
        expected = {"procedural": (300, 144, 192), "smoke": (10, 64, 80), "grid": (120, 96, 128)}
        expected["reproduce_cpu"] = (240, 128, 160)
        name = overrides[0].split("=")[1]
        assert tuple(sizes.values()) == expected[name]
    else:
        assert set(data["source_kwargs"]) == {"root"}


def test_a_source_setting_overrides_on_the_command_line(tmp_path):
    cfg = compose_config(
        [f"paths.run_dir={tmp_path}", "data.source_kwargs.num_samples=12", "++data.source_kwargs.hfov_deg=70"]
    )
    assert OmegaConf.to_container(cfg.data.source_kwargs) == {
        "num_samples": 12,
        "height": 144,
        "width": 192,
        "hfov_deg": 70,
    }
    cfg = compose_config(["data=folder", f"paths.run_dir={tmp_path}", f"data.source_kwargs.root={tmp_path}"])
    assert cfg.data.source_kwargs.root == str(tmp_path)
