"""Recordings the tests write themselves (no downloads): an Azure-Kinect-like ``.mkv`` (PyAV) and ROS 1 / ROS 2
bags (rosbags' writers). Loaded by the ``recording_files`` fixture of tests/conftest.py.

The ``.mkv`` is what the Kinect recorder writes, as far as the reader looks: Matroska, a ``DEPTH`` and an ``IR``
video track (titles and the ``K4A_DEPTH_TRACK`` / ``K4A_IR_TRACK`` / ``K4A_DEPTH_MODE`` tags), raw 16-bit big-endian
samples with the FourCC ``b16g``, and a ``calibration.json`` attachment. FFmpeg's Matroska muxer (under PyAV) stores
raw video only in VFW mode (``allow_raw_vfw``) with a BITMAPINFOHEADER of compression 0 (BI_RGB) and a negative
(top-down) height, whatever codec tag is asked for; ``write_kinect_mkv`` then sets the header's FourCC to ``b16g``
and its height positive in place (same length, so no Matroska size changes), which is how the Kinect's own
recorder describes these tracks. The pixel bytes are exactly the big-endian samples.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

#: a depth camera calibration as the Kinect stores it (unitised cx, cy, fx, fy first)
KINECT_PARAMS = [0.5122698, 0.4945123, 0.4921168, 0.4921667, 3.13, 2.32, 0.13, 3.46, 3.35, 0.66, 0, 0, -5e-5, 8e-5]


def kinect_calibration_json(params=KINECT_PARAMS) -> bytes:
    cameras = [
        {
            "Intrinsics": {
                "ModelParameterCount": 14,
                "ModelParameters": list(params),
                "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
            },
            "Location": "CALIBRATION_CameraLocationD0",
            "Purpose": "CALIBRATION_CameraPurposeDepth",
            "SensorHeight": 1024,
            "SensorWidth": 1024,
        },
        {
            "Intrinsics": {"ModelParameterCount": 14, "ModelParameters": [0.5, 0.5, 0.47, 0.63] + [0.0] * 10},
            "Location": "CALIBRATION_CameraLocationPV0",
            "Purpose": "CALIBRATION_CameraPurposePhotoVideo",
            "SensorHeight": 3072,
            "SensorWidth": 4096,
        },
    ]
    return json.dumps({"CalibrationInformation": {"Cameras": cameras}}).encode()


def write_kinect_mkv(
    path,
    depth_mm,
    ir=None,
    depth_mode: str = "NFOV_UNBINNED",
    calibration: bytes | None = None,
    fps: int = 30,
) -> Path:
    """``depth_mm`` / ``ir``: (T, H, W) uint16 stacks; returns ``path``."""
    import av

    path = Path(path)
    depth_mm = np.asarray(depth_mm, dtype=np.uint16)
    t, h, w = depth_mm.shape
    container = av.open(str(path), "w", format="matroska", options={"allow_raw_vfw": "1"})
    tracks = [("DEPTH", "K4A_DEPTH_TRACK", depth_mm)] + (
        [("IR", "K4A_IR_TRACK", np.asarray(ir, np.uint16))] if ir is not None else []
    )
    streams = []
    for title, tag, _ in tracks:
        stream = container.add_stream("rawvideo", rate=fps)
        stream.width, stream.height, stream.pix_fmt = w, h, "gray16be"
        stream.metadata["title"] = title
        stream.metadata[tag] = "1"
        if title == "DEPTH":
            stream.metadata["K4A_DEPTH_MODE"] = depth_mode
        streams.append(stream)
    if calibration is not None:
        container.add_attachment(name="calibration.json", mimetype="application/octet-stream", data=calibration)
    for i in range(t):
        for stream, (_, _, stack) in zip(streams, tracks):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(stack[i]), format="gray16be")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
    for stream in streams:
        for packet in stream.encode():
            container.mux(packet)
    container.close()
    data = path.read_bytes()
    bmp = struct.pack("<IiiHHI", 40, w, -h, 1, 16, 0)
    assert data.count(bmp) == len(streams), "unexpected BITMAPINFOHEADER layout from the muxer"
    path.write_bytes(data.replace(bmp, struct.pack("<IiiHH", 40, w, h, 1, 16) + b"b16g"))
    return path


def _image(typestore, stamp_ns: int, array: np.ndarray, encoding: str, bigendian: bool = False, pad: int = 0):
    Image = typestore.types["sensor_msgs/msg/Image"]
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    head = {"stamp": Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), "frame_id": "depth"}
    if "seq" in Header.__dataclass_fields__:
        head["seq"] = 0
    array = np.asarray(array)
    rows = array.astype(array.dtype.newbyteorder(">" if bigendian else "<")).view(np.uint8).reshape(array.shape[0], -1)
    rows = np.concatenate([rows, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)  # step padding
    return Image(
        header=Header(**head),
        height=array.shape[0],
        width=array.shape[1],
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=rows.shape[1],
        data=rows.ravel(),
    )


def _camera_info(typestore, stamp_ns: int, k, width: int, height: int):
    Info = typestore.types["sensor_msgs/msg/CameraInfo"]
    fields = Info.__dataclass_fields__
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    head = {"stamp": Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), "frame_id": "depth"}
    if "seq" in Header.__dataclass_fields__:
        head["seq"] = 0
    RoI = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    values = {
        "header": Header(**head),
        "height": height,
        "width": width,
        "distortion_model": "plumb_bob",
        "binning_x": 0,
        "binning_y": 0,
        "roi": RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    }
    lower = "k" in fields
    values["d" if lower else "D"] = np.zeros(5)
    values["k" if lower else "K"] = np.asarray(k, dtype=np.float64)
    values["r" if lower else "R"] = np.eye(3).ravel()
    values["p" if lower else "P"] = np.concatenate([np.asarray(k).reshape(3, 3), np.zeros((3, 1))], axis=1).ravel()
    return Info(**values)


def write_bag(
    path,
    version: int,
    depth,
    depth_encoding: str = "16UC1",
    amplitude=None,
    depth_topic: str = "/camera/depth/image_raw",
    amplitude_topic: str = "/camera/ir/image_raw",
    camera_info=None,
    bigendian: bool = False,
    pad: int = 0,
    stamps_ns=None,
) -> Path:
    """A ROS ``version`` 1 (``.bag`` file) or 2 (bag folder) bag: ``depth`` (T, H, W) in the encoding's units,
    ``amplitude`` (T, H, W) uint16 (mono16) or None, ``camera_info`` = (k 9 values, width, height) or None."""
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    depth = np.asarray(depth)
    stamps = (
        stamps_ns if stamps_ns is not None else [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(len(depth))]
    )
    if version == 1:
        from rosbags.rosbag1 import Writer

        typestore = get_typestore(Stores.ROS1_NOETIC)
        writer, serialize = Writer(path), typestore.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        typestore = get_typestore(Stores.ROS2_HUMBLE)
        writer, serialize = Writer(path, version=9), typestore.serialize_cdr
    image, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
    with writer:
        c_depth = writer.add_connection(depth_topic, image, typestore=typestore)
        c_amp = writer.add_connection(amplitude_topic, image, typestore=typestore) if amplitude is not None else None
        c_info = writer.add_connection("/camera/depth/camera_info", info, typestore=typestore) if camera_info else None
        for i, stamp in enumerate(stamps):
            if c_info is not None:
                k, w, h = camera_info
                writer.write(c_info, stamp, serialize(_camera_info(typestore, stamp, k, w, h), info))
            if c_amp is not None:  # the amplitude before the depth: the reader pairs by header stamp, not order
                msg = _image(typestore, stamp, np.asarray(amplitude[i], np.uint16), "mono16", bigendian, pad)
                writer.write(c_amp, stamp, serialize(msg, image))
            msg = _image(typestore, stamp, depth[i], depth_encoding, bigendian, pad)
            writer.write(c_depth, stamp + 1000, serialize(msg, image))
    return path
