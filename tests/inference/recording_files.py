"""Recordings the tests write themselves (no downloads): an Azure-Kinect-like ``.mkv`` (PyAV) and ROS 1 / ROS 2
bags (rosbags' writers). Loaded by the ``recording_files`` fixture of tests/conftest.py.

The ``.mkv`` is what the Kinect recorder writes, as far as the reader looks: Matroska, a ``DEPTH`` and an ``IR``
video track (titles and the ``K4A_DEPTH_TRACK`` / ``K4A_IR_TRACK`` / ``K4A_DEPTH_MODE`` tags), raw 16-bit big-endian
samples with the FourCC ``b16g``, and a ``calibration.json`` attachment. FFmpeg's Matroska muxer (under PyAV) stores
raw video only in VFW mode (``allow_raw_vfw``) with a BITMAPINFOHEADER of compression 0 (BI_RGB) and a negative
(top-down) height, whatever codec tag is asked for; ``write_kinect_mkv`` then sets the header's FourCC to ``b16g``
and its height positive in place (same length, so no Matroska size changes), which is how the Kinect's own
recorder describes these tracks. The pixel bytes are exactly the big-endian samples.

The compressed bag topics are written the way ROS's image_transport plugins publish them: ``compressedDepth``
(a 12-byte ConfigHeader, then a 16-bit PNG or an RVL stream; 32FC1 as quantised inverse depth with the publisher's
defaults depth_quantization 100, depth_max 10 m) and ``compressed`` (a plain PNG / JPEG). The RVL encoder here is
a direct, pixel-by-pixel transcription of the published algorithm, independent of the reader's vectorised decoder.
"""

from __future__ import annotations

import io
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


def _bag_writer(path: Path, version: int):
    """(writer, typestore, serialize) of rosbags for a ROS ``version`` 1 ``.bag`` file or a ROS 2 bag folder."""
    from rosbags.typesys import Stores, get_typestore

    if version == 1:
        from rosbags.rosbag1 import Writer

        typestore = get_typestore(Stores.ROS1_NOETIC)
        return Writer(path), typestore, typestore.serialize_ros1
    from rosbags.rosbag2 import Writer

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    return Writer(path, version=9), typestore, typestore.serialize_cdr


def _header(typestore, stamp_ns: int):
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    head = {"stamp": Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), "frame_id": "depth"}
    if "seq" in Header.__dataclass_fields__:
        head["seq"] = 0
    return Header(**head)


