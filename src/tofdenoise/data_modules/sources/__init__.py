"""Data sources: each yields clean depth (mm), amplitude and a validity mask per sample id."""

from tofdenoise.data_modules.sources.base import DataSource, RawSample, depth_validity
from tofdenoise.data_modules.sources.flyingthings3d import FlyingThings3DSource, radial_to_z
from tofdenoise.data_modules.sources.folder import FolderSource
from tofdenoise.data_modules.sources.procedural import ProceduralSource, generate_scene, render_scene

SOURCES = ("procedural", "flyingthings3d", "folder")

__all__ = ["SOURCES", "DataSource", "FlyingThings3DSource", "FolderSource", "ProceduralSource", "RawSample",
           "depth_validity", "generate_scene", "radial_to_z", "render_scene"]
