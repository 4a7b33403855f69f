"""ros_codecs: RVL against a hand-computed stream and an independent encoder, compressedDepth's inverse-depth
quantisation against its closed form, and format strings."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from tofdenoise.inference.ros_codecs import (
    CompressedImageError,
    decode_compressed_image,
    parse_compressed_format,
    rvl_decode,
)


def test_rvl_decodes_a_hand_computed_stream():
    # pixels 0 0 5 7 0: 2 zeros, 2 values (deltas +5 -> zig-zag 10 = nibbles A 1, +2 -> 4), 1 zero, 0 values
    # nibbles 2 2 A 1 4 1 0 (+ one pad) in one word, first nibble most significant: 0x22A14100
    stream = struct.pack("<I", 0x22A14100)
    assert rvl_decode(stream, 5).tolist() == [0, 0, 5, 7, 0]


def test_rvl_round_trips_an_independent_encoder_with_holes_large_values_and_wrapping_deltas(recording_files):
    rng = np.random.default_rng(7)
    px = rng.integers(1, 65535, (23, 31), dtype=np.uint16)
    px[rng.random(px.shape) < 0.3] = 0  # holes: zero runs of every length
    px[0, :9] = 0
    px[-1, -5:] = 0
    px[5, 3], px[5, 4] = 65535, 1  # a delta of -65534 and one of +65534
    decoded = rvl_decode(recording_files.rvl_encode(px), px.size)
    assert decoded.dtype == np.uint16 and np.array_equal(decoded.reshape(px.shape), px)
    assert np.array_equal(rvl_decode(recording_files.rvl_encode(np.zeros(40, np.uint16)), 40), np.zeros(40))


def test_a_truncated_rvl_stream_is_an_error_naming_where(recording_files):
    px = np.arange(1, 201, dtype=np.uint16).reshape(10, 20)
    stream = recording_files.rvl_encode(px)
    with pytest.raises(CompressedImageError, match=r"frame 3: RVL stream ends after \d+ of 200 pixels"):
        rvl_decode(stream[: len(stream) // 2], 200, "frame 3")
    with pytest.raises(CompressedImageError, match="goes past the image's 100 pixels"):
        rvl_decode(stream, 100, "frame 3")


@pytest.mark.parametrize(
    "fmt,expected",
    [
        ("16UC1; compressedDepth png", ("16UC1", "compressedDepth png")),
        ("16UC1; compressedDepth rvl", ("16UC1", "compressedDepth rvl")),
        ("32FC1; compressedDepth", ("32FC1", "compressedDepth png")),
        ("mono16; png compressed mono16", ("mono16", "png")),
        ("mono8; jpeg compressed mono8", ("mono8", "jpeg")),
        ("png", ("", "png")),
    ],
)
def test_format_strings_of_image_transport(fmt, expected):
    assert parse_compressed_format(fmt) == expected


@pytest.mark.parametrize("fmt", ["16UC1; compressedDepth zstd", "16UC1; theora", "h264"])
def test_an_unknown_codec_is_named(fmt):
    with pytest.raises(CompressedImageError, match="format|codec"):
        parse_compressed_format(fmt)


@pytest.mark.parametrize("codec", ["png", "rvl"])
def test_compressed_depth_16uc1_is_exact(recording_files, codec):
    rng = np.random.default_rng(1)
    mm = rng.integers(200, 6000, (12, 16)).astype(np.uint16)
    mm[2:5, 3:9] = 0
    pixels, enc = decode_compressed_image(
        recording_files.compressed_depth_payload(mm, "16UC1", codec), f"16UC1; compressedDepth {codec}", "here"
    )
    assert enc == "16UC1" and pixels.dtype == np.uint16 and np.array_equal(pixels, mm)


@pytest.mark.parametrize("codec", ["png", "rvl"])
def test_compressed_depth_32fc1_inverts_the_quantisation_within_half_a_step(recording_files, codec):
    rng = np.random.default_rng(2)
    z = rng.uniform(0.3, 9.5, (12, 16)).astype(np.float32)
    z[0, :3] = np.nan
    z[1, :2] = 12.0  # beyond depth_max: the publisher writes 0
    q, a, b = recording_files.quantise_inverse_depth(z)
    metres, enc = decode_compressed_image(
        recording_files.compressed_depth_payload(z, "32FC1", codec), f"32FC1; compressedDepth {codec}", "here"
    )
    assert enc == "32FC1" and metres.dtype == np.float32
    invalid = q == 0
    assert invalid[0, :3].all() and invalid[1, :2].all() and np.isnan(metres[invalid]).all()
    # the closed form z = A / (q - B), and the round-trip error of truncating q: dz <= z^2 / A (one step of 1/z)
    assert np.allclose(metres[~invalid], a / (q[~invalid].astype(np.float64) - b), rtol=1e-6)
    assert (np.abs(metres - z)[~invalid] <= z[~invalid] ** 2 / a + 1e-5).all()


def test_damaged_payloads_are_errors_naming_where(recording_files):
    good = recording_files.compressed_depth_payload(np.ones((4, 4), np.uint16), "16UC1", "png")
    with pytest.raises(CompressedImageError, match="topic /d at 5 ns: compressedDepth payload of 8 bytes"):
        decode_compressed_image(b"\0" * 8, "16UC1; compressedDepth png", "topic /d at 5 ns")
    with pytest.raises(CompressedImageError, match="topic /d: compressedDepth PNG payload of .* does not decode"):
        decode_compressed_image(good[:30], "16UC1; compressedDepth png", "topic /d")
    with pytest.raises(CompressedImageError, match="RVL image says 0 x 4"):
        decode_compressed_image(good[:12] + struct.pack("<II", 0, 4), "16UC1; compressedDepth rvl", "topic /d")


def test_a_plain_png_compressed_16_bit_depth_is_exact_and_an_8_bit_one_says_so(recording_files):
    mm = np.arange(1, 1 + 12 * 16, dtype=np.uint16).reshape(12, 16) * 97
    pixels, enc = decode_compressed_image(recording_files.png_bytes(mm), "16UC1; png compressed 16UC1", "here")
    assert enc == "16UC1" and pixels.dtype == np.uint16 and np.array_equal(pixels, mm)
    grey, enc = decode_compressed_image(recording_files.png_bytes(mm.astype(np.uint8)), "png", "here")
    assert enc == "mono8" and grey.dtype == np.uint8


def test_a_stream_of_endless_integers_is_not_rvl():
    # every nibble has its "more follows" bit: no integer ends within 32 bits
    with pytest.raises(CompressedImageError, match="frame 9: RVL stream has an integer of more than 32 bits"):
        rvl_decode(struct.pack("<II", 0x88888888, 0x88888880), 10, "frame 9")
