"""Camera intrinsics of a depth frame and its point cloud.

``Intrinsics`` holds the pinhole parameters of the depth image in pixels (OpenCV convention: (0, 0) is the centre
of the top-left pixel) and the image size. They come from

- a small YAML/JSON file (``load_intrinsics``)::

      fx: 504.2
      fy: 504.3
      cx: 321.6
      cy: 329.2
      width: 640
      height: 576

  or a ROS ``camera_info`` YAML of ``camera_calibration_parsers`` (``camera_matrix: {data: [fx, 0, cx, 0, fy, cy,
  0, 0, 1]}``, ``image_width``, ``image_height``);
- the ``calibration.json`` attachment of an Azure Kinect recording (``kinect_depth_intrinsics``: the depth camera's
  raw, unitised parameters scaled to the depth mode's binned resolution and shifted by its crop, as the Sensor SDK
  does for its mode-specific calibration);
- a ``sensor_msgs/CameraInfo`` message of a bag (its ``K`` matrix).

``points_m`` back-projects the valid pixels of a z-depth map (the distance along the optical axis: what the Kinect
and ROS depth images hold) into the camera's optical frame (REP 103: x right, y down, z forward), in metres. Lens
distortion is not applied: the points are those of the pinhole model of the intrinsics.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

__all__ = [
    "Intrinsics",
    "IntrinsicsError",
    "KINECT_DEPTH_MODES",
    "kinect_depth_intrinsics",
    "load_intrinsics",
    "points_m",
]


class IntrinsicsError(ValueError):
    """Intrinsics that are missing, malformed or do not fit the frame; the message names the source."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics [px] of a depth image of ``width`` x ``height`` pixels; ``source`` names where they came
    from (for error messages)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    source: str = ""

    def __post_init__(self) -> None:
        where = f" ({self.source})" if self.source else ""
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise IntrinsicsError(f"intrinsics{where}: {name} must be a positive number of pixels, got {value}")
        for name in ("cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise IntrinsicsError(f"intrinsics{where}: {name} must be a finite number, got {getattr(self, name)}")
        for name in ("width", "height"):
            if int(getattr(self, name)) < 1:
                raise IntrinsicsError(f"intrinsics{where}: {name} must be >= 1 pixel, got {getattr(self, name)}")

    def check_shape(self, shape: tuple[int, ...], frame: str) -> None:
        """IntrinsicsError unless a frame of ``shape`` (H, W) is the image these intrinsics describe."""
        if tuple(shape[-2:]) != (self.height, self.width):
            raise IntrinsicsError(
                f"intrinsics of {self.source or 'the camera'} describe a {self.width} x {self.height} image; "
                f"frame {frame} is {shape[-1]} x {shape[-2]} (width x height)"
            )


def _number(data: dict[str, Any], key: str, source: str) -> float:
    if key not in data:
        raise IntrinsicsError(
            f"intrinsics file {source}: field {key!r} is missing (expected fx, fy, cx, cy, width, height)"
        )
    try:
        return float(data[key])
    except (TypeError, ValueError):
        raise IntrinsicsError(f"intrinsics file {source}: field {key!r} must be a number, got {data[key]!r}") from None


def load_intrinsics(path: str | Path) -> Intrinsics:
    """Intrinsics from a YAML/JSON file with fx, fy, cx, cy, width, height (or a ROS camera_info YAML)."""

    path = Path(path).expanduser()
    if not path.is_file():
        raise IntrinsicsError(f"intrinsics file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, yaml.YAMLError) as exc:
        raise IntrinsicsError(f"intrinsics file {path} could not be read as YAML/JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise IntrinsicsError(f"intrinsics file {path}: expected a mapping with fx, fy, cx, cy, width, height")
    source = str(path)
    if "camera_matrix" in data and "fx" not in data:  # ROS camera_info YAML
        matrix = data["camera_matrix"]
        values = matrix.get("data") if isinstance(matrix, dict) else None
        if not isinstance(values, list) or len(values) != 9:
            raise IntrinsicsError(f"intrinsics file {path}: camera_matrix.data must hold the 9 entries of K")
        data = {
            "fx": values[0],
            "cx": values[2],
            "fy": values[4],
            "cy": values[5],
            "width": data.get("image_width"),
            "height": data.get("image_height"),
        }
    fx, fy, cx, cy = (_number(data, k, source) for k in ("fx", "fy", "cx", "cy"))
    width, height = (_number(data, k, source) for k in ("width", "height"))
    if width != int(width) or height != int(height):
        raise IntrinsicsError(f"intrinsics file {path}: width and height must be whole pixels, got {width} x {height}")
    return Intrinsics(fx, fy, cx, cy, int(width), int(height), source=source)


#: Azure Kinect depth modes: (binned resolution of the 1024 x 1024 calibration image, crop offset, output size),
#: as the Sensor SDK defines its mode-specific depth calibration
KINECT_DEPTH_MODES: dict[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]] = {
    "NFOV_2X2BINNED": ((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ((1024, 1024), (0, 0), (1024, 1024)),
}


def kinect_depth_intrinsics(calibration_json: bytes | str, depth_mode: str | None, source: str) -> Intrinsics:
    """The depth camera's intrinsics in a depth mode from an Azure Kinect ``calibration.json``.

    The file stores the depth camera (``Location`` ``CALIBRATION_CameraLocationD0``) with ``ModelParameters``
    ``[cx, cy, fx, fy, k1..k6, codx, cody, p2, p1]`` unitised (divided by the 1024 x 1024 sensor size) with (0, 0)
    at the corner of the top-left pixel: scaled to the mode's binned resolution, shifted by its crop and by half a
    pixel. ``depth_mode`` (the track's ``K4A_DEPTH_MODE`` tag) picks the mode."""
    try:
        doc = json.loads(calibration_json)
        cameras = doc["CalibrationInformation"]["Cameras"]
    except (ValueError, KeyError, TypeError) as exc:
        raise IntrinsicsError(
            f"{source}: calibration.json is not an Azure Kinect calibration (no CalibrationInformation.Cameras): {exc}"
        ) from exc
    depth = [c for c in cameras if isinstance(c, dict) and c.get("Location") == "CALIBRATION_CameraLocationD0"]
    if not depth:
        raise IntrinsicsError(f"{source}: calibration.json has no depth camera (Location CALIBRATION_CameraLocationD0)")
    params = depth[0].get("Intrinsics", {}).get("ModelParameters")
    if not isinstance(params, list) or len(params) < 4:
        raise IntrinsicsError(f"{source}: calibration.json depth camera has no Intrinsics.ModelParameters")
    if depth_mode not in KINECT_DEPTH_MODES:
        raise IntrinsicsError(
            f"{source}: depth mode {depth_mode!r} has no depth intrinsics; expected one of "
            f"{', '.join(KINECT_DEPTH_MODES)}"
        )
    (bw, bh), (ox, oy), (w, h) = KINECT_DEPTH_MODES[depth_mode]
    cx, cy, fx, fy = (float(v) for v in params[:4])
    return Intrinsics(
        fx=fx * bw,
        fy=fy * bh,
        cx=cx * bw - ox - 0.5,
        cy=cy * bh - oy - 0.5,
        width=w,
        height=h,
        source=f"{source} (calibration.json, {depth_mode})",
    )


def points_m(depth_m: np.ndarray, intrinsics: Intrinsics, frame: str = "(depth map)") -> np.ndarray:
    """(N, 3) float32 points [m] of the valid pixels (finite, > 0) of a z-depth map [m], row by row: pixel (u, v)
    with depth z goes to ((u - cx) z / fx, (v - cy) z / fy, z)."""
    depth = np.asarray(depth_m, dtype=np.float64)
    intrinsics.check_shape(depth.shape, frame)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    z = depth[v, u]
    x = (u - intrinsics.cx) * z / intrinsics.fx
    y = (v - intrinsics.cy) * z / intrinsics.fy
    return np.stack([x, y, z], axis=1).astype(np.float32)
