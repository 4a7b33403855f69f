"""data.source + data.source_kwargs: a source's own settings reach it as one group, checked against what the
source declares (``config_keys()``); what the datamodule supplies (seed, calibration) reaches it through
``SourceContext``; the cache key (the source's description) is the one of the former per-source parameters."""

from __future__ import annotations

import inspect
import json
from typing import Any

import numpy as np
import pytest

from tofdenoise.data_modules import ToFDataModule
from tofdenoise.data_modules.cache import canonical_digest
from tofdenoise.data_modules.sources import (
    DATA_SOURCES,
    RawSample,
    SourceContext,
    available_sources,
    check_source_kwargs,
    init_keywords,
    register_source,
    source_from_config,
)
from tofdenoise.physics.calibration import resolve_calibration

SCENES = {"num_samples": 3, "height": 16, "width": 24}


def test_every_source_declares_its_settings_and_none_is_a_datamodule_parameter():
    """Adding a source adds nothing to ToFDataModule: no source setting is one of its parameters."""
    datamodule = set(inspect.signature(ToFDataModule.__init__).parameters)
    assert {"source", "source_kwargs"} <= datamodule
    expected = {
        "procedural": [
            "num_samples",
            "height",
            "width",
            "min_depth_mm",
            "max_depth_mm",
            "hfov_deg",
            "max_depth_fraction",
        ],
        "folder": [
            "root",
            "list_file",
            "depth_unit_mm",
            "min_valid_mm",
            "max_valid_mm",
            "depth_channel",
            "amplitude_channel",
        ],
        "flyingthings3d": ["root", "list_files", "hfov_deg", "min_valid_mm", "max_valid_mm"],
    }
    assert sorted(available_sources()) == sorted(expected)
    for name, keys in expected.items():
        assert DATA_SOURCES.get(name).config_keys() == keys, name
        assert not set(keys) & datamodule, name


@pytest.mark.parametrize("source", ["procedural", "folder", "flyingthings3d"])
def test_unknown_key_names_the_key_the_source_and_its_valid_keys(tmp_path, source):
    valid = ", ".join(DATA_SOURCES.get(source).config_keys())
    message = rf"data\.source_kwargs\.colour: not a setting of the {source} source; valid keys: {valid}$"
    with pytest.raises(ValueError, match=message):
        ToFDataModule(source=source, source_kwargs={"colour": 1}, cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match=message):
        check_source_kwargs(source, {"colour": 1})


def test_a_setting_the_datamodule_supplies_is_refused_with_where_it_comes_from(tmp_path):
    with pytest.raises(ValueError, match=r"data\.source_kwargs\.seed: .*procedural source \(seed comes from the "):
        ToFDataModule(source_kwargs={**SCENES, "seed": 4}, cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match=r"data\.source_kwargs must be a mapping of the procedural source's"):
        ToFDataModule(source_kwargs=[300], cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match="unknown data source 'kinect'; valid names: flyingthings3d, folder"):
        check_source_kwargs("kinect", {})


def test_the_datamodule_supplies_the_seed_and_the_calibrations_depth_range(tmp_path):
    cam75 = resolve_calibration("cam75")
    dm = ToFDataModule(source_kwargs=SCENES, seed=3, sensor="cam75", cache_dir=str(tmp_path))
    source = dm.make_source()
    assert source.seed == 3 and (source.height, source.width, source.num_samples) == (16, 24, 3)
    assert source.max_depth_mm == 0.8 * cam75.unambiguous_range_mm  # 80 % of this camera's unambiguous range
    half = ToFDataModule(source_kwargs={**SCENES, "max_depth_fraction": 0.5}, cache_dir=str(tmp_path))
    assert half.make_source().max_depth_mm == 0.5 * resolve_calibration(None).unambiguous_range_mm
    explicit = ToFDataModule(source_kwargs={**SCENES, "max_depth_mm": 1500.0}, sensor="cam75", cache_dir=str(tmp_path))
    assert explicit.make_source().max_depth_mm == 1500.0
    with pytest.raises(ValueError, match=r"data\.source_kwargs\.max_depth_fraction must be in \(0, 1\], got 1.5"):
        ToFDataModule(source_kwargs={**SCENES, "max_depth_fraction": 1.5}, cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match=r"data\.source_kwargs\.num_samples must be >= 1"):
        ToFDataModule(source_kwargs={"num_samples": 0}, cache_dir=str(tmp_path))
    # the folder source needs nothing of the context: its settings are its __init__ arguments
    (tmp_path / "list.txt").write_text("d.npy a.npy\n")
    context = SourceContext(seed=9, calibration=resolve_calibration(None))
    folder = source_from_config("folder", {"root": str(tmp_path), "depth_unit_mm": 1000}, context)
    assert folder.root == tmp_path and folder.depth_unit_mm == 1000.0
    assert init_keywords(type(folder)) == DATA_SOURCES.get("folder").config_keys()


