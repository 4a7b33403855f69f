"""Standard depth outputs: 32FC1 metres with NaN (REP 118) as float32 TIFF, the PLY point cloud against hand-computed
points, the intrinsics files and their errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tofdenoise.inference.camera import (
    Intrinsics,
    IntrinsicsError,
    KinectCalibration,
    load_intrinsics,
    points_m,
    resolve_intrinsics,
)
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


def kinect_calibration_json() -> str:
    """An Azure Kinect calibration.json as the Sensor SDK writes it (k4a_device_get_raw_calibration): the depth
    camera D0 with unitised [cx, cy, fx, fy, k1..k6, codx, cody, p2, p1] and its metric radius, and the colour
    camera PV0 (ignored)."""
    depth = [0.5, 0.51, 0.49, 0.492, 0.61, -2.9, 1.6, 0.49, -2.7, 1.5, 0.0, 0.0, -1e-4, 5e-5]
    colour = [0.4987, 0.5063, 0.4797, 0.6395, 0.53, -2.6, 1.5, 0.41, -2.4, 1.4, 0.0, 0.0, 7e-4, -2e-4]
    cameras = [
        {
            "Intrinsics": {
                "ModelParameterCount": 14,
                "ModelParameters": depth,
                "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
            },
            "Location": "CALIBRATION_CameraLocationD0",
            "MetricRadius": 1.74,
            "Purpose": "CALIBRATION_CameraPurposeDepth",
            "Rt": {"Rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1], "Translation": [0, 0, 0]},
            "SensorHeight": 1024,
            "SensorWidth": 1024,
            "Shutter": "CALIBRATION_ShutterTypeUndefined",
        },
        {
            "Intrinsics": {
                "ModelParameterCount": 14,
                "ModelParameters": colour,
                "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
            },
            "Location": "CALIBRATION_CameraLocationPV0",
            "MetricRadius": 0,
            "Purpose": "CALIBRATION_CameraPurposePhotoVideo",
            "SensorHeight": 3072,
            "SensorWidth": 4096,
        },
    ]
    return json.dumps({"CalibrationInformation": {"Cameras": cameras, "FactoryCalToolVersion": "x"}}, indent=2)


def test_the_azure_kinects_own_calibration_json_gives_the_depth_modes_intrinsics(tmp_path):
    path = tmp_path / "calibration.json"
    path.write_text(kinect_calibration_json())
    calibration = load_intrinsics(path)
    assert isinstance(calibration, KinectCalibration)
    # NFOV unbinned, 640 x 576: the 1024 x 1024 unitised parameters, less the crop (192, 180) and half a pixel
    intr = resolve_intrinsics(calibration, (576, 640), "f")
    assert (intr.width, intr.height) == (640, 576)
    assert intr.fx == pytest.approx(0.49 * 1024) and intr.fx == pytest.approx(501.76)
    assert intr.fy == pytest.approx(503.808)
    assert intr.cx == pytest.approx(512 - 192 - 0.5) and intr.cx == pytest.approx(319.5)
    assert intr.cy == pytest.approx(522.24 - 180 - 0.5) and intr.cy == pytest.approx(341.74)
    # NFOV 2x2 binned, 320 x 288: 512 x 512 bins, crop (96, 90)
    binned = resolve_intrinsics(calibration, (288, 320), "f")
    assert (binned.fx, binned.fy) == pytest.approx((250.88, 251.904))
    assert (binned.cx, binned.cy) == pytest.approx((159.5, 170.62))
    # WFOV 2x2 binned, 512 x 512: no crop
    wide = resolve_intrinsics(calibration, (512, 512), "f")
    assert (wide.fx, wide.cx, wide.cy) == pytest.approx((250.88, 255.5, 260.62))
    with pytest.raises(IntrinsicsError, match=r"640 x 576 \(NFOV_UNBINNED\).*frame g is 64 x 48") as err:
        resolve_intrinsics(calibration, (48, 64), "g")
    assert "calibration.json" in str(err.value) and "\n" not in str(err.value)
    no_depth = tmp_path / "colour_only.json"
    doc = json.loads(kinect_calibration_json())
    del doc["CalibrationInformation"]["Cameras"][0]
    no_depth.write_text(json.dumps(doc))
    with pytest.raises(
        IntrinsicsError, match=r"colour_only.json.*no depth camera \(Location CALIBRATION_CameraLocationD0"
    ):
        load_intrinsics(no_depth)


OPENCV_YAML = """%YAML:1.0
---
calibration_time: "Thu 26 Nov 2026 10:00:00 UTC"
nr_of_frames: 25
image_width: 640
image_height: 576
board_width: 9
board_height: 6
square_size: 25.
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 5.0421e+02, 0., 3.2163e+02, 0., 5.0433e+02,
       3.2921e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ 1.2e-01, -2.5e-01, 0., 0., 1.1e-01 ]
avg_reprojection_error: 2.1e-01
"""


def test_opencv_filestorage_yaml_and_xml(tmp_path):
    """OpenCV's calibration sample's output (cv::FileStorage: %YAML:1.0 header, !!opencv-matrix), which PyYAML
    cannot read, and the same file as OpenCV writes it today (XML, and YAML with a %YAML 1.2 header)."""
    path = tmp_path / "out_camera_data.yml"
    path.write_text(OPENCV_YAML)
    intr = load_intrinsics(path)
    assert intr == Intrinsics(504.21, 504.33, 321.63, 329.21, 640, 576, source=str(path))
    k = np.array([[504.21, 0, 321.63], [0, 504.33, 329.21], [0, 0, 1]])
    for name in ("written.yml", "written.xml"):
        storage = cv2.FileStorage(str(tmp_path / name), cv2.FILE_STORAGE_WRITE)
        storage.write("image_width", 640)
        storage.write("image_height", 576)
        storage.write("camera_matrix", k)
        storage.write("distortion_coefficients", np.zeros((5, 1)))
        storage.release()
        written = load_intrinsics(tmp_path / name)
        assert (written.fx, written.fy, written.cx, written.cy) == (504.21, 504.33, 321.63, 329.21)
        assert (written.width, written.height) == (640, 576)
    no_size = tmp_path / "no_size.yml"
    no_size.write_text(OPENCV_YAML.replace("image_height: 576\n", ""))
    with pytest.raises(IntrinsicsError, match=r"no_size.yml: field 'image_height' is missing"):
        load_intrinsics(no_size)
    broken = tmp_path / "broken.yml"
    broken.write_text(OPENCV_YAML.replace("   cols: 3\n", "   cols: [\n", 1))
    with pytest.raises(IntrinsicsError, match=r"broken.yml could not be read as an OpenCV FileStorage file") as err:
        load_intrinsics(broken)
    assert "\n" not in str(err.value)


def test_a_file_of_no_known_form_names_the_file_and_the_forms(tmp_path):
    path = tmp_path / "cam.yaml"
    path.write_text("focal_length_mm: 2.8\nsensor: imx556\n")
    with pytest.raises(IntrinsicsError) as err:
        load_intrinsics(path)
    message = str(err.value)
    assert "cam.yaml" in message and "\n" not in message
    for form in ("fx, fy, cx, cy, width, height", "ROS camera_info", "OpenCV FileStorage", "calibration.json"):
        assert form in message
