"""Decoding ``sensor_msgs/CompressedImage`` payloads: the ROS image_transport plugins a depth camera's bag holds.

A ROS driver that publishes through ``image_transport`` offers each image topic in compressed forms too, and bags
are often recorded from those (``/camera/depth/image_raw/compressedDepth``, ``/camera/ir/image_raw/compressed``).
The message's ``format`` names the source encoding and the codec:

- **compressedDepth** (``compressed_depth_image_transport``), ``"<enc>; compressedDepth [png|rvl]"``; a bare
  ``"<enc>; compressedDepth"`` is the old PNG form. The payload is a 12-byte little-endian ``ConfigHeader``
  (int32 format, float32 ``depthParam[2]``) followed by the image:
  - ``png``: a 16-bit grey PNG;
  - ``rvl``: uint32 width, uint32 height, then an RVL stream (Wilson 2017, "Fast Lossless Depth Image
    Compression"): run lengths of zeros and of non-zeros, each non-zero pixel as the zig-zag coded difference to
    the previous non-zero pixel; every integer is a variable-length code of 3-bit groups (lowest first) in nibbles
    whose high bit says "more follows", eight nibbles per little-endian 32-bit word, most significant first.
  For ``16UC1`` / ``mono16`` the image is the depth in mm (0 = invalid). For ``32FC1`` it is the quantised inverse
  depth q = A / z + B (A = ``depthParam[0]``, B = ``depthParam[1]``, z in metres), so z = A / (q - B), and
  q = 0 marks an invalid pixel (NaN).
- **compressed** (``compressed_image_transport``), ``"<enc>; png compressed <enc>"`` / ``"...; jpeg compressed
  ..."`` or just ``"png"`` / ``"jpeg"``: the payload is a plain PNG or JPEG file (JPEG only for 8-bit images; it is
  lossy, so it is fit for an amplitude preview, not for depth).

PNG and JPEG are decoded with Pillow. The RVL decoder is vectorised with NumPy except for a loop over runs.
"""

from __future__ import annotations

import io
import struct

import numpy as np
from PIL import Image, UnidentifiedImageError

from tofdenoise.inference.frames import FrameError

__all__ = [
    "CONFIG_HEADER_BYTES",
    "CompressedImageError",
    "decode_compressed_image",
    "parse_compressed_format",
    "rvl_decode",
]

CONFIG_HEADER_BYTES = 12  # compression_common.h ConfigHeader: int32 format + float32 depthParam[2]
_NIBBLE_SHIFTS = np.arange(28, -1, -4, dtype=np.uint32)  # the first nibble of a word is its most significant
_UINT16_ENCODINGS = ("16UC1", "mono16")


class CompressedImageError(FrameError):
    """A ``sensor_msgs/CompressedImage`` that cannot be decoded; the message says where and what was expected."""


def parse_compressed_format(fmt: str) -> tuple[str, str]:
    """``(source encoding, codec)`` of a CompressedImage ``format`` string.

    codec is ``"compressedDepth png"``, ``"compressedDepth rvl"``, ``"png"`` or ``"jpeg"``. The source encoding is
    the part before ``;`` (empty for a bare ``"png"`` / ``"jpeg"``).
    """
    text = str(fmt).strip()
    encoding, _, rest = text.partition(";") if ";" in text else ("", "", text)
    encoding, rest = encoding.strip(), rest.strip().lower()
    words = rest.split()
    if words[:1] == ["compresseddepth"]:
        kind = words[1] if len(words) > 1 else "png"  # "compressedDepth" alone: the PNG form before RVL existed
        if kind not in ("png", "rvl"):
            raise CompressedImageError(f"compressedDepth codec {kind!r} in format {fmt!r}; expected png or rvl")
        return encoding, f"compressedDepth {kind}"
    if words[:1] in (["png"], ["jpeg"], ["jpg"]):
        return encoding, "jpeg" if words[0] == "jpg" else words[0]
    raise CompressedImageError(
        f"CompressedImage format {fmt!r}; expected '<encoding>; compressedDepth [png|rvl]' or "
        "'<encoding>; png|jpeg compressed <encoding>' (ROS image_transport)"
    )


def _vle_values(words: np.ndarray, where: str) -> np.ndarray:
    """Every complete variable-length integer of an RVL stream, in order (int64)."""
    nibbles = ((words[:, None] >> _NIBBLE_SHIFTS[None, :]) & 0xF).astype(np.int64).ravel()
    ends = (nibbles & 0x8) == 0
    if not ends.any():
        return np.zeros(0, np.int64)
    complete = np.flatnonzero(ends)[-1] + 1  # nibbles up to the end of the last whole integer
    nibbles, ends = nibbles[:complete], ends[:complete]
    group = np.cumsum(ends) - ends  # the value each nibble belongs to
    starts = np.flatnonzero(np.concatenate(([True], ends[:-1])))
    place = np.arange(nibbles.size) - starts[group]  # 3-bit group k of its value, lowest first
    if place.max(initial=0) > 10:
        raise CompressedImageError(f"{where}: RVL stream has an integer of more than 32 bits (not an RVL stream)")
    contributions = (nibbles & 0x7) << (3 * place)
    # each contribution < 2^33: exact in float64, and bincount is much faster than np.add.at
    return np.bincount(group, weights=contributions.astype(np.float64), minlength=starts.size).astype(np.int64)


