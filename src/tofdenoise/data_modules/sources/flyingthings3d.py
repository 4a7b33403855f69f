"""ToF-FlyingThings3D reader (Qiu et al., ICCV 2019) in its published layout.

Layout under ``root``::

    train_list.txt, test_list.txt         one sample token per line
    gt_depth_rgb/<token>_gt_depth.mat     key ``gt_depth``: radial depth at HALF scale (x2 -> ~mm)
    gt_depth_rgb/<token>_gt_conf.mat      key ``conf``: 0 = invalid
    nToF/<token>_noisy_intensity.png      8-bit ToF amplitude (the signal cue of the noise model)

Some copies name the ground-truth folder ``gt_depth_rgb_small_pt/``; both are accepted. The dataset's own noisy
depth (``nToF/<token>_noisy_depth.mat``) is NOT read: noisy inputs are synthesised from the ground truth.

Depth: ``gt_depth * 2`` is the radial distance in ~mm; it is converted to z-depth with a pinhole of
63.5 deg horizontal field of view at 640 px (the focal length scales with the width):
z = r / sqrt(x^2 + y^2 + 1), x = (u - W/2) / f, y = (v - H/2) / f.
Valid pixels: finite, gt > 0, conf > 0 and min_valid_mm < r < max_valid_mm (10 and 4095 by default).

Settings (``data.source_kwargs``): every ``__init__`` argument, e.g.
``data=flyingthings3d data.source_kwargs.root=/data/ToF-FlyingThings3D``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.data_modules.io import DataFileError, check_same_shape, read_amplitude, read_mat
from tofdenoise.data_modules.sources.base import (
    RawSample,
    SourceContext,
    init_keywords,
    raise_if_missing,
    read_list_file,
    register_source,
)

GT_DIRS = ("gt_depth_rgb", "gt_depth_rgb_small_pt")
DEFAULT_LISTS = ("train_list.txt", "test_list.txt")
HFOV_DEG = 63.5
GT_SCALE = 2.0


def radial_to_z(radial_mm: np.ndarray, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    """z-depth from radial distance: z = r / sqrt(x^2 + y^2 + 1), f = (W/2)/tan(HFOV/2), x = (u - W/2)/f."""
    height, width = radial_mm.shape
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    xs = (np.arange(width, dtype=np.float64) - width / 2.0) / f
    ys = (np.arange(height, dtype=np.float64) - height / 2.0) / f
    norm = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    return (radial_mm / norm).astype(np.float32)


@register_source("flyingthings3d")
class FlyingThings3DSource:
    """Clean depth (mm, z) + ToF amplitude + validity from a ToF-FlyingThings3D copy."""

    name = "flyingthings3d"

    def __init__(
        self,
        root: str | Path | None = None,
        list_files: list[str] | tuple[str, ...] | None = None,
        hfov_deg: float = HFOV_DEG,
        min_valid_mm: float = 10.0,
        max_valid_mm: float = 4095.0,
    ):
        if root is None or str(root) == "":
            raise ValueError(
                "the flyingthings3d source needs its dataset folder: "
                "set data.source_kwargs.root=/path/to/ToF-FlyingThings3D"
            )
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(
                f"ToF-FlyingThings3D root not found: {self.root} (set data.source_kwargs.root to the dataset folder)"
            )
        self.list_files = tuple(list_files) if list_files else None
        self.hfov_deg = float(hfov_deg)
        self.min_valid_mm, self.max_valid_mm = float(min_valid_mm), float(max_valid_mm)
        self._ids: list[str] | None = None
        self._gt_dir: Path | None = None

    @classmethod
    def config_keys(cls) -> list[str]:
        """``data.source_kwargs``: every ``__init__`` argument."""
        return init_keywords(cls)

    @classmethod
    def from_config(cls, settings: dict[str, Any], context: SourceContext) -> FlyingThings3DSource:
        """The datamodule supplies nothing the dataset needs: ``settings`` are the ``__init__`` arguments."""
        return cls(**settings)

    # ------------------------------------------------------------------ listing
    def _list_paths(self) -> list[Path]:
        if self.list_files is not None:
            return [self.root / name for name in self.list_files]
        found = [self.root / name for name in DEFAULT_LISTS if (self.root / name).is_file()]
        if not found:
            raise FileNotFoundError(
                f"no list file in {self.root}: expected {' or '.join(DEFAULT_LISTS)} "
                "(or set data.source_kwargs.list_files)"
            )
        return found

    def sample_ids(self) -> list[str]:
        if self._ids is None:
            ids: list[str] = []
            seen: set[str] = set()
            for path in self._list_paths():
                for token in read_list_file(path, what="ToF-FlyingThings3D list file"):
                    token = token.split()[0]
                    if token not in seen:
                        seen.add(token)
                        ids.append(token)
            self._ids = ids
        return list(self._ids)

    def gt_dir(self) -> Path:
        if self._gt_dir is None:
            for name in GT_DIRS:
                if (self.root / name).is_dir():
                    self._gt_dir = self.root / name
                    break
            else:
                raise FileNotFoundError(
                    f"ToF-FlyingThings3D ground truth folder not found under {self.root}: "
                    f"expected {' or '.join(GT_DIRS)}/"
                )
        return self._gt_dir

    def paths(self, token: str) -> dict[str, Path]:
        gt = self.gt_dir()
        return {
            "depth": gt / f"{token}_gt_depth.mat",
            "conf": gt / f"{token}_gt_conf.mat",
            "amplitude": self.root / "nToF" / f"{token}_noisy_intensity.png",
        }

    def files(self, sample_id: str) -> list[Path]:
        """The depth, confidence and amplitude file of a sample: their stamps key its cached maps."""
        return list(self.paths(sample_id).values())

    def check(self) -> None:
        """Every listed token must have its three files (reported before training, with the first misses)."""
        missing = [str(p) for token in self.sample_ids() for p in self.paths(token).values() if not p.is_file()]
        raise_if_missing(missing, f"ToF-FlyingThings3D at {self.root}")

    # ------------------------------------------------------------------ reading
    def load(self, sample_id: str) -> RawSample:
        paths = self.paths(sample_id)
        gt = read_mat(paths["depth"], "gt_depth", what="ToF-FlyingThings3D depth").astype(np.float32)
        if gt.ndim != 2:
            raise DataFileError(f"ToF-FlyingThings3D depth file {paths['depth']} has shape {gt.shape}; expected (H, W)")
        conf = read_mat(paths["conf"], "conf", what="ToF-FlyingThings3D confidence")
        check_same_shape(
            gt, conf, reference_path=paths["depth"], other_path=paths["conf"], what="ToF-FlyingThings3D confidence"
        )
        amplitude = read_amplitude(paths["amplitude"], what="ToF-FlyingThings3D amplitude")
        check_same_shape(
            gt,
            amplitude,
            reference_path=paths["depth"],
            other_path=paths["amplitude"],
            what="ToF-FlyingThings3D amplitude",
        )
        radial_mm = gt * np.float32(GT_SCALE)
        with np.errstate(invalid="ignore"):
            valid = (
                np.isfinite(radial_mm)
                & (gt > 0)
                & (conf > 0)
                & (radial_mm > self.min_valid_mm)
                & (radial_mm < self.max_valid_mm)
            )
        depth_mm = radial_to_z(np.where(valid, radial_mm, 0.0), self.hfov_deg)
        amplitude = np.where(valid & np.isfinite(amplitude), amplitude, 0.0).astype(np.float32)
        return RawSample(sample_id, depth_mm, amplitude, valid)

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "root": str(self.root.resolve()),
            "list_files": [p.name for p in self._list_paths()],
            "hfov_deg": self.hfov_deg,
            "gt_scale": GT_SCALE,
            "min_valid_mm": self.min_valid_mm,
            "max_valid_mm": self.max_valid_mm,
        }
