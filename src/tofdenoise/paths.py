"""Repository locations used to find shipped configuration files.

`REPO_ROOT` is the checkout root (the folder holding `configs/`). The package lives in a src layout
(`REPO_ROOT/src/tofdenoise/paths.py`), so the root is two levels above the package folder. The
environment variable `TOFDENOISE_ROOT` overrides it (e.g. for a wheel installed away from a checkout).
"""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR: Path = Path(__file__).resolve().parent


def _find_repo_root() -> Path:
    override = os.environ.get("TOFDENOISE_ROOT")
    if override:
        return Path(override).expanduser().resolve()
    candidate = PACKAGE_DIR.parent.parent
    if (candidate / "configs").is_dir():
        return candidate
    # Fall back to the current working directory when it looks like a checkout.
    cwd = Path.cwd()
    if (cwd / "configs").is_dir():
        return cwd
    return candidate


REPO_ROOT: Path = _find_repo_root()
CONFIG_DIR: Path = REPO_ROOT / "configs"
SENSOR_CONFIG_DIR: Path = CONFIG_DIR / "sensor"
DEFAULT_SENSOR_CONFIG: Path = SENSOR_CONFIG_DIR / "default.yaml"

__all__ = ["PACKAGE_DIR", "REPO_ROOT", "CONFIG_DIR", "SENSOR_CONFIG_DIR", "DEFAULT_SENSOR_CONFIG"]