def rvl_decode(stream: bytes, num_pixels: int, where: str = "RVL stream") -> np.ndarray:
    """The ``num_pixels`` uint16 samples of an RVL stream (the bytes after the width and height)."""
    whole = len(stream) // 4 * 4
    values = _vle_values(np.frombuffer(stream[:whole], dtype="<u4").astype(np.uint32), where)
    lengths: list[int] = []  # zeros, values, zeros, values ... in pixels
    counts: list[int] = []  # where in ``values`` the run lengths are (the rest up to the end are deltas)
    pixel, i, total = 0, 0, values.size
    while pixel < num_pixels:
        if i + 1 >= total:
            raise CompressedImageError(
                f"{where}: RVL stream ends after {pixel} of {num_pixels} pixels (truncated or not RVL)"
            )
        zeros, nonzeros = int(values[i]), int(values[i + 1])
        if pixel + zeros + nonzeros > num_pixels:
            raise CompressedImageError(
                f"{where}: RVL run of {zeros} zeros and {nonzeros} values at pixel {pixel} goes past the image's "
                f"{num_pixels} pixels (not the image's RVL stream)"
            )
        if i + 2 + nonzeros > total:
            raise CompressedImageError(
                f"{where}: RVL stream ends after {pixel + zeros + total - i - 2} of {num_pixels} pixels (truncated)"
            )
        lengths += (zeros, nonzeros)
        counts += (i, i + 1)
        pixel += zeros + nonzeros
        i += 2 + nonzeros
    is_delta = np.ones(i, bool)
    is_delta[counts] = False
    zigzag = values[:i][is_delta]
    deltas = (zigzag >> 1) ^ -(zigzag & 1)
    has_value = np.repeat(np.tile([False, True], len(lengths) // 2), lengths)
    out = np.zeros(num_pixels, np.uint16)
    out[has_value] = (np.cumsum(deltas) & 0xFFFF).astype(np.uint16)  # 16-bit wrap, as the C decoder's short
    return out


def _decode_file(payload: bytes, where: str, what: str) -> np.ndarray:
    try:
        with Image.open(io.BytesIO(payload)) as img:
            img.load()
            mode = img.mode
            pixels = np.asarray(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise CompressedImageError(f"{where}: {what} payload of {len(payload)} bytes does not decode: {exc}") from exc
    if pixels.ndim != 2:
        raise CompressedImageError(f"{where}: {what} image has mode {mode} ({pixels.shape}); expected one channel")
    if mode.startswith("I;16") or mode == "I":  # Pillow opens some 16-bit PNGs as 32-bit integers ("I")
        return pixels.astype(np.uint16)
    return pixels


def _compressed_depth(payload: bytes, encoding: str, kind: str, where: str) -> np.ndarray:
    if len(payload) <= CONFIG_HEADER_BYTES:
        raise CompressedImageError(
            f"{where}: compressedDepth payload of {len(payload)} bytes; expected a {CONFIG_HEADER_BYTES}-byte "
            "ConfigHeader and an image"
        )
    _, quant_a, quant_b = struct.unpack("<iff", payload[:CONFIG_HEADER_BYTES])
    body = payload[CONFIG_HEADER_BYTES:]
    if kind == "rvl":
        if len(body) < 8:
            raise CompressedImageError(f"{where}: RVL image of {len(body)} bytes has no width and height")
        width, height = struct.unpack("<II", body[:8])
        if width == 0 or height == 0 or width * height > 1 << 28:
            raise CompressedImageError(f"{where}: RVL image says {width} x {height} pixels")
        coded = rvl_decode(body[8:], width * height, where).reshape(height, width)
    else:
        coded = _decode_file(body, where, "compressedDepth PNG")
        if coded.dtype != np.uint16:
            raise CompressedImageError(f"{where}: compressedDepth PNG is {coded.dtype}; expected 16-bit grey")
    if encoding in _UINT16_ENCODINGS:
        return coded
    if encoding == "32FC1":
        with np.errstate(divide="ignore"):
            metres = np.float32(quant_a) / (coded.astype(np.float32) - np.float32(quant_b))
        return np.where(coded > 0, metres, np.float32(np.nan)).astype(np.float32)
    raise CompressedImageError(
        f"{where}: compressedDepth of source encoding {encoding!r}; expected 16UC1, mono16 or 32FC1"
    )


def decode_compressed_image(payload: bytes, fmt: str, where: str) -> tuple[np.ndarray, str]:
    """``(pixels, encoding)`` of a CompressedImage: uint16 for 16-bit encodings, float32 metres (NaN = invalid) for
    a 32FC1 compressedDepth, uint8 for 8-bit images. ``encoding`` is the source encoding the format names (for a
    bare ``png``/``jpeg``, the one the decoded image has: ``mono16`` or ``mono8``)."""
    try:
        encoding, codec = parse_compressed_format(fmt)
    except CompressedImageError as exc:
        raise CompressedImageError(f"{where}: {exc}") from None
    payload = bytes(payload)
    if codec.startswith("compressedDepth"):
        return _compressed_depth(payload, encoding, codec.split()[1], where), encoding
    pixels = _decode_file(payload, where, codec.upper())
    if not encoding:
        encoding = "mono16" if pixels.dtype == np.uint16 else "mono8"
    return pixels, encoding
