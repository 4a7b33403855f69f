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
  0, 0, 1]}``, ``image_width``, ``image_height``), or an OpenCV ``cv::FileStorage`` file (YAML with its
  ``%YAML:1.0`` header and ``!!opencv-matrix`` tags, or XML) as OpenCV's calibration sample writes it
  (``camera_matrix``, ``image_width``, ``image_height``, ``distortion_coefficients``; read with OpenCV itself);
- the Azure Kinect's ``calibration.json`` (``kinect_depth_intrinsics``: the depth camera's raw, unitised parameters
  scaled to the depth mode's binned resolution and shifted by its crop, as the Sensor SDK does for its
  mode-specific calibration): attached to a recording, where the track names the depth mode, or as a file of its
  own (``load_intrinsics`` -> ``KinectCalibration``), where the depth mode is the one whose image has the frame's
  size (``kinect_mode_for_size``);
- a ``sensor_msgs/CameraInfo`` message of a bag (its ``K`` matrix).

``resolve_intrinsics(intrinsics, shape, frame)`` gives the ``Intrinsics`` of a frame of that shape from either
kind, or an ``IntrinsicsError`` naming both sizes.

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
    "INTRINSICS_FORMS",
    "Intrinsics",
    "IntrinsicsError",
    "KINECT_DEPTH_MODES",
    "KinectCalibration",
    "kinect_depth_intrinsics",
    "kinect_mode_for_size",
    "load_intrinsics",
    "points_m",
    "resolve_intrinsics",
]

#: the forms of an intrinsics file ``load_intrinsics`` reads, for the error that names them
INTRINSICS_FORMS = (
    "YAML/JSON with fx, fy, cx, cy, width, height; a ROS camera_info YAML; an OpenCV FileStorage YAML/XML "
    "(camera_matrix, image_width, image_height); an Azure Kinect calibration.json (CalibrationInformation.Cameras)"
)


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


def _opencv_storage(path: Path) -> dict[str, Any] | None:
    """fx, fy, cx, cy, width, height of an OpenCV ``cv::FileStorage`` file (None: it has no ``camera_matrix``).
    Keys are matched without case (OpenCV's calibration tutorial writes ``Camera_Matrix``, ``image_Width``)."""
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV 5 raises SystemError with the parse error as its cause
        cause = exc.__cause__ or exc
        lines = [ln.strip() for ln in str(cause).strip().splitlines() if ln.strip()]
        raise IntrinsicsError(
            f"intrinsics file {path} could not be read as an OpenCV FileStorage file: {lines[-1] if lines else cause}"
        ) from exc
    try:
        if not storage.isOpened():
            raise IntrinsicsError(f"intrinsics file {path} could not be read as an OpenCV FileStorage file")
        root = storage.root()
        keys = {key.lower(): key for key in root.keys()}

        def node(name: str) -> Any:
            return storage.getNode(keys[name]) if name in keys else None

        matrix_node = node("camera_matrix")
        if matrix_node is None:
            return None
        matrix = matrix_node.mat()
        if matrix is None or matrix.shape != (3, 3):
            raise IntrinsicsError(
                f"intrinsics file {path}: camera_matrix must be a 3 x 3 !!opencv-matrix, got "
                f"{'no matrix' if matrix is None else ' x '.join(map(str, matrix.shape))}"
            )
        size = {}
        for name in ("image_width", "image_height"):
            value = node(name)
            if value is None or not value.isInt():
                raise IntrinsicsError(
                    f"intrinsics file {path}: field {name!r} is {'missing' if value is None else 'not an integer'} "
                    "(an OpenCV calibration file gives the image size as image_width and image_height)"
                )
            size[name] = int(value.real())
    finally:
        storage.release()
    return {
        "fx": matrix[0, 0],
        "fy": matrix[1, 1],
        "cx": matrix[0, 2],
        "cy": matrix[1, 2],
        "width": size["image_width"],
        "height": size["image_height"],
    }


def _is_opencv_storage(path: Path, text: str) -> bool:
    head = text.lstrip()[:200]
    return (
        head.startswith("%YAML:")
        or "!!opencv-matrix" in text
        or head.startswith("<?xml")
        and "<opencv_storage>" in text
    )


