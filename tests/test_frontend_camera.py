"""Camera files in every supported format, size fitting, FOV guess, undistortion."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.frontend.camera import (
    Undistorter,
    camera_for_recording,
    fit_camera,
    guess_camera,
    read_camera_file,
    scale_camera,
)
from papl_mapper.map import Camera

CAM = Camera(1280, 720, 900.0, 905.0, 640.2, 355.7, np.array([-0.12, 0.05, 0.001, -0.002, 0.0]))


def _same(a: Camera, b: Camera, tol: float = 1e-9) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=tol)
    n = min(len(a.distortion), len(b.distortion))
    np.testing.assert_allclose(a.distortion[:n], b.distortion[:n], atol=tol)


def test_our_camera_json(tmp_path):
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(CAM.to_dict()))
    _same(read_camera_file(p), CAM)


@pytest.mark.parametrize("suffix", [".yml", ".json", ".xml"])
def test_opencv_filestorage(tmp_path, suffix):
    p = tmp_path / f"calib{suffix}"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", CAM.width)
    fs.write("image_height", CAM.height)
    fs.write("camera_matrix", CAM.K)
    fs.write("distortion_coefficients", CAM.distortion.reshape(1, 5))
    fs.release()
    _same(read_camera_file(p), CAM)


def test_plain_json_with_camera_matrix(tmp_path):
    p = tmp_path / "intrinsics.json"
    p.write_text(json.dumps({"camera_matrix": CAM.K.tolist(), "dist_coeffs": CAM.distortion.tolist()}))
    cam = read_camera_file(p)
    assert (cam.width, cam.height) == (0, 0)  # unknown size: adopts the recording's
    _same(fit_camera(cam, 1280, 720), CAM)


@pytest.mark.parametrize(
    "model, params, expect",
    [
        ("PINHOLE", "900 905 640.7 356.2", (900, 905, 640.2, 355.7, [0, 0, 0, 0])),
        ("SIMPLE_PINHOLE", "900 640.7 356.2", (900, 900, 640.2, 355.7, [0, 0, 0, 0])),
        ("SIMPLE_RADIAL", "900 640.7 356.2 -0.1", (900, 900, 640.2, 355.7, [-0.1, 0, 0, 0])),
        ("RADIAL", "900 640.7 356.2 -0.1 0.02", (900, 900, 640.2, 355.7, [-0.1, 0.02, 0, 0])),
        (
            "OPENCV",
            "900 905 640.7 356.2 -0.1 0.02 0.001 -0.002",
            (900, 905, 640.2, 355.7, [-0.1, 0.02, 0.001, -0.002]),
        ),
    ],
)
def test_colmap_models_and_half_pixel_shift(tmp_path, model, params, expect):
    p = tmp_path / "cameras.txt"
    p.write_text(f"# Camera list\n# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 {model} 1280 720 {params}\n")
    cam = read_camera_file(p)
    fx, fy, cx, cy, dist = expect
    assert (cam.width, cam.height) == (1280, 720)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [fx, fy, cx, cy], atol=1e-9)
    np.testing.assert_allclose(cam.distortion[:4], dist, atol=1e-12)


def test_colmap_unsupported_model(tmp_path):
    p = tmp_path / "cameras.txt"
    p.write_text("1 FISHEYE 640 480 1 2 3 4\n")
    with pytest.raises(InputError, match="FISHEYE"):
        read_camera_file(p)


def test_kitti_calib(tmp_path):
    p = tmp_path / "calib.txt"
    P0 = np.array([[718.856, 0, 607.1928, 0], [0, 718.856, 185.2157, 0], [0, 0, 1, 0]])
    P2 = P0.copy()
    P2[0, 3] = 45.0
    p.write_text(
        "P0: " + " ".join(f"{v:.6e}" for v in P0.ravel()) + "\n"
        "P1: " + " ".join(f"{v:.6e}" for v in P0.ravel()) + "\n"
        "P2: " + " ".join(f"{v:.6e}" for v in P2.ravel()) + "\nTr: " + " ".join(["0"] * 12) + "\n"
    )
    cam = fit_camera(read_camera_file(p), 1241, 376)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [718.856, 718.856, 607.1928, 185.2157])
    assert (cam.width, cam.height) == (1241, 376)


EUROC_SENSOR_YAML = """%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
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
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
EUROC = Camera(
    752,
    480,
    458.654,
    457.296,
    367.215,
    248.375,
    np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]),
)


def test_euroc_sensor_yaml(tmp_path):
    p = tmp_path / "sensor.yaml"
    p.write_text(EUROC_SENSOR_YAML)
    _same(read_camera_file(p), EUROC)


KALIBR_CAMCHAIN_YAML = """cam0:
  camera_model: pinhole
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  distortion_model: radtan
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  resolution: [752, 480]
cam1:
  camera_model: pinhole
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  distortion_model: radtan
  distortion_coeffs: [0, 0, 0, 0]
  resolution: [752, 480]
"""
ORBSLAM_SETTINGS_YAML = """%YAML:1.0
Camera.type: "PinHole"
{p}fx: 458.654
{p}fy: 457.296
{p}cx: 367.215
{p}cy: 248.375
{p}k1: -0.28340811
{p}k2: 0.07395907
{p}p1: 0.00019359
{p}p2: 1.76187114e-05
Camera.width: 752
Camera.height: 480
Camera.fps: 20
Camera.RGB: 1
ORBextractor.nFeatures: 1000
"""


