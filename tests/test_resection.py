"""Pose from known structure where points are few: rotation from directions, centre from points and lines
given it (geometry/resection.py), the pose's uncertainty (pose_refine.pose_std) and the tracking
fallback that chains them (tracking.pose_from_lines)."""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.lines import plucker_from_endpoints
from papl_mapper.geometry.resection import centre_equations, centre_from_rotation, rotation_from_directions
from papl_mapper.geometry.se3 import invert, make_T, rotation_angle_deg, so3_exp, so3_log
from papl_mapper.mapping.pose_refine import PoseRefineConfig, point_residuals, pose_std, refine_pose
from papl_mapper.mapping.tracking import PnPConfig, pose_from_lines

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
AXES_W = np.eye(3)  # world +Z up, X and Y horizontal

MAX_ROT_NOISELESS_DEG = 1e-6
MAX_CENTRE_NOISELESS = 1e-6
MAX_ROT_NOISY_DEG = 0.3
MAX_CENTRE_NOISY = 0.03


def _pose() -> np.ndarray:
    """T_cw of a camera at (0.3, -0.2, 1.5) looking along world +Y, slightly yawed and pitched."""
    R_wc0 = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    return invert(make_T(so3_exp(np.array([0.05, 0.02, 0.1])) @ R_wc0, np.array([0.3, -0.2, 1.5])))


def _centre(T_cw: np.ndarray) -> np.ndarray:
    return invert(T_cw)[:3, 3]


