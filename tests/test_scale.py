"""Scale estimators on maps with a known scale: camera height, markers, known lengths, the choice
between sources, and applying a scale to a map (with and without noise)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.geometry.se3 import project_points
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points
from papl_mapper.scale import (
    ScaleEstimate,
    camera_height_scale,
    choose,
    detect_markers,
    fit_floor,
    line_length_scale,
    marker_scale,
    parse_marker_spec,
    point_distance_scale,
    scale_map,
    units_note,
)

#: map units per metre of the synthetic maps: the answer every estimator must find (1 / this)
UNITS_PER_M = 0.37
CAMERA = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
EYE_M = 1.6


def _look(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_wc of a camera at `centre` looking at `target` with world +Z up (OpenCV axes)."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = centre
    return T


def room_map(noise_m: float = 0.0, slope: float = 0.0, floor: bool = True, seed: int = 0) -> Map:
    """A corridor walk in map units (metres times UNITS_PER_M): floor points (z = slope * x), wall and
    ceiling points, horizontal skirting lines, cameras at EYE_M above the floor under them."""
    rng = np.random.default_rng(seed)
    n_kf = 30
    x = np.linspace(0.0, 12.0, n_kf)
    centres = np.stack([x, np.zeros(n_kf), slope * x + EYE_M], axis=1)
    T = np.array([_look(c, c + [1.0, 0.3 * math.sin(i), -0.1]) for i, c in enumerate(centres)])
    pts = []
    if floor:
        fx, fy = rng.uniform(-1, 13, 1500), rng.uniform(-1, 1, 1500)
        pts.append(np.stack([fx, fy, slope * fx], axis=1))
    for y in (-1.0, 1.0):  # walls: points over every height
        wx, wz = rng.uniform(-1, 13, 1500), rng.uniform(0, 2.6, 1500)
        pts.append(np.stack([wx, np.full(1500, y), wz + slope * wx], axis=1))
    cx = rng.uniform(-1, 13, 500)
    pts.append(np.stack([cx, rng.uniform(-1, 1, 500), 2.6 + slope * cx], axis=1))
    xyz = np.concatenate(pts)
    xyz += rng.normal(0, noise_m, xyz.shape)
    n = len(xyz)
    points = Points(
        np.arange(n), xyz, np.full((n, 3), 128, np.uint8), np.zeros((0, 2), np.int64), np.zeros((0, 2))
    )
    # two skirting lines along +X at 0.1 m, seen from keyframes 0..4
    ends = np.array([[[0.0, y, 0.1], [4.0, y, 0.1]] for y in (-1.0, 1.0)])
    w = np.zeros((2, 3))
    w[:, 1] = 1.0
    obs = np.array([[lid, k] for lid in (0, 1) for k in range(5)])
    lines = Lines(
        np.arange(2), ends, w, np.full(2, LineState.ANCHORED, np.int8), np.zeros(2, np.int64),
        np.full(2, 0.3), obs, np.zeros((len(obs), 4)),
    )  # fmt: skip
    kf = Keyframes(np.arange(n_kf), np.arange(n_kf) * 5, np.arange(n_kf) / 6.0, T)
    m = Map(CAMERA, kf, points, lines, Axes(np.eye(3)[[2, 0, 1]], 0), {"units": "m"})
    m = scale_map(m, ScaleEstimate(UNITS_PER_M, 0.0, "test", "metres to map units"))
    m.metadata = {"units": "arbitrary"}  # as a monocular mapper leaves it
    return m


# ---- camera height ------------------------------------------------------------------------------


@pytest.mark.parametrize("noise_m", [0.0, 0.02])
def test_camera_height_finds_the_scale(noise_m):
    est = camera_height_scale(room_map(noise_m), EYE_M)
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=0.01 if noise_m else 2e-3)
    assert est.source == "camera_height" and 0 < est.rel_sigma < 0.02
    assert est.detail["floor"] == "one level floor under the walk"
    assert abs(est.scale * UNITS_PER_M - 1) <= 4 * est.rel_sigma + 1e-9  # the uncertainty is honest


def test_camera_height_follows_a_sloping_floor():
    """A 3% ramp: one level under the whole walk would be off by metres; the local floor is not."""
    est = camera_height_scale(room_map(0.01, slope=0.03), EYE_M)
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=0.01)
    assert est.detail["floor"] == "around each keyframe (the floor slopes)"


def test_floor_level_is_the_floor_not_the_wall_points():
    floor = fit_floor(room_map(0.01))
    assert floor.drop == pytest.approx(EYE_M * UNITS_PER_M, rel=0.01)
    assert floor.up @ [0, 0, 1] == pytest.approx(1.0)


def test_no_floor_found_is_one_clear_error():
    m = room_map(floor=False)
    m.points.xyz = m.points.xyz[m.points.xyz[:, 2] > 1.2 * UNITS_PER_M]  # nothing below the cameras
    m.points.ids = np.arange(len(m.points.xyz))
    m.points.color = m.points.color[: len(m.points.xyz)]
    m.lines = Lines.empty(3)
    with pytest.raises(InputError, match="no floor found"):
        camera_height_scale(m, EYE_M)


def test_camera_height_must_be_positive():
    with pytest.raises(InputError, match="positive"):
        camera_height_scale(room_map(), -1.65)


# ---- markers ------------------------------------------------------------------------------------

MARKER_CORNERS_M = np.array([[5.0, 2.0, 1.6], [5.2, 2.0, 1.6], [5.2, 2.0, 1.4], [5.0, 2.0, 1.4]])  # on y = 2


def marker_views(m: Map, px_noise: float, rows=range(8, 22), seed: int = 0) -> list[tuple[int, np.ndarray]]:
    """Detections of a 0.2 m marker on the wall y = 2 m seen from keyframes `rows`, with pixel noise."""
    rng = np.random.default_rng(seed)
    X = MARKER_CORNERS_M * UNITS_PER_M
    out = []
    for r in rows:
        T = _look(m.keyframes.T_wc[r, :3, 3], X.mean(axis=0))
        m.keyframes.T_wc[r] = T  # this keyframe turns to look at the marker
        uv, z = project_points(CAMERA.K, T, X)
        assert (z > 0).all()
        out.append((r, uv + rng.normal(0, px_noise, uv.shape)))
    return out


@pytest.mark.parametrize("px_noise", [0.0, 0.3])
def test_marker_finds_the_scale(px_noise):
    m = room_map()
    spec = parse_marker_spec("aruco:4X4_50:7=0.2")
    est = marker_scale(m, spec, marker_views(m, px_noise))
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=1e-6 if px_noise == 0 else 0.01)
    assert est.source == "marker" and est.detail["views"] + est.detail["views_left_out"] == 14
    assert est.detail["views"] >= 10  # the farthest views, under 20 pixels a side, are left out
    if px_noise:
        assert 0 < est.rel_sigma < 0.02
        assert abs(est.scale * UNITS_PER_M - 1) < 4 * est.rel_sigma  # the uncertainty is honest


def test_marker_never_seen_once_seen_or_grazing_are_refused():
    m = room_map()
    spec = parse_marker_spec("aruco:4X4_50:7=0.2")
    with pytest.raises(InputError, match="never detected"):
        marker_scale(m, spec, [])
    with pytest.raises(InputError, match="one keyframe only"):
        marker_scale(m, spec, marker_views(m, 0.0, rows=[10, 10]))
    # keyframes 0.6 m from the wall and 4-7 m along it see the marker 80-85 degrees off its normal
    m.keyframes.T_wc[23:, 1, 3] = 1.4 * UNITS_PER_M
    with pytest.raises(InputError, match="grazing"):
        marker_scale(m, spec, marker_views(m, 0.0, rows=range(23, 30)))
    est = marker_scale(m, spec, marker_views(m, 0.0, rows=[*range(10, 16), *range(23, 30)]))
    assert est.detail["views"] == 6 and est.detail["views_left_out"] == 7
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=1e-6)


def test_marker_specs_parse_or_name_the_fault():
    s = parse_marker_spec("aruco:DICT_4X4_50:7=0.2")
    assert (s.dictionary, s.marker_id, s.size_m) == ("4X4_50", 7, 0.2)
    assert parse_marker_spec("aruco:apriltag_36h11:3=0.15").dictionary == "APRILTAG_36H11"
    for bad, why in [
        ("qr:4X4_50:7=0.2", "expected aruco"),
        ("aruco:5X9_50:7=0.2", "unknown ArUco dictionary"),
        ("aruco:4X4_50:70=0.2", "ids 0..49"),
        ("aruco:4X4_50:7=-0.2", "positive side length"),
        ("aruco:4X4_50:seven=0.2", "integer"),
        ("aruco:4X4_50", "expected aruco"),
    ]:
        with pytest.raises(InputError, match=why) as info:
            parse_marker_spec(bad)
        assert "--marker" in str(info.value) and "\n" not in str(info.value)


def test_detect_markers_finds_a_warped_marker_and_its_corners():
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    tag = cv2.aruco.generateImageMarker(d, 7, 120, borderBits=1)
    src = np.float32([[0, 0], [119, 0], [119, 119], [0, 119]])
    dst = np.float32([[200, 150], [330, 170], [320, 300], [190, 290]])
    H = cv2.getPerspectiveTransform(src, dst)
    img = np.full((480, 640), 255, np.uint8)
    warped = cv2.warpPerspective(tag, H, (640, 480), borderValue=255)
    img = np.minimum(img, warped)
    spec7, spec8 = parse_marker_spec("aruco:4X4_50:7=0.2"), parse_marker_spec("aruco:4X4_50:8=0.2")
    found = detect_markers([(3, img)], [spec7, spec8])
    assert found[spec8] == []
    ((row, corners),) = found[spec7]
    assert row == 3
    # the outer corners of the black square, in ArUco's order (top-left first, clockwise)
    want = cv2.perspectiveTransform(
        np.float32([[[-0.5, -0.5], [119.5, -0.5], [119.5, 119.5], [-0.5, 119.5]]]), H
    )
    assert np.abs(corners - want[0]).max() < 1.5


# ---- known lengths ------------------------------------------------------------------------------


def test_known_line_length_finds_the_scale_and_refuses_bad_input():
    m = room_map()
    est = line_length_scale(m, 1, 4.0)  # the skirting lines are 4 m long
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=1e-9)
    assert 0 < est.rel_sigma < 0.01
    with pytest.raises(InputError, match="no line 99"):
        line_length_scale(m, 99, 2.0)
    with pytest.raises(InputError, match="positive"):
        line_length_scale(m, 1, -2.0)


def test_two_points_a_known_distance_apart():
    m = room_map()
    a, b = m.points.xyz[0], m.points.xyz[1]
    metres = float(np.linalg.norm(a - b)) / UNITS_PER_M
    est = point_distance_scale(m, int(m.points.ids[0]), int(m.points.ids[1]), metres)
    assert est.scale == pytest.approx(1 / UNITS_PER_M, rel=1e-9)
    with pytest.raises(InputError, match="no point"):
        point_distance_scale(m, 0, 10**9, 1.0)
    with pytest.raises(InputError, match="two different"):
        point_distance_scale(m, 0, 0, 1.0)


# ---- choosing and applying ----------------------------------------------------------------------


def test_choose_keeps_the_better_conditioned_and_refuses_conflicts():
    a = ScaleEstimate(2.0, 0.01, "marker", "marker A")
    b = ScaleEstimate(2.02, 0.002, "camera_height", "camera height")
    assert choose([a, b]) is b
    far = ScaleEstimate(2.5, 0.01, "length", "line 3 of known length 2 m")
    with pytest.raises(InputError, match=r"conflicting scales.*% apart") as info:
        choose([a, b, far])
    assert "line 3" in str(info.value) and "camera height" in str(info.value)
    with pytest.raises(InputError, match="positive"):
        ScaleEstimate(-1.0, 0.1, "length", "bad")


def test_scale_map_multiplies_lengths_and_keeps_every_projection():
    m = room_map()
    est = ScaleEstimate(1 / UNITS_PER_M, 0.004, "camera_height", "camera height 1.6 m above the floor")
    s = scale_map(m, est)
    assert s.metadata["units"] == "m" and s.metadata["scale"]["metres_per_unit"] == est.scale
    assert np.allclose(s.points.xyz, m.points.xyz / UNITS_PER_M)
    assert np.allclose(s.lines.lengths(), [4.0, 4.0])
    assert np.allclose(s.lines.inverse_depth, m.lines.inverse_depth * UNITS_PER_M)
    uv0, _ = project_points(CAMERA.K, m.keyframes.T_wc[:, None], m.points.xyz[None, :50])
    uv1, _ = project_points(CAMERA.K, s.keyframes.T_wc[:, None], s.points.xyz[None, :50])
    assert np.allclose(uv0, uv1)
    s.validate()
    assert m.metadata["units"] == "arbitrary"  # the input is untouched
    assert units_note(s.metadata) == "m from camera height 1.6 m above the floor ±0.4%"
    assert units_note(m.metadata) == "arbitrary (monocular scale unknown)"
    again = scale_map(s, ScaleEstimate(1.01, 0.001, "length", "line 1"))
    assert again.metadata["scale"]["metres_per_original_unit"] == pytest.approx(1.01 / UNITS_PER_M)
