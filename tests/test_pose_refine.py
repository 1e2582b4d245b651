"""Pose refinement with points, line segments and vanishing directions (mapping/pose_refine.py)."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.geometry.lines import plucker_from_endpoints
from papl_mapper.geometry.se3 import make_T, retract, rotation_angle_deg, so3_exp, so3_log
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map
from papl_mapper.mapping.pose_refine import (
    FrameRefiner,
    PoseRefineConfig,
    RegistrationDirections,
    direction_residuals,
    direction_spread_deg,
    directions_from_poses,
    frame_directions,
    line_residuals,
    match_directions,
    point_residuals,
    points_rotation_std_deg,
    refine_pose,
    world_directions,
)
from papl_mapper.mapping.tracking import PnPConfig, track_pnp
from papl_mapper.tracks import Tracks

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
AXES_W = np.eye(3)  # world +Z up, X and Y horizontal

MAX_ROT_NOISELESS_DEG = 1e-6
MAX_TRANS_NOISELESS = 1e-6
MAX_ROT_NOISY_DEG = 0.1
MAX_TRANS_NOISY = 0.01
FD_RTOL = 1e-5


def _camera_pose(seed: int = 0) -> np.ndarray:
    """T_cw of a camera at about (0.3, -0.2, 1.5) looking along world +Y, slightly yawed and pitched."""
    R_wc0 = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # camera z = world +Y, camera y = world -Z
    R_wc = so3_exp(np.array([0.05, 0.02, 0.1])) @ R_wc0
    T_wc = make_T(R_wc, np.array([0.3, -0.2, 1.5]))
    return np.linalg.inv(T_wc)


def _scene(n_pts: int = 60, n_lines: int = 20, seed: int = 0, spread: float = 3.0):
    """Points and axis-aligned lines in front of the camera; their pixels and segment endpoints."""
    rng = np.random.default_rng(seed)
    T_cw = _camera_pose()
    T_wc = np.linalg.inv(T_cw)
    depth = rng.uniform(3.0, 8.0, n_pts)
    xy = rng.uniform(-spread / 2, spread / 2, (n_pts, 2))
    X_c = np.column_stack([xy * depth[:, None] / 4.0, depth])
    X_w = X_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    uv = point_residuals(T_cw, X_w, np.zeros((n_pts, 2)), K)
    mid_c = np.column_stack([rng.uniform(-1.5, 1.5, (n_lines, 2)), rng.uniform(3.0, 8.0, n_lines)])
    mid_w = mid_c @ T_wc[:3, :3].T + T_wc[:3, 3]
    d = AXES_W[rng.integers(0, 3, n_lines)]
    ends_w = np.stack([mid_w - 0.5 * d, mid_w + 0.5 * d], 1)
    e_c = ends_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    seg = (e_c @ K.T)[..., :2] / (e_c @ K.T)[..., 2:3]
    # observed endpoints slide along the line: the error is the distance to the line only
    t = rng.uniform(-0.2, 0.2, (n_lines, 2, 1))
    seg = seg + t * (seg[:, 1:2] - seg[:, 0:1])
    return T_cw, X_w, uv, ends_w, seg.reshape(-1, 4)


def _dirs_c(T_cw: np.ndarray, flip: bool = True) -> np.ndarray:
    d = AXES_W @ T_cw[:3, :3].T
    return d * np.array([[-1.0], [1.0], [-1.0]]) if flip else d


def _fd_check(fun, T_cw: np.ndarray) -> None:
    r0, J = fun(T_cw)
    h = 1e-6
    J_fd = np.zeros_like(J)
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        rp, _ = fun(retract(np.eye(4), xi) @ T_cw)
        xi[k] = -h
        rm, _ = fun(retract(np.eye(4), xi) @ T_cw)
        J_fd[..., k] = (rp - rm) / (2 * h)
    np.testing.assert_allclose(J, J_fd, rtol=FD_RTOL, atol=FD_RTOL * np.abs(J_fd).max())


def test_point_jacobian_matches_finite_differences() -> None:
    T_cw, X_w, uv, _, _ = _scene(10, 0)
    _fd_check(lambda T: point_residuals(T, X_w, uv + 3.0, K, jacobian=True)[:2], T_cw)


def test_line_jacobian_matches_finite_differences() -> None:
    T_cw, _, _, ends_w, seg = _scene(0, 10)
    L_w = plucker_from_endpoints(ends_w[:, 0], ends_w[:, 1])
    _fd_check(lambda T: line_residuals(T, L_w, seg + 2.0, K, jacobian=True), T_cw)


def test_direction_jacobian_matches_finite_differences() -> None:
    T_cw = _camera_pose()
    d_c = _dirs_c(retract(np.eye(4), np.array([0.02, -0.01, 0.03, 0, 0, 0])) @ T_cw)
    _fd_check(lambda T: direction_residuals(T, AXES_W, d_c, jacobian=True), T_cw)


def test_direction_residual_is_sign_free_and_small_angle() -> None:
    T_cw = _camera_pose()
    d_c = _dirs_c(T_cw)
    np.testing.assert_allclose(direction_residuals(T_cw, AXES_W, d_c), 0.0, atol=1e-12)
    T_off = retract(np.eye(4), np.array([0.0, 0.0, np.radians(1.0), 0, 0, 0])) @ T_cw
    ang = np.degrees(np.linalg.norm(direction_residuals(T_off, AXES_W, d_c), axis=-1))
    assert np.all(ang <= 1.0 + 1e-6)  # rotation by 1 deg about camera z moves each direction <= 1 deg


@pytest.mark.parametrize("terms", ["points", "lines", "all"])
def test_perturbed_pose_recovered_without_noise(terms: str) -> None:
    T_true, X_w, uv, ends_w, seg = _scene()
    T0 = retract(np.eye(4), np.array([0.02, -0.03, 0.015, 0.05, -0.04, 0.03])) @ T_true
    kw = {}
    if terms in ("lines", "all"):
        kw.update(lines_w=ends_w, line_xy=seg)
    if terms == "all":
        kw.update(dirs_w=AXES_W, dirs_c=_dirs_c(T_true))
    pts = (X_w, uv) if terms != "lines" else (np.zeros((0, 3)), np.zeros((0, 2)))
    T, st = refine_pose(T0, *pts, K, config=PoseRefineConfig(iterations=30, lines=True), **kw)
    assert rotation_angle_deg(T[:3, :3], T_true[:3, :3]) < MAX_ROT_NOISELESS_DEG
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < MAX_TRANS_NOISELESS
    assert st.cost_final < st.cost_initial


def test_perturbed_pose_recovered_with_noise() -> None:
    T_true, X_w, uv, ends_w, seg = _scene(seed=1)
    rng = np.random.default_rng(5)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    seg = seg + rng.normal(0, 0.5, seg.shape)
    d_c = _dirs_c(T_true) @ so3_exp(rng.normal(0, np.radians(0.1), 3)).T
    T0 = retract(np.eye(4), np.array([0.02, -0.03, 0.015, 0.05, -0.04, 0.03])) @ T_true
    cfg = PoseRefineConfig(lines=True)
    T, st = refine_pose(T0, X_w, uv, K, lines_w=ends_w, line_xy=seg, dirs_w=AXES_W, dirs_c=d_c, config=cfg)
    assert rotation_angle_deg(T[:3, :3], T_true[:3, :3]) < MAX_ROT_NOISY_DEG
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < MAX_TRANS_NOISY
    assert (st.n_points, st.n_lines, st.n_directions) == (60, 20, 3)
    assert st.point_rms_px < 1.0 and st.line_rms_px < 1.0


def test_outlier_points_do_not_pull_the_pose() -> None:
    T_true, X_w, uv, ends_w, seg = _scene(seed=2)
    uv = uv.copy()
    uv[:6] += 25.0  # 10% gross outliers that the Huber loss must tame
    T0 = retract(np.eye(4), np.array([0.01, 0.01, -0.01, 0.02, 0.0, 0.0])) @ T_true
    T, _ = refine_pose(T0, X_w, uv, K, config=PoseRefineConfig(huber=1.0, iterations=30))
    T_ls, _ = refine_pose(T0, X_w, uv, K, config=PoseRefineConfig(huber=1e9, iterations=30))
    err = rotation_angle_deg(T[:3, :3], T_true[:3, :3])
    assert err < rotation_angle_deg(T_ls[:3, :3], T_true[:3, :3])


def test_directions_correct_rotation_when_points_are_few_and_bunched() -> None:
    """Eight points in a small patch: the points-only pose trades rotation for translation; the
    vanishing directions pin the rotation (incl. the yaw about the vertical)."""
    errs_points, errs_dirs = [], []
    for seed in range(10):
        T_true, X_w, uv, _, _ = _scene(n_pts=8, n_lines=0, seed=seed, spread=0.4)
        rng = np.random.default_rng(100 + seed)
        uv = uv + rng.normal(0, 1.0, uv.shape)
        d_c = _dirs_c(T_true) @ so3_exp(rng.normal(0, np.radians(0.05), 3)).T
        T0 = T_true.copy()  # the noise alone moves the pose
        cfg = PoseRefineConfig(iterations=30, direction_sigma_deg=0.1)
        T_p, _ = refine_pose(T0, X_w, uv, K, config=cfg)
        T_d, st = refine_pose(T0, X_w, uv, K, dirs_w=AXES_W, dirs_c=d_c, config=cfg)
        errs_points.append(rotation_angle_deg(T_p[:3, :3], T_true[:3, :3]))
        errs_dirs.append(rotation_angle_deg(T_d[:3, :3], T_true[:3, :3]))
    assert np.mean(errs_dirs) < 0.15
    assert np.mean(errs_dirs) < 0.25 * np.mean(errs_points)


def test_match_directions_is_sign_free_and_skips_nan() -> None:
    T_cw = _camera_pose()
    d_c = np.vstack([_dirs_c(T_cw)[[2, 0]], np.full((1, 3), np.nan)])
    R_guess = so3_exp(np.radians([1.0, 0.5, 0.0])) @ T_cw[:3, :3]
    w, c, idx = match_directions(R_guess, AXES_W, d_c, max_angle_deg=3.0)
    np.testing.assert_allclose(w, AXES_W[[2, 0]])
    np.testing.assert_allclose(c, d_c[:2])
    np.testing.assert_array_equal(idx, [2, 0])
    w, _, _ = match_directions(R_guess, AXES_W, d_c, max_angle_deg=0.2)
    assert len(w) == 0


def test_world_directions_from_drifting_keyframes() -> None:
    rng = np.random.default_rng(3)
    n = 40
    R_wc = so3_exp(np.column_stack([np.zeros(n), np.zeros(n), rng.uniform(-np.pi, np.pi, n)]))
    R_wc = R_wc @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    axes_w = np.array([[0, 0, 1.0], [1.0, 0, 0], [np.cos(0.5), np.sin(0.5), 0]])  # vertical + Atlanta pair
    noise = so3_exp(rng.normal(0, np.radians(0.3), (n, 3)))
    d_c = np.einsum("nji,vj->nvi", R_wc @ noise, axes_w) * rng.choice([-1.0, 1.0], (n, 3, 1))
    d_c[::4, 2] = np.nan  # the third direction is missing in some frames
    est, spread = world_directions(R_wc, d_c, max_angle_deg=2.0)
    assert len(est) == 3
    ang = np.degrees(np.arccos(np.clip(np.abs(est @ axes_w.T), 0, 1))).min(0)
    assert np.all(ang < 0.3)
    # each direction moves by a 2D Gaussian of 0.3 deg per tangent axis: the spread estimates that sigma
    np.testing.assert_allclose(spread, 0.3, atol=0.1)
    np.testing.assert_allclose(direction_spread_deg(est, R_wc, d_c, 2.0), spread, atol=1e-9)


def _tracks_one_frame(T_cw: np.ndarray, uv: np.ndarray, seg: np.ndarray) -> Tracks:
    n, m = len(uv), len(seg)
    vp = _dirs_c(T_cw)[None]
    return Tracks(
        camera=Camera(640, 480, 500.0, 500.0, 319.5, 239.5),
        frame_index=np.array([0]),
        timestamp=np.array([0.0]),
        is_keyframe=np.array([False]),
        point_frame=np.zeros(n, np.int64),
        point_track=np.arange(n),
        point_uv=uv,
        line_frame=np.zeros(m, np.int64),
        line_track=np.arange(m) + 100,
        line_xy=seg,
        line_vp=np.zeros(m, np.int64),
        vp_dirs_c=vp,
        vertical_vp=np.array([0]),
    )


def test_frame_refiner_uses_map_lines_and_axes() -> None:
    T_true, X_w, uv, ends_w, seg = _scene(seed=4)
    tracks = _tracks_one_frame(T_true, uv, seg)
    m = Map(tracks.camera)
    keep = np.arange(len(seg)) % 4 != 3  # a quarter of the segments have no map line
    n = int(keep.sum())
    m.lines = Lines(
        np.arange(len(seg))[keep] + 100,
        ends_w[keep],
        np.zeros((n, 3)),
        np.full(n, LineState.ORTHONORMAL, np.int8),
        np.full(n, -1),
        np.full(n, np.nan),
        np.zeros((0, 2), np.int64),
        np.zeros((0, 4)),
    )
    m.axes = Axes(AXES_W.copy(), 2)
    ref = FrameRefiner.from_map(tracks, m, PoseRefineConfig(lines=True))
    T0 = retract(np.eye(4), np.array([0.01, -0.01, 0.01, 0.02, 0.01, -0.02])) @ T_true
    T, st = ref.refine(0, T0, X_w, uv)
    assert (st.n_lines, st.n_directions) == (n, 3)
    assert rotation_angle_deg(T[:3, :3], T_true[:3, :3]) < MAX_ROT_NOISELESS_DEG
    off = FrameRefiner.from_map(tracks, m, PoseRefineConfig(enabled=False))
    assert off.refine(0, T0, X_w, uv)[0] is T0


def test_track_pnp_with_refinement_terms() -> None:
    T_true, X_w, uv, ends_w, seg = _scene(seed=6)
    rng = np.random.default_rng(7)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    res = track_pnp(
        X_w, uv, K, None, PnPConfig(), lines_w=ends_w, line_xy=seg, dirs_w=AXES_W, dirs_c=_dirs_c(T_true)
    )
    assert res.ok
    assert res.refine is not None and res.refine.n_directions == 3
    assert rotation_angle_deg(res.T_cw[:3, :3], T_true[:3, :3]) < MAX_ROT_NOISY_DEG


def test_registration_directions_follow_keyframes() -> None:
    T_true, _, uv, _, seg = _scene(seed=8)
    tracks = _tracks_one_frame(T_true, uv, seg)
    dirs = RegistrationDirections(tracks, min_support=1)
    assert len(dirs({})[0]) == 0
    poses = {0: T_true}
    est = dirs(poses)
    np.testing.assert_allclose(np.abs(est[0] @ AXES_W.T).max(1), 1.0, atol=1e-9)
    np.testing.assert_allclose(est[1], 0.0, atol=1e-5)
    assert dirs(poses) is est  # cached while no keyframe is added
    assert len(directions_from_poses(tracks, poses, min_support=2)[0]) == 0  # one frame: too little support


def test_vertical_only_uses_the_vertical_direction() -> None:
    T_true, X_w, uv, _, seg = _scene(seed=9)
    tracks = _tracks_one_frame(T_true, uv, seg)  # vp 0 is world X; make it the vertical one for the test
    np.testing.assert_allclose(frame_directions(tracks, 0, vertical_only=True), tracks.vp_dirs_c[0, [0]])
    m = Map(tracks.camera)
    m.axes = Axes(AXES_W.copy(), 0)
    ref = FrameRefiner.from_map(tracks, m, PoseRefineConfig(vertical_only=True, lines=False))
    _, st = ref.refine(0, T_true, X_w, uv)
    assert st.n_directions == 1
    est, _ = directions_from_poses(tracks, {0: T_true}, min_support=1, vertical_only=True)
    np.testing.assert_allclose(np.abs(est), AXES_W[[0]], atol=1e-9)


def test_scattered_direction_gets_its_own_sigma() -> None:
    """A direction whose vanishing points scatter (sigma 3 deg) must not pull the pose as hard as one
    known to 0.5 deg: with the per-direction sigma the biased direction moves the rotation less."""
    T_true, X_w, uv, _, _ = _scene(n_pts=30, n_lines=0, seed=10)
    d_c = _dirs_c(T_true)
    d_c[0] = so3_exp(np.radians([0.0, 2.0, 0.0])) @ d_c[0]  # one direction 2 deg off
    cfg = PoseRefineConfig(iterations=30, max_direction_spread_deg=5.0)
    T_fixed, _ = refine_pose(T_true, X_w, uv, K, dirs_w=AXES_W, dirs_c=d_c, config=cfg)
    T_own, _ = refine_pose(
        T_true, X_w, uv, K, dirs_w=AXES_W, dirs_c=d_c, dirs_sigma_deg=np.array([3.0, np.nan, 0.1]), config=cfg
    )
    err_fixed = rotation_angle_deg(T_fixed[:3, :3], T_true[:3, :3])
    err_own = rotation_angle_deg(T_own[:3, :3], T_true[:3, :3])
    assert err_own < 0.5 * err_fixed
    cfg.max_direction_spread_deg = 2.0  # the 3 deg direction is left out altogether
    sig = np.array([3.0, 0.2, 0.1])
    _, st = refine_pose(T_true, X_w, uv, K, dirs_w=AXES_W, dirs_c=d_c, dirs_sigma_deg=sig, config=cfg)
    assert st.n_directions == 2


def test_frame_refiner_takes_axis_spread_from_keyframes() -> None:
    T_true, X_w, uv, _, seg = _scene(seed=11)
    tracks = _tracks_one_frame(T_true, uv, seg)
    tracks.vp_dirs_c[0, 1] = so3_exp(np.radians([1.5, 0.0, 0.0])) @ tracks.vp_dirs_c[0, 1]  # 1.5 deg off
    m = Map(tracks.camera)
    m.keyframes = Keyframes(np.array([0]), np.array([0]), np.array([0.0]), np.linalg.inv(T_true)[None])
    m.axes = Axes(AXES_W.copy(), 2)
    ref = FrameRefiner.from_map(tracks, m)
    assert ref.dirs_sigma_deg[0] < 1e-5 and ref.dirs_sigma_deg[2] < 1e-5
    assert ref.dirs_sigma_deg[1] > 1.0  # one observation 1.5 deg off: sigma 1.5 / 1.18
    _, st = ref.refine(0, T_true, X_w, uv)
    assert st.n_directions == 2  # the scattered one exceeds max_direction_spread_deg


def test_track_pnp_uses_directions_only_below_the_inlier_count() -> None:
    T_true, X_w, uv, _, _ = _scene(seed=12)
    cfg = PnPConfig(refine=PoseRefineConfig(directions_below_inliers=30))
    res = track_pnp(X_w, uv, K, None, cfg, dirs_w=AXES_W, dirs_c=_dirs_c(T_true))
    assert res.ok and res.refine is None  # 60 inliers: points are strong enough
    res = track_pnp(X_w[:20], uv[:20], K, None, cfg, dirs_w=AXES_W, dirs_c=_dirs_c(T_true))
    assert res.ok and res.refine is not None and res.refine.n_directions == 3


def test_points_rotation_std_matches_monte_carlo_and_gates_directions() -> None:
    T_true, X_w, uv, _, _ = _scene(n_pts=12, n_lines=0, seed=13, spread=0.6)
    std = points_rotation_std_deg(T_true, X_w, uv, K, 1.0)
    rng = np.random.default_rng(14)
    errs = []
    for _ in range(60):
        T, _ = refine_pose(
            T_true, X_w, uv + rng.normal(0, 1.0, uv.shape), K, config=PoseRefineConfig(huber=1e9)
        )
        errs.append(so3_log(T[:3, :3] @ T_true[:3, :3].T))
    # the largest per-axis spread of the estimates is the covariance's largest eigenvalue (to sampling error)
    mc = np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(np.array(errs).T)).max()))
    assert 0.7 * std < mc < 1.3 * std
    T_wide, X_wide, uv_wide, _, _ = _scene(n_pts=60, n_lines=0, seed=13)
    assert points_rotation_std_deg(T_wide, X_wide, uv_wide, K, 1.0) < 0.5 * std
    cfg = PnPConfig(
        min_inliers=8, refine=PoseRefineConfig(directions_above_rotation_std_deg=0.5 * (std + 1e-9))
    )
    res = track_pnp(X_w, uv, K, None, cfg, dirs_w=AXES_W, dirs_c=_dirs_c(T_true))
    assert res.refine is not None  # bunched points: uncertain rotation, directions used
    res = track_pnp(X_wide, uv_wide, K, None, cfg, dirs_w=AXES_W, dirs_c=_dirs_c(T_wide))
    assert res.refine is None  # well spread points: rotation certain enough