def _points(T_cw: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n world points 3-8 in front of the camera and their pixels."""
    depth = rng.uniform(3.0, 8.0, n)
    X_c = np.column_stack([rng.uniform(-0.4, 0.4, (n, 2)) * depth[:, None], depth])
    X_w = (X_c - T_cw[:3, 3]) @ T_cw[:3, :3]
    return X_w, point_residuals(T_cw, X_w, np.zeros((n, 2)), K)


def _lines(T_cw: np.ndarray, axes: list[int], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """World lines along the given axes 3-8 in front of the camera (Pluecker (M, 6)) and their observed
    segments (M, 4) px, whose endpoints slide along the image line (only the distance to it counts)."""
    n = len(axes)
    mid_c = np.column_stack([rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(3.0, 8.0, n)])
    mid_w = (mid_c - T_cw[:3, 3]) @ T_cw[:3, :3]
    d = AXES_W[axes]
    ends_w = np.stack([mid_w - 0.5 * d, mid_w + 0.5 * d], 1)
    e_c = ends_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    seg = (e_c @ K.T)[..., :2] / (e_c @ K.T)[..., 2:3]
    s = rng.uniform(-0.2, 0.2, (n, 2, 1))
    seg = seg + s * (seg[:, 1:2] - seg[:, 0:1])
    return plucker_from_endpoints(ends_w[:, 0], ends_w[:, 1]), seg.reshape(-1, 4)


def test_rotation_from_two_directions_is_exact_and_sign_free() -> None:
    T = _pose()
    R_true = T[:3, :3]
    guess = so3_exp(np.array([0.03, -0.04, 0.05])) @ R_true
    d_c = AXES_W[:2] @ R_true.T * np.array([[-1.0], [1.0]])  # a vanishing direction has no sign
    R = rotation_from_directions(guess, AXES_W[:2], d_c)
    assert rotation_angle_deg(R, R_true) < MAX_ROT_NOISELESS_DEG


def test_rotation_from_one_direction_aligns_it_and_keeps_the_rest_of_the_guess() -> None:
    R_true = _pose()[:3, :3]
    # the guess is off about the vertical (not fixed by it) and about a horizontal axis (fixed by it)
    about_vertical = R_true @ so3_exp(0.04 * AXES_W[2]) @ R_true.T
    guess = so3_exp(np.array([0.03, 0.0, 0.0])) @ about_vertical @ R_true
    R = rotation_from_directions(guess, AXES_W[2:], -(AXES_W[2] @ R_true.T)[None])
    np.testing.assert_allclose(np.abs(AXES_W[2] @ R.T @ (AXES_W[2] @ R_true.T)), 1.0, atol=1e-12)
    # what is left is the turn about the vertical, from the guess
    left = so3_log(R.T @ R_true)
    np.testing.assert_allclose(np.abs(left @ AXES_W[2]), np.linalg.norm(left), rtol=1e-6)
    assert rotation_angle_deg(rotation_from_directions(guess, np.zeros((0, 3)), np.zeros((0, 3))), guess) == 0


def test_centre_from_points_and_lines_is_exact_without_noise() -> None:
    rng = np.random.default_rng(0)
    T = _pose()
    X, uv = _points(T, 2, rng)
    L, seg = _lines(T, [0, 1, 2], rng)
    for kw in (
        {"points_w": X, "uv": uv},  # two points: four equations
        {"lines_w": L, "line_xy": seg},  # three lines in three directions: three equations
        {"points_w": X[:1], "uv": uv[:1], "lines_w": L[:1], "line_xy": seg[:1]},
    ):
        C, sv = centre_from_rotation(T[:3, :3], K, **kw)
        assert np.linalg.norm(C - _centre(T)) < MAX_CENTRE_NOISELESS
        assert sv[2] > 1e-3 * sv[0]


def test_a_line_gives_one_equation_and_vertical_lines_leave_the_height_free() -> None:
    rng = np.random.default_rng(1)
    T = _pose()
    L, seg = _lines(T, [2, 2, 2, 2], rng)  # vertical lines only
    A, y, feature = centre_equations(T[:3, :3], K, lines_w=L, line_xy=seg)
    assert A.shape == (4, 3) and feature.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(A @ _centre(T), y, atol=1e-9)  # the true centre satisfies every equation
    _, sv = centre_from_rotation(T[:3, :3], K, lines_w=L, line_xy=seg)
    assert sv[2] < 1e-9 * sv[0]  # every plane contains the vertical: the height is not observed


def test_centre_close_under_noise() -> None:
    rng = np.random.default_rng(2)
    T = _pose()
    X, uv = _points(T, 10, rng)
    L, seg = _lines(T, [0, 1, 2] * 4, rng)
    C, _ = centre_from_rotation(
        T[:3, :3], K, X, uv + rng.normal(0, 0.5, uv.shape), L, seg + rng.normal(0, 0.5, seg.shape)
    )
    assert np.linalg.norm(C - _centre(T)) < MAX_CENTRE_NOISY


def test_pose_std_matches_monte_carlo_and_is_infinite_when_the_pose_is_free() -> None:
    rng = np.random.default_rng(3)
    T_true = _pose()
    X, uv = _points(T_true, 3, rng)
    L, seg = _lines(T_true, [0, 1, 2, 0, 1, 2], rng)
    cfg = PoseRefineConfig(lines=True, huber=1e9)
    rot_std, centre_std = pose_std(T_true, X, uv, K, lines_w=L, line_xy=seg, config=cfg)
    rot_err, centre_err = [], []
    for _ in range(60):
        T, _ = refine_pose(
            T_true,
            X,
            uv + rng.normal(0, 1.0, uv.shape),
            K,
            lines_w=L,
            line_xy=seg + rng.normal(0, 1.0, seg.shape),
            config=cfg,
        )
        rot_err.append(so3_log(T[:3, :3] @ T_true[:3, :3].T))
        centre_err.append(_centre(T) - _centre(T_true))
    mc_rot = np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(np.array(rot_err).T)).max()))
    mc_centre = np.sqrt(np.linalg.eigvalsh(np.cov(np.array(centre_err).T)).max())
    assert 0.7 * rot_std < mc_rot < 1.3 * rot_std
    assert 0.7 * centre_std < mc_centre < 1.3 * centre_std
    L2, seg2 = _lines(T_true, [2, 2], rng)  # two vertical lines alone fix no pose
    assert pose_std(T_true, np.zeros((0, 3)), np.zeros((0, 2)), K, lines_w=L2, line_xy=seg2, config=cfg)[
        0
    ] == float("inf")


def _fallback_scene(seed: int, n_pts: int = 3, axes: tuple[int, ...] = (0, 1, 2, 0, 2, 1)):
    rng = np.random.default_rng(seed)
    T = _pose()
    X, uv = _points(T, n_pts, rng)
    L, seg = _lines(T, list(axes), rng)
    guess = make_T(so3_exp(np.array([0.0, 0.03, 0.02])) @ T[:3, :3], T[:3, 3] + np.array([0.05, -0.03, 0.04]))
    return T, X, uv, L, seg, guess


def test_pose_from_lines_without_noise() -> None:
    T, X, uv, L, seg, guess = _fallback_scene(4)
    d_c = AXES_W @ T[:3, :3].T
    res = pose_from_lines(X, uv, K, guess, L, seg, dirs_w=AXES_W, dirs_c=d_c)
    assert res.ok, res.reason
    assert rotation_angle_deg(res.T_cw[:3, :3], T[:3, :3]) < MAX_ROT_NOISELESS_DEG
    assert np.linalg.norm(_centre(res.T_cw) - _centre(T)) < MAX_CENTRE_NOISELESS
    # the vertical direction alone: the lines and points fix the turn about it
    res = pose_from_lines(X, uv, K, guess, L, seg, dirs_w=AXES_W[2:], dirs_c=d_c[2:])
    assert res.ok, res.reason
    assert rotation_angle_deg(res.T_cw[:3, :3], T[:3, :3]) < MAX_ROT_NOISELESS_DEG


def test_pose_from_lines_under_noise_and_a_wrong_line() -> None:
    T, X, uv, L, seg, guess = _fallback_scene(5)
    rng = np.random.default_rng(6)
    seg = seg + rng.normal(0, 0.5, seg.shape)
    seg[0] += np.array([0.0, 40.0, 0.0, 40.0])  # a wrong track: 40 px off its line
    d_c = AXES_W @ T[:3, :3].T + rng.normal(0, 0.005, (3, 3))
    res = pose_from_lines(X, uv + rng.normal(0, 0.5, uv.shape), K, guess, L, seg, dirs_w=AXES_W, dirs_c=d_c)
    assert res.ok, res.reason
    assert rotation_angle_deg(res.T_cw[:3, :3], T[:3, :3]) < MAX_ROT_NOISY_DEG
    assert np.linalg.norm(_centre(res.T_cw) - _centre(T)) < MAX_CENTRE_NOISY


def test_pose_from_lines_refuses_what_does_not_fix_the_pose() -> None:
    T, X, uv, L, seg, guess = _fallback_scene(7, n_pts=0, axes=(2, 2, 2))
    d_c = AXES_W @ T[:3, :3].T
    res = pose_from_lines(X, uv, K, guess, L, seg, dirs_w=AXES_W[2:], dirs_c=d_c[2:])
    assert not res.ok  # vertical lines and the vertical direction: height and heading are free
    res = pose_from_lines(X, uv, K, guess, L[:1], seg[:1], PnPConfig(), dirs_w=AXES_W, dirs_c=d_c)
    assert not res.ok and "need 2 lines" in res.reason
