"""Readers: clear errors naming the file and the expectation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.atomic import atomic_write
from tofdenoise.data_modules.io import (
    DataFileError,
    depth_mm_to_png16,
    read_amplitude,
    read_depth_mm,
    read_mat,
    read_npy,
    read_png_uint16,
    write_depth_png16,
)


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        read_depth_mm(tmp_path / "nope.png")


def test_unreadable_image_names_the_file(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"this is not a png")
    with pytest.raises(DataFileError, match="broken.png.*could not be decoded"):
        read_amplitude(bad)


def test_wrong_dtype_is_rejected_with_expectation(tmp_path):
    path = tmp_path / "depth8.png"
    cv2.imwrite(str(path), np.full((4, 5), 7, np.uint8))
    eight_bit = r"has dtype {}; 8-bit values cannot hold depth in millimetres: expected a 16-bit PNG/TIFF"
    with pytest.raises(DataFileError, match=r"depth8.png " + eight_bit.format("uint8")):
        read_depth_mm(path)
    with pytest.raises(DataFileError, match="uint16"):
        read_png_uint16(path)
    colour = tmp_path / "colour16.png"
    cv2.imwrite(str(colour), np.zeros((4, 5, 3), np.uint16))
    with pytest.raises(DataFileError, match="3 channels; expected a single-channel"):
        read_depth_mm(colour)
    assert read_amplitude(colour).shape == (4, 5)  # amplitude accepts colour (converted to grey)


def test_png16_npy_and_mat_values(tmp_path):
    import scipy.io

    depth = (np.arange(20, dtype=np.uint16) * 100).reshape(4, 5)
    cv2.imwrite(str(tmp_path / "d.png"), depth)
    np.testing.assert_array_equal(read_depth_mm(tmp_path / "d.png"), depth.astype(np.float32))
    np.save(tmp_path / "d.npy", depth.astype(np.float64) / 1000.0)
    np.testing.assert_allclose(read_depth_mm(tmp_path / "d.npy", scale_mm=1000.0), depth, rtol=1e-6)
    scipy.io.savemat(tmp_path / "d.mat", {"gt_depth": depth.astype(np.float32)})
    np.testing.assert_array_equal(read_mat(tmp_path / "d.mat", "gt_depth"), depth)
    with pytest.raises(DataFileError, match="no variable 'conf'"):
        read_mat(tmp_path / "d.mat", "conf")
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    with pytest.raises(DataFileError, match=r"shape \(2, 3, 4\); expected a 2-D map"):
        read_depth_mm(tmp_path / "cube.npy")
    (tmp_path / "trunc.npy").write_bytes((tmp_path / "d.npy").read_bytes()[:60])
    with pytest.raises(DataFileError, match="trunc.npy could not be read"):
        read_npy(tmp_path / "trunc.npy")


def test_exr_error_explains_opencv_requirement(tmp_path):
    path = tmp_path / "depth.exr"
    path.write_bytes(b"\x76\x2f\x31\x01" + b"\x00" * 64)  # EXR magic, no valid content
    with pytest.raises(DataFileError, match="OPENCV_IO_ENABLE_OPENEXR"):
        read_depth_mm(path)


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "depth.bmpx"
    path.write_bytes(b"x")
    with pytest.raises(DataFileError, match="unsupported suffix"):
        read_depth_mm(path)


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def failing(tmp):
        tmp.write_text("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, failing)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_depth_png16_rounds_keeps_validity_and_marks_unstorable_invalid():
    d = np.array([[0.4, 0.6, 1234.5, 1235.5, 65535.4], [np.nan, -3.0, np.inf, 65535.5, 70000.0]])
    png = depth_mm_to_png16(d)
    assert png.dtype == np.uint16
    # half to even; a positive depth never rounds to the invalid 0; beyond 65535.5 mm cannot be stored
    assert png.tolist() == [[1, 1, 1234, 1236, 65535], [0, 0, 0, 0, 0]]


def test_write_depth_png16_is_atomic_and_warns_about_lost_pixels(tmp_path):
    d = np.array([[1000.2, 70000.0], [np.nan, 2.0]])
    with pytest.warns(RuntimeWarning, match=r"a\.png: 1 pixel\(s\) deeper than 65535 mm"):
        write_depth_png16(tmp_path / "a.png", d)
    back = read_depth_mm(tmp_path / "a.png")
    assert back.dtype == np.float32 and back.tolist() == [[1000.0, 0.0], [0.0, 2.0]]
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary file left
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_depth_png16(tmp_path / "b.png", np.full((2, 2), 500.0))  # nothing lost: no warning


def test_8bit_depth_arrays_are_refused_like_an_8bit_png(tmp_path):
    """A uint8 .npy of depth / 20 (true median 1774 mm) was read as millimetres (median 88 mm): every 8-bit integer
    array is refused with the 8-bit PNG's message, naming the file and its dtype; 16-bit and wider arrays still read."""
    import scipy.io

    depth = np.random.default_rng(0).uniform(500, 3000, size=(6, 7))
    eight = (depth / 20).astype(np.uint8)
    np.save(tmp_path / "u8.npy", eight)
    np.save(tmp_path / "i8.npy", eight.astype(np.int8) // 2)
    np.savez(tmp_path / "u8.npz", depth=eight)
    scipy.io.savemat(tmp_path / "u8.mat", {"depth": eight})
    cv2.imwrite(str(tmp_path / "u8.png"), eight)
    with pytest.raises(DataFileError) as png:
        read_depth_mm(tmp_path / "u8.png")
    for name, dtype, key in [("u8.npy", "uint8", None), ("i8.npy", "int8", None), ("u8.npz", "uint8", None)] + [
        ("u8.mat", "uint8", "depth")
    ]:
        with pytest.raises(DataFileError) as info:
            read_depth_mm(tmp_path / name, key=key, what="folder depth")
        expected = str(png.value).replace("depth file", "folder depth file").replace("u8.png", name)
        assert str(info.value) == expected.replace("dtype uint8", f"dtype {dtype}")
    for dtype in (np.uint16, np.int16, np.int32, np.float16, np.float32):
        np.save(tmp_path / "ok.npy", np.rint(depth).astype(dtype))
        assert np.median(read_depth_mm(tmp_path / "ok.npy")) == pytest.approx(np.median(np.rint(depth)), rel=1e-3)
