"""Data sources: each yields clean depth (mm), amplitude and a validity mask per sample id."""

from tofdenoise.data_modules.sources.base import (
    DATA_SOURCES,
    DataSource,
    RawSample,
    available_sources,
    build_source,
    depth_validity,
    register_source,
)
from tofdenoise.data_modules.sources.flyingthings3d import FlyingThings3DSource, radial_to_z
from tofdenoise.data_modules.sources.folder import FolderSource
from tofdenoise.data_modules.sources.procedural import ProceduralSource, generate_scene, render_scene

__all__ = [
    "DATA_SOURCES",
    "DataSource",
    "FlyingThings3DSource",
    "FolderSource",
    "ProceduralSource",
    "RawSample",
    "available_sources",
    "build_source",
    "depth_validity",
    "generate_scene",
    "radial_to_z",
    "register_source",
    "render_scene",
]
