"""The camera model (``verify.camera``): the camera files users have (ROS camera_info, Kalibr camchain, EuRoC
sensor.yaml, the small form), ``--intrinsics``, keypoints undistorted through radial-tangential and equidistant
lenses, and a table of bad camera files refused with the file named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from verify.camera import camera_from_options, parse_intrinsics, read_camera_file, undistort_points
from verify.geometry import GeometricVerifier

K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])

ROS = """image_width: 752
image_height: 480
camera_name: cam0
camera_matrix:
  rows: 3
  cols: 3
  data: [458.654, 0, 367.215, 0, 457.296, 248.375, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]
"""
KALIBR = """cam0:
  camera_model: pinhole
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  distortion_model: equidistant
  distortion_coeffs: [0.01, -0.02, 0.003, -0.001]
  T_cam_imu:
  - [1, 0, 0, 0.1]
  - [0, 1, 0, 0]
  - [0, 0, 1, 0]
  - [0, 0, 0, 1]
  resolution: [752, 480]
cam1:
  camera_model: pinhole
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  distortion_model: radtan
  distortion_coeffs: [-0.28368365, 0.07451284, -0.00010473, -3.555907e-05]
"""
EUROC = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
SMALL = "intrinsics: [458.654, 457.296, 367.215, 248.375]\ndistortion_model: fisheye\n" \
        "distortion_coefficients: [0.01, -0.02, 0.003, -0.001]\n"


@pytest.mark.parametrize("text, model, n, has_T", [(ROS, "radtan", 5, False), (KALIBR, "equidistant", 4, True),
                                                   (EUROC, "radtan", 4, True), (SMALL, "equidistant", 4, False)])
def test_camera_files(tmp_path, text, model, n, has_T):
    path = tmp_path / "camera.yaml"
    path.write_text(text)
    cam = read_camera_file(path)
    assert np.allclose(cam.K, K) and cam.model == model and len(cam.coefficients) == n
    assert (cam.T_body_camera is not None) == has_T
    assert GeometricVerifier(cam.geometry_conf()).conf["distortion_model"] == model


def test_kalibr_other_camera_and_body_pose(tmp_path):
    path = tmp_path / "camchain.yaml"
    path.write_text(KALIBR)
    assert read_camera_file(path, "cam1").model == "radtan"
    assert np.allclose(read_camera_file(path).T_body_camera[:3, 3], [-0.1, 0, 0])  # T_cam_imu inverted
    with pytest.raises(ConfigError, match="no camera cam2"):
        read_camera_file(path, "cam2")


def test_intrinsics_option_overrides_the_file(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(SMALL)
    cam = camera_from_options("400,400,320,240", path)
    assert cam.K[0, 0] == 400 and cam.model == "equidistant"
    assert camera_from_options() is None
    assert camera_from_options("400,401,320,240").model == "none"
    assert np.allclose(parse_intrinsics([1, 2, 3, 4]), [[1, 0, 3], [0, 2, 4], [0, 0, 1]])


BAD = [
    ("not yaml", "a: [", "cannot read camera file"),
    ("a list", "- 1\n- 2\n", "not a camera file"),
    ("no camera", "foo: 1\n", "not a camera file"),
    ("three intrinsics", "intrinsics: [1, 2, 3]\n", "four numbers"),
    ("negative focal", "intrinsics: [-1, 2, 3, 4]\n", "fx, fy > 0|camera matrix"),
    ("unknown model", "intrinsics: [1, 2, 3, 4]\ndistortion_model: scaramuzza\ndistortion_coefficients: [1]\n",
     "unknown distortion model"),
    ("wrong count", "intrinsics: [1, 2, 3, 4]\ndistortion_model: equidistant\ndistortion_coefficients: [1, 2]\n",
     "takes 4 coefficients"),
    ("nan coefficient", "intrinsics: [1, 2, 3, 4]\ndistortion_model: radtan\n"
     "distortion_coefficients: [.nan, 0, 0, 0]\n", "finite"),
    ("text coefficient", "intrinsics: [1, 2, 3, 4]\ndistortion_model: radtan\n"
     "distortion_coefficients: [a, 0, 0, 0]\n", "must be numbers"),
    ("ros matrix 2x2", "camera_matrix: {data: [1, 0, 0, 1]}\n", "3x3 matrix"),
    ("bad T_BS", "intrinsics: [1, 2, 3, 4]\nT_BS: {data: [1, 2]}\n", "4x4 matrix"),
]


@pytest.mark.parametrize("name, text, message", BAD, ids=[b[0] for b in BAD])
def test_bad_camera_files_are_one_error_naming_the_file(tmp_path, name, text, message):
    path = tmp_path / "camera.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        read_camera_file(path)
    assert "camera.yaml" in str(err.value) or "intrinsics" in str(err.value)


@pytest.mark.parametrize("text", ["a", "1,2,3", "1,2,3,x", "0,1,2,3", "nan,1,1,1"])
def test_bad_intrinsics_option(text):
    with pytest.raises(ConfigError, match="--intrinsics"):
        parse_intrinsics(text)


def test_the_conf_refuses_a_wrong_coefficient_count():
    with pytest.raises(ConfigError, match="takes 4 coefficients"):
        GeometricVerifier({"distortion_model": "equidistant", "distortion_coefficients": [0.1]})
    with pytest.raises(ConfigError, match="distortion_model"):
        GeometricVerifier({"distortion_model": "scaramuzza"})


@pytest.mark.parametrize("model, D", [("radtan", [-0.28, 0.074, 0.0002, 1.8e-5]),
                                      ("equidistant", [0.01, -0.02, 0.003, -0.001])])
def test_undistorted_points_are_where_a_pinhole_sees_them(model, D):
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-0.8, 0.8, (200, 2)), np.ones(200)] * 2.0  # in front of the camera, in its image
    ideal = (X / X[:, 2:]) @ K.T
    rvec = tvec = np.zeros(3)
    if model == "equidistant":
        seen = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, K, np.array(D))[0].reshape(-1, 2)
    else:
        seen = cv2.projectPoints(X, rvec, tvec, K, np.array(D))[0].reshape(-1, 2)
    assert np.abs(seen - ideal[:, :2]).max() > 5  # the lens moves them
    np.testing.assert_allclose(undistort_points(seen, K, model, D), ideal[:, :2], atol=0.05)
    assert undistort_points(seen, K, "none", ()) is not None and np.array_equal(undistort_points(seen, K, "none", ()),
                                                                                 seen)