def load_intrinsics(path: str | Path) -> Intrinsics | KinectCalibration:
    """Intrinsics from a file of one of ``INTRINSICS_FORMS``: ``Intrinsics``, or a ``KinectCalibration`` for an
    Azure Kinect ``calibration.json`` (whose depth intrinsics depend on the depth mode: ``resolve_intrinsics``)."""

    path = Path(path).expanduser()
    if not path.is_file():
        raise IntrinsicsError(f"intrinsics file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise IntrinsicsError(
            f"intrinsics file {path} could not be read as text: {exc}; expected {INTRINSICS_FORMS}"
        ) from exc
    source = str(path)
    if _is_opencv_storage(path, text):
        data = _opencv_storage(path)
        if data is None:
            raise IntrinsicsError(
                f"intrinsics file {path}: an OpenCV FileStorage file without camera_matrix; expected {INTRINSICS_FORMS}"
            )
    else:
        try:
            data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
        except (json.JSONDecodeError, yaml.YAMLError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise IntrinsicsError(
                f"intrinsics file {path} could not be read as YAML/JSON ({first}); expected {INTRINSICS_FORMS}"
            ) from exc
        if not isinstance(data, dict):
            raise IntrinsicsError(f"intrinsics file {path}: expected a mapping, one of {INTRINSICS_FORMS}")
        if "CalibrationInformation" in data:  # the Azure Kinect's own calibration.json
            return KinectCalibration(text.encode("utf-8"), source)
        if not any(key in data for key in ("fx", "fy", "cx", "cy", "camera_matrix")):
            raise IntrinsicsError(f"intrinsics file {path} is none of the forms read: {INTRINSICS_FORMS}")
        if "camera_matrix" in data and "fx" not in data:  # ROS camera_info YAML (or OpenCV's FileStorage JSON)
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
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height), source=source)


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


def kinect_mode_for_size(width: int, height: int) -> str | None:
    """The Azure Kinect depth mode whose depth image is ``width`` x ``height`` (None: none is). PASSIVE_IR shares
    WFOV_UNBINNED's size and its intrinsics; the depth mode is named."""
    for mode, (_, _, size) in KINECT_DEPTH_MODES.items():
        if size == (width, height) and mode != "PASSIVE_IR":
            return mode
    return None


@dataclass(frozen=True)
class KinectCalibration:
    """An Azure Kinect ``calibration.json`` read as a file of its own: the depth intrinsics of a frame are those of
    the depth mode of the frame's size (``for_shape``). ``calibration_json``: the file's bytes, checked on
    construction (a depth camera with its model parameters)."""

    calibration_json: bytes
    source: str

    def __post_init__(self) -> None:
        kinect_depth_intrinsics(self.calibration_json, "NFOV_UNBINNED", self.source)

    def for_shape(self, shape: tuple[int, ...], frame: str) -> Intrinsics:
        height, width = (int(v) for v in tuple(shape)[-2:])
        mode = kinect_mode_for_size(width, height)
        if mode is None:
            sizes = ", ".join(
                f"{w} x {h} ({m})" for m, (_, _, (w, h)) in KINECT_DEPTH_MODES.items() if m != "PASSIVE_IR"
            )
            raise IntrinsicsError(
                f"intrinsics of {self.source} (an Azure Kinect calibration.json) are those of a Kinect depth image: "
                f"{sizes}; frame {frame} is {width} x {height} (width x height)"
            )
        return kinect_depth_intrinsics(self.calibration_json, mode, self.source)


def resolve_intrinsics(intrinsics: Intrinsics | KinectCalibration, shape: tuple[int, ...], frame: str) -> Intrinsics:
    """The ``Intrinsics`` of a frame of ``shape`` (H, W): ``intrinsics`` itself when it describes that image size
    (else an ``IntrinsicsError`` naming both sizes), or the depth mode's of a Kinect calibration."""
    if isinstance(intrinsics, KinectCalibration):
        return intrinsics.for_shape(shape, frame)
    intrinsics.check_shape(shape, frame)
    return intrinsics


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