def _image(typestore, stamp_ns: int, array: np.ndarray, encoding: str, bigendian: bool = False, pad: int = 0):
    Image = typestore.types["sensor_msgs/msg/Image"]
    array = np.asarray(array)
    rows = array.astype(array.dtype.newbyteorder(">" if bigendian else "<")).view(np.uint8).reshape(array.shape[0], -1)
    rows = np.concatenate([rows, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)  # step padding
    return Image(
        header=_header(typestore, stamp_ns),
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
    RoI = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    values = {
        "header": _header(typestore, stamp_ns),
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
    path = Path(path)
    depth = np.asarray(depth)
    stamps = (
        stamps_ns if stamps_ns is not None else [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(len(depth))]
    )
    writer, typestore, serialize = _bag_writer(path, version)
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


def write_image_bag(path, version: int, images, camera_infos=()) -> Path:
    """A bag of ``sensor_msgs/Image`` messages in the order given: ``images`` = (topic, header stamp ns, array,
    encoding) each, logged 1 ms apart whatever their header stamps (a driver's stamps need not be unique or in
    order); ``camera_infos`` = (topic, k 9 values, width, height), one message each, logged first."""
    path = Path(path)
    writer, typestore, serialize = _bag_writer(path, version)
    image, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
    log_ns = 1_000_000_000
    with writer:
        connections = {}
        for topic, k, width, height in camera_infos:
            conn = writer.add_connection(topic, info, typestore=typestore)
            writer.write(conn, log_ns, serialize(_camera_info(typestore, log_ns, k, width, height), info))
            log_ns += 1_000_000
        for topic, stamp, array, encoding in images:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, image, typestore=typestore)
            msg = _image(typestore, stamp, np.asarray(array), encoding)
            writer.write(connections[topic], log_ns, serialize(msg, image))
            log_ns += 1_000_000
    return path


# ------------------------------------------------------------------------------ image_transport compressed forms
def rvl_encode(pixels) -> bytes:
    """RVL (Wilson 2017), pixel by pixel: runs of zeros / non-zeros, zig-zag deltas, 3-bit VLE nibbles."""
    nibbles: list[int] = []

    def vle(value: int) -> None:
        while True:
            chunk, value = value & 0x7, value >> 3
            nibbles.append(chunk | (0x8 if value else 0))
            if not value:
                return

    flat = [int(v) for v in np.asarray(pixels, np.uint16).ravel()]
    i, previous = 0, 0
    while i < len(flat):
        zeros = 0
        while i < len(flat) and flat[i] == 0:
            zeros, i = zeros + 1, i + 1
        vle(zeros)
        run = []
        while i < len(flat) and flat[i] != 0:
            run.append(flat[i])
            i += 1
        vle(len(run))
        for value in run:
            delta = value - previous
            vle((delta << 1) ^ (delta >> 31))  # zig-zag of a 32-bit int
            previous = value
    nibbles += [0] * (-len(nibbles) % 8)
    words = [sum(n << (28 - 4 * k) for k, n in enumerate(nibbles[j : j + 8])) for j in range(0, len(nibbles), 8)]
    return struct.pack(f"<{len(words)}I", *words)


def quantise_inverse_depth(metres, depth_quantization: float = 100.0, depth_max: float = 10.0):
    """compressed_depth_image_transport's 32FC1 encoding: (uint16 q, A, B), q = A / z + B, 0 where z >= max/NaN."""
    a = np.float32(depth_quantization * (depth_quantization + 1.0))
    b = np.float32(1.0 - a / np.float32(depth_max))
    z = np.asarray(metres, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(z < depth_max, a / z + b, 0.0)
    return np.nan_to_num(q, nan=0.0).astype(np.uint16), float(a), float(b)


def png_bytes(pixels) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(pixels)).save(buf, format="PNG")
    return buf.getvalue()


def compressed_depth_payload(depth, encoding: str, codec: str) -> bytes:
    """A compressedDepth message's ``data``: ConfigHeader + PNG (``png``) or width, height, RVL (``rvl``)."""
    if encoding == "32FC1":
        coded, a, b = quantise_inverse_depth(depth)
    else:
        coded, a, b = np.asarray(depth, np.uint16), 0.0, 0.0
    header = struct.pack("<iff", 0, a, b)
    if codec == "rvl":
        return header + struct.pack("<II", coded.shape[1], coded.shape[0]) + rvl_encode(coded)
    return header + png_bytes(coded)


def _compressed(typestore, stamp_ns: int, fmt: str, data: bytes):
    Msg = typestore.types["sensor_msgs/msg/CompressedImage"]
    return Msg(header=_header(typestore, stamp_ns), format=fmt, data=np.frombuffer(data, np.uint8).copy())


def write_compressed_bag(
    path,
    version: int,
    depth,
    depth_encoding: str = "16UC1",
    codec: str = "png",
    amplitude=None,
    amplitude_codec: str = "png",
    depth_topic: str = "/camera/depth/image_raw/compressedDepth",
    amplitude_topic: str = "/camera/ir/image_raw/compressed",
    payloads=None,
) -> Path:
    """A bag of ``sensor_msgs/CompressedImage`` topics: depth as compressedDepth (``codec`` png / rvl), amplitude
    as ``compressed`` (``amplitude_codec`` png for mono16, jpeg for mono8). ``payloads`` (a list of bytes per
    frame) replaces the depth messages' data, for damaged messages."""
    path = Path(path)
    depth = np.asarray(depth)
    stamps = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(len(depth))]
    writer, typestore, serialize = _bag_writer(path, version)
    kind = "sensor_msgs/msg/CompressedImage"
    with writer:
        c_depth = writer.add_connection(depth_topic, kind, typestore=typestore)
        c_amp = writer.add_connection(amplitude_topic, kind, typestore=typestore) if amplitude is not None else None
        for i, stamp in enumerate(stamps):
            if c_amp is not None:
                amp = np.asarray(amplitude[i])
                enc = "mono16" if amp.dtype == np.uint16 else "mono8"
                if amplitude_codec == "jpeg":
                    from PIL import Image

                    buf = io.BytesIO()
                    Image.fromarray(amp).save(buf, format="JPEG", quality=95)
                    data = buf.getvalue()
                else:
                    data = png_bytes(amp)
                msg = _compressed(typestore, stamp, f"{enc}; {amplitude_codec} compressed {enc}", data)
                writer.write(c_amp, stamp, serialize(msg, kind))
            data = payloads[i] if payloads is not None else compressed_depth_payload(depth[i], depth_encoding, codec)
            msg = _compressed(typestore, stamp, f"{depth_encoding}; compressedDepth {codec}", data)
            writer.write(c_depth, stamp + 1000, serialize(msg, kind))
    return path
