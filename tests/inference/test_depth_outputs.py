"""Standard depth outputs: 32FC1 metres with NaN (REP 118) as float32 TIFF, the PLY point cloud against hand-computed
points, the intrinsics files and their errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.inference.camera import Intrinsics, IntrinsicsError, load_intrinsics, points_m
from tofdenoise.inference.outputs import (
    OutputOptions,
    depth_mm_to_m,
    output_paths,
    write_depth_m_tiff,
    write_frame_outputs,
    write_ply_points,
)


def read_ply(path) -> tuple[list[str], np.ndarray]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    count = int(next(line for line in header if line.startswith("element vertex")).split()[-1])
    points = np.frombuffer(data[end:], dtype="<f4").reshape(-1, 3)
    assert len(points) == count and len(data) == end + 12 * count
    return header, points


def test_depth_m_tiff_is_float32_metres_with_nan_bit_for_bit(tmp_path):
    depth_mm = np.array([[0, 1234, 1], [65535, 500.5, np.nan], [-3, np.inf, 2999]], dtype=np.float32)
    path = write_depth_m_tiff(tmp_path / "d_depth_m.tiff", depth_mm)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.float32 and back.shape == (3, 3)
    invalid = np.array([[1, 0, 0], [0, 0, 1], [1, 1, 0]], dtype=bool)
    assert np.array_equal(np.isnan(back), invalid)
    expected = np.array([[0, 1.234, 0.001], [65.535, 0.5005, 0], [0, 0, 2.999]], dtype=np.float64)
    assert np.array_equal(back[~invalid], expected[~invalid].astype(np.float32))
    assert np.array_equal(depth_mm_to_m(depth_mm)[~invalid], back[~invalid])


def test_ply_points_equal_hand_computed_back_projection(tmp_path):
    # 2 x 3 z-depth map [mm], fx 100, fy 200, cx 1, cy 0.5; pixel (u, v) -> ((u-cx) z/fx, (v-cy) z/fy, z)
    depth_mm = np.array([[1000, 0, 2000], [np.nan, 500, 4000]], dtype=np.float32)
    intr = Intrinsics(fx=100.0, fy=200.0, cx=1.0, cy=0.5, width=3, height=2)
    write_frame_outputs(tmp_path, "f", depth_mm, depth_mm > 0, depth_mm, OutputOptions(ply=True), intrinsics=intr)
    header, points = read_ply(output_paths(tmp_path, "f")["ply"])
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert [h for h in header if h.startswith("property")] == [
        "property float x",
        "property float y",
        "property float z",
    ]
    expected = np.array(
        [
            [-0.01, -0.0025, 1.0],  # (u 0, v 0, z 1 m): x = -1 * 1 / 100, y = -0.5 * 1 / 200
            [0.02, -0.005, 2.0],  # (2, 0, 2 m): x = 1 * 2 / 100, y = -0.5 * 2 / 200
            [0.0, 0.00125, 0.5],  # (1, 1, 0.5 m): x = 0, y = 0.5 * 0.5 / 200
            [0.04, 0.01, 4.0],  # (2, 1, 4 m): x = 1 * 4 / 100, y = 0.5 * 4 / 200
        ],
        dtype=np.float32,
    )
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-7)


def test_ply_needs_intrinsics_of_the_frame_size_and_writes_nothing_without(tmp_path):
    depth = np.full((4, 5), 1000.0, np.float32)
    with pytest.raises(ValueError, match="needs the camera intrinsics"):
        write_frame_outputs(tmp_path, "g", depth, depth > 0, depth, OutputOptions(ply=True))
    with pytest.raises(IntrinsicsError, match=r"describe a 6 x 4 image; frame g is 5 x 4"):
        write_frame_outputs(
            tmp_path, "g", depth, depth > 0, depth, OutputOptions(ply=True), intrinsics=Intrinsics(1, 1, 0, 0, 6, 4)
        )
    assert list(tmp_path.iterdir()) == []


def test_ply_writer_is_atomic_and_checks_shape(tmp_path):
    with pytest.raises(ValueError, match=r"expected \(N, 3\) points"):
        write_ply_points(tmp_path / "p.ply", np.zeros((4, 2)))
    path = write_ply_points(tmp_path / "p.ply", np.zeros((0, 3)))
    assert read_ply(path)[1].shape == (0, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.ply"]


def test_points_m_keeps_row_order_and_only_valid_pixels():
    depth_m = np.array([[np.nan, 1.0], [0.0, 2.0]])
    pts = points_m(depth_m, Intrinsics(1.0, 1.0, 0.0, 0.0, 2, 2))
    assert pts.dtype == np.float32
    assert pts.tolist() == [[1.0, 0.0, 1.0], [2.0, 2.0, 2.0]]


def test_intrinsics_files_plain_and_ros_camera_info(tmp_path):
    plain = tmp_path / "cam.yaml"
    plain.write_text("fx: 504.2\nfy: 504.3\ncx: 321.6\ncy: 329.2\nwidth: 640\nheight: 576\n")
    assert load_intrinsics(plain) == Intrinsics(504.2, 504.3, 321.6, 329.2, 640, 576, source=str(plain))
    ros = tmp_path / "depth.yaml"
    ros.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: depth\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [525.0, 0, 319.5, 0, 526.0, 239.5, 0, 0, 1]\n"
    )
    intr = load_intrinsics(ros)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (525.0, 526.0, 319.5, 239.5, 640, 480)
    js = tmp_path / "c.json"
    js.write_text('{"fx": 1, "fy": 2, "cx": 3, "cy": 4, "width": 5, "height": 6}')
    assert load_intrinsics(js).fy == 2.0


@pytest.mark.parametrize(
    "text,match",
    [
        ("fx: 500\nfy: 500\ncx: 1\nwidth: 4\nheight: 4\n", r"field 'cy' is missing"),
        ("fx: -5\nfy: 500\ncx: 1\ncy: 1\nwidth: 4\nheight: 4\n", r"fx must be a positive number"),
        ("fx: abc\nfy: 500\ncx: 1\ncy: 1\nwidth: 4\nheight: 4\n", r"field 'fx' must be a number"),
        ("fx: 5\nfy: 500\ncx: 1\ncy: 1\nwidth: 4.5\nheight: 4\n", r"whole pixels"),
        ("- 1\n- 2\n", r"expected a mapping"),
    ],
)
def test_bad_intrinsics_name_the_file_and_field(tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(IntrinsicsError, match=match) as err:
        load_intrinsics(path)
    assert "bad.yaml" in str(err.value) or "fx must" in str(err.value)
    with pytest.raises(IntrinsicsError, match="not found"):
        load_intrinsics(tmp_path / "missing.yaml")