def test_kalibr_camchain_uses_cam0(tmp_path):
    p = tmp_path / "camchain.yaml"
    p.write_text(KALIBR_CAMCHAIN_YAML)
    _same(read_camera_file(p), EUROC)


@pytest.mark.parametrize("prefix", ["Camera.", "Camera1."])
def test_orbslam_settings(tmp_path, prefix):
    """ORB-SLAM2 settings (`Camera.fx`) and ORB-SLAM3's (`Camera1.fx`, `Camera.type`, the size keys)."""
    p = tmp_path / "EuRoC.yaml"
    p.write_text(ORBSLAM_SETTINGS_YAML.format(p=prefix))
    _same(read_camera_file(p), EUROC)


@pytest.mark.parametrize(
    "text, message",
    [
        (
            EUROC_SENSOR_YAML.replace("radial-tangential", "equidistant"),
            "equidistant distortion is not supported",
        ),
        ("cam0:\n  camera_model: omni\n  intrinsics: [1, 2, 3, 4]\n", "camera model omni"),
        ('Camera.type: "KannalaBrandt8"\nCamera1.fx: 400\n', "camera type kannalabrandt8"),
        ("Camera.fx: 400\nCamera.fy: 400\nCamera.cx: 320\n", "without Camera.cy"),
        (EUROC_SENSOR_YAML.replace("[752, 480]", "[752, -480]"), "not a valid EuRoC"),
    ],
)
def test_dataset_yaml_that_cannot_be_used_names_the_file(tmp_path, text, message):
    p = tmp_path / "calib.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        read_camera_file(p)
    assert str(p) in str(err.value)


def test_unrecognised_and_missing_files(tmp_path):
    p = tmp_path / "cam.txt"
    p.write_text("hello world\n")
    with pytest.raises(InputError, match="unrecognised"):
        read_camera_file(p)
    with pytest.raises(InputError, match="not found"):
        read_camera_file(tmp_path / "nope.yml")


def test_guess_from_horizontal_fov(caplog):
    src = camera_for_recording(None, 1280, 720, hfov_deg=90.0)
    assert src.guessed and "guess" in src.source
    assert src.camera.fx == pytest.approx(640.0)
    assert (src.camera.cx, src.camera.cy) == (639.5, 359.5)
    # the horizontal FOV of the guess, measured from the pixel edges, is the one asked for
    cam = guess_camera(640, 480, 60.0)
    assert math.degrees(2 * math.atan((cam.width / 2) / cam.fx)) == pytest.approx(60.0)
    assert "guessing intrinsics" in caplog.text


def test_size_policy_scales_same_aspect_and_rejects_other(tmp_path):
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(CAM.to_dict()))
    src = camera_for_recording(p, 640, 360)
    assert src.scaled_from == (1280, 720) and not src.guessed
    cam = src.camera
    assert cam.fx == pytest.approx(450.0) and cam.fy == pytest.approx(452.5)
    # pixel centres are integers: the centre of source pixel (0, 0) ... the image corner maps to the corner
    assert (cam.cx + 0.5) * 2 == pytest.approx(CAM.cx + 0.5)
    with pytest.raises(InputError, match="aspect"):
        camera_for_recording(p, 640, 480)


def test_scale_then_project_matches_resized_image():
    """A 3D point projects to the same place in a resized image as the source pixel scaled about edges."""
    X = np.array([0.3, -0.2, 2.0])
    cam = Camera(1280, 720, 900, 900, 640.2, 355.7, np.zeros(5))
    small = scale_camera(cam, 320, 180)
    u_big = (cam.K @ X)[:2] / X[2]
    u_small = (small.K @ X)[:2] / X[2]
    np.testing.assert_allclose(u_small, (u_big + 0.5) / 4 - 0.5, atol=1e-9)


def test_undistort_points_inverts_distortion():
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-0.6, 0.6, 200), rng.uniform(-0.35, 0.35, 200), np.ones(200)])
    ideal = (X @ CAM.K.T)[:, :2]
    distorted, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), CAM.K, CAM.distortion)
    und = Undistorter(CAM)
    assert not und.identity
    np.testing.assert_allclose(und.points(distorted.reshape(-1, 2)), ideal, atol=1e-3)
    segs = np.hstack([distorted.reshape(-1, 2)[:100], distorted.reshape(-1, 2)[100:]])
    np.testing.assert_allclose(und.segments(segs), np.hstack([ideal[:100], ideal[100:]]), atol=1e-3)
    assert np.all(und.undistorted_camera.distortion == 0)
    ident = Undistorter(scale_camera(guess_camera(640, 480), 640, 480))
    assert ident.identity
    np.testing.assert_array_equal(ident.points(ideal), ideal)
