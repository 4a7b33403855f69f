"""Data sources: each yields clean depth (mm), amplitude and a validity mask per sample id.

``data.source`` names one, ``data.source_kwargs`` holds its own settings (``base.source_from_config``). A new source:
a module here with ``@register_source("<name>")``, ``config_keys()`` and ``from_config(settings, context)``, imported
below so that it registers; nothing in the datamodule changes.
"""

from tofdenoise.data_modules.sources.base import (
    DATA_SOURCES,
    DataSource,
    RawSample,
    SourceContext,
    available_sources,
    check_source_kwargs,
    depth_validity,
    init_keywords,
    register_source,
    source_from_config,
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
    "SourceContext",
    "available_sources",
    "check_source_kwargs",
    "depth_validity",
    "generate_scene",
    "init_keywords",
    "radial_to_z",
    "register_source",
    "render_scene",
    "source_from_config",
]