# The source descriptions (and their digests, which name the cache folders) the datamodule built before the
# source's settings moved into data.source_kwargs (ToFDataModule(num_samples=..., height=..., ...), commit
# e09fbf7): the same settings must keep them, or every cached map would be computed again.
PINNED = [
    (
        {},
        {},
        "2764cf873ae1eefb305d0970048f1b39a85f68ea47fd20a4ffec7b670f5b42d0",
        {"height": 480, "max_depth_mm": 2398.339664, "seed": 0, "width": 640},
    ),
    (
        {"num_samples": 300, "height": 144, "width": 192},
        {"signal_route": "physical"},
        "9a70cc6b0b6126c01d4beb64e4a8ddbb573b92c269cef22164e96922447f08d9",
        {"height": 144, "max_depth_mm": 2398.339664, "seed": 0, "width": 192},
    ),
    (
        {"num_samples": 120, "height": 96, "width": 128},
        {"sensor": "cam75", "seed": 1, "signal_route": "physical"},
        "6c2bfdf98d23c9441c84d6c9cc66ef6f199e868f560a4ba7f953fe104ef95794",
        {"height": 96, "max_depth_mm": 1598.8931093333333, "seed": 1, "width": 128},
    ),
    (
        {"num_samples": 5, "height": 32, "width": 40, "min_depth_mm": 400.0, "max_depth_mm": 1800.0, "hfov_deg": 70.0},
        {"seed": 3},
        "cb74a0f53c732686fc7f527ace305ad13bcd2d59f6dcfe260583f8773ab8d0f7",
        {"height": 32, "hfov_deg": 70.0, "max_depth_mm": 1800.0, "min_depth_mm": 400.0, "seed": 3, "width": 40},
    ),
    (
        {"num_samples": 5, "height": 32, "width": 40, "max_depth_fraction": 0.5},
        {},
        "0a2ad42fe53b74c3cdf35963cdd82864ee4d09ae33bca32fff15b0ca797b9637",
        {"height": 32, "max_depth_mm": 1498.96229, "seed": 0, "width": 40},
    ),
]


@pytest.mark.parametrize("source_kwargs, datamodule_kwargs, digest, described", PINNED)
def test_the_source_description_keying_the_cache_is_unchanged(
    tmp_path, source_kwargs, datamodule_kwargs, digest, described
):
    dm = ToFDataModule(source_kwargs=source_kwargs, cache_dir=str(tmp_path), **datamodule_kwargs)
    got = dm.make_source().describe()
    base = {"source": "procedural", "min_depth_mm": 300.0, "hfov_deg": 63.5, "renderer": 2}
    assert got == {**base, **described}
    assert canonical_digest(got) == digest


@pytest.mark.parametrize(
    "sensor, folder",
    [
        (None, "procedural-1ce3b4255ddb/maps-6d80bb75630bffb9"),
        ("cam75", "procedural-04d1f90f99da/maps-2b55407ef71ce588"),
    ],
)
def test_the_map_cache_folder_is_unchanged(tmp_path, sensor, folder):
    """The whole key of the maps (source, calibration, signal route) names the same folder as before."""
    dm = ToFDataModule(
        source_kwargs=SCENES,
        sensor=sensor,
        seed=2,
        crop_size=8,
        holes=False,
        signal_route="physical",
        cache_dir=str(tmp_path),
    )
    dm.prepare_data()
    assert dm.prepared.cache.folder.relative_to(tmp_path).as_posix() == folder
    described = json.loads((dm.prepared.cache.folder.parent / "source.json").read_text())
    assert dm.summary()["source_settings"] == described == dm.make_source().describe()


class _Gradient:
    """A source defined outside the datamodule: ramps of ``size`` x ``size`` pixels, their depth offset by the
    datamodule's seed (what its ``from_config`` takes from the context)."""

    name = "gradient"
    radiometric_amplitude = False

    def __init__(self, count: int = 5, size: int = 12, offset_mm: float = 0.0):
        self.count, self.size, self.offset_mm = count, size, offset_mm

    @classmethod
    def config_keys(cls) -> list[str]:
        return init_keywords(cls, leave_out=("offset_mm",))

    @classmethod
    def from_config(cls, settings: dict[str, Any], context: SourceContext) -> _Gradient:
        return cls(**settings, offset_mm=100.0 * context.seed)

    def sample_ids(self) -> list[str]:
        return [f"g{i}" for i in range(self.count)]

    def check(self) -> None:
        return None

    def load(self, sample_id: str) -> RawSample:
        i = int(sample_id[1:])
        depth = np.linspace(600, 1200, self.size * self.size, dtype=np.float32).reshape(self.size, self.size)
        depth = depth + np.float32(self.offset_mm + 10 * i)
        amplitude = np.linspace(10, 100, depth.size, dtype=np.float32).reshape(depth.shape)
        return RawSample(sample_id, depth, amplitude, np.ones(depth.shape, bool))

    def describe(self) -> dict[str, Any]:
        return {"source": self.name, "count": self.count, "size": self.size, "offset_mm": self.offset_mm}


def test_a_new_source_is_a_registered_class_and_nothing_in_the_datamodule(tmp_path):
    register_source("gradient")(_Gradient)
    try:
        dm = ToFDataModule(
            source="gradient",
            source_kwargs={"count": 5, "size": 12},
            seed=2,
            crop_size=8,
            batch_size=1,
            holes=False,
            cache_dir=str(tmp_path),
        )
        dm.prepare_data()
        dm.setup("fit")
        assert dm.make_source().offset_mm == 200.0  # the seed reached it through the context
        assert sum(len(ids) for ids in dm.splits.values()) == 5
        assert next(iter(dm.train_dataloader()))["clean"].shape == (1, 1, 8, 8)
        with pytest.raises(ValueError, match=r"data\.source_kwargs\.offset_mm: not a setting of the gradient source"):
            ToFDataModule(source="gradient", source_kwargs={"offset_mm": 1.0}, cache_dir=str(tmp_path))
    finally:
        DATA_SOURCES._factories.pop("gradient", None)
