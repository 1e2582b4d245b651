"""Focal-length self-calibration (papl_mapper.backend.calibration) on synthetic maps with a known f."""

from __future__ import annotations

import copy
import json

import cv2
import numpy as np
import pytest

from papl_mapper import geometry as geo
from papl_mapper.backend.calibration import (
    FocalCheckConfig,
    adjust_focal,
    check_focal,
    focal_sigma_at,
    hfov_deg,
    projection_jacobians,
)
from papl_mapper.errors import GeometryError
from papl_mapper.map import Camera, Keyframes, Map, Points
from tests.conftest import make_map

F_TRUE = 450.0
MAX_REL_ERROR_NOISE0 = 0.002  # estimated f vs the truth, noise-free observations
MAX_REL_ERROR_NOISE1 = 0.02  # ... with 1 px observation noise
JACOBIAN_RTOL = 1e-5  # analytic vs central finite differences, relative to the largest entry

R_LOOK_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # camera z along world +Y


def room_map(motion: str = "turning", noise_px: float = 0.0, n_kf: int = 14, seed: int = 0) -> Map:
    """Camera walking through a 12 x 16 x 3 room seen on its walls, with true focal F_TRUE. 'turning'
    yaws +-45 deg and pitches +-8 deg along the way; 'straight' walks along +Y with no rotation."""
    rng = np.random.default_rng(seed)
    cam = Camera(640, 480, F_TRUE, F_TRUE, 319.5, 239.5)
    s = np.linspace(0.0, 1.0, n_kf)
    if motion == "turning":
        C = np.stack([2.0 * np.sin(2 * np.pi * s), -3 + 4 * s, 1.5 + 0.1 * np.sin(5 * s)], 1)
        yaw, pitch = np.radians(45) * np.sin(3 * np.pi * s), np.radians(8) * np.sin(4 * np.pi * s)
    else:
        C = np.stack([0 * s, -3 + 4 * s, 1.5 + 0 * s], 1)
        yaw, pitch = 0 * s, 0 * s
    R = (
        geo.so3_exp(np.stack([0 * s, 0 * s, yaw], 1))
        @ R_LOOK_Y
        @ geo.so3_exp(np.stack([pitch, 0 * s, 0 * s], 1))
    )
    T = np.stack([geo.make_T(Ri, c) for Ri, c in zip(R, C, strict=True)])
    n = 60
    u = rng.uniform(size=(4, n, 2))
    X = np.concatenate(
        [
            np.stack([-6 + 12 * u[0, :, 0], np.full(n, 8.0), 3 * u[0, :, 1]], 1),
            np.stack([np.full(n, -6.0), -8 + 16 * u[1, :, 0], 3 * u[1, :, 1]], 1),
            np.stack([np.full(n, 6.0), -8 + 16 * u[2, :, 0], 3 * u[2, :, 1]], 1),
            np.stack([-5 + 10 * u[3, :, 0], 2 + 5 * u[3, :, 1], 3 * rng.uniform(size=n)], 1),
        ]
    )
    uv, z = geo.project_points(cam.K, T[None], X[:, None])  # (P, N, 2)
    vis = (z > 0.3) & (uv[..., 0] > 0) & (uv[..., 0] < 639) & (uv[..., 1] > 0) & (uv[..., 1] < 479)
    keep = vis.sum(1) >= 3
    X, vis, uv = X[keep], vis[keep], uv[keep]
    pi, ki = np.nonzero(vis)
    obs = uv[pi, ki] + rng.normal(scale=noise_px, size=(len(pi), 2))
    kf = Keyframes(np.arange(n_kf), np.arange(n_kf), np.arange(n_kf) / 10.0, T)
    pts = Points(np.arange(len(X)), X, np.full((len(X), 3), 200, np.uint8), np.stack([pi, ki], 1), obs)
    return Map(cam, kf, pts)


def built_with(m: Map, f: float) -> Map:
    """The map a mapper would make with focal f: camera f, poses and points adjusted to it (f held)."""
    fit = adjust_focal(
        m.keyframes.T_wc, m.points.xyz, m.points.obs_ids[:, 0], m.points.obs_ids[:, 1], m.points.obs_uv,
        m.camera, f, FocalCheckConfig(max_iterations=60), free_f=False,
    )  # fmt: skip
    out = copy.deepcopy(m)
    out.camera = Camera(m.camera.width, m.camera.height, f, f, m.camera.cx, m.camera.cy)
    out.keyframes.T_wc = fit.T_wc
    out.points.xyz = fit.xyz
    return out


def test_projection_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    T = np.stack(
        [geo.make_T(geo.so3_exp(rng.normal(scale=0.3, size=3)), rng.normal(size=3)) for _ in range(3)]
    )
    X = rng.normal(size=(4, 3)) + np.array([0, 0, 8.0])
    obs_pt, obs_kf = np.array([0, 1, 2, 3, 1]), np.array([0, 1, 2, 1, 2])
    f = 430.0

    def proj(T, X, f):
        Tk = T[obs_kf]
        Xc = np.einsum("nji,nj->ni", Tk[:, :3, :3], X[obs_pt] - Tk[:, :3, 3])
        return f * Xc[:, :2] / Xc[:, 2:]

    J_pose, J_pt, J_f = projection_jacobians(T, X, f, obs_pt, obs_kf)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        Tp, Tm = T.copy(), T.copy()
        for sign, TT in ((1, Tp), (-1, Tm)):
            TT[:, :3, :3] = T[:, :3, :3] @ geo.so3_exp(sign * d[:3])
            TT[:, :3, 3] = T[:, :3, 3] + sign * d[3:]
        num = (proj(Tp, X, f) - proj(Tm, X, f)) / (2 * h)
        assert np.abs(num - J_pose[:, :, k]).max() <= JACOBIAN_RTOL * np.abs(J_pose).max()
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        num = (proj(T, X + d, f) - proj(T, X - d, f)) / (2 * h)
        assert np.abs(num - J_pt[:, :, k]).max() <= JACOBIAN_RTOL * np.abs(J_pt).max()
    num = (proj(T, X, f + h) - proj(T, X, f - h)) / (2 * h)
    assert np.abs(num - J_f).max() <= JACOBIAN_RTOL * np.abs(J_f).max()


@pytest.mark.parametrize("noise_px, tol", [(0.0, MAX_REL_ERROR_NOISE0), (1.0, MAX_REL_ERROR_NOISE1)])
def test_correct_focal_is_plausible(noise_px, tol):
    r = check_focal(room_map("turning", noise_px))
    assert r.observable and r.plausible and not r.warn
    assert abs(r.f_estimated / F_TRUE - 1) < tol
    assert "plausible" in r.message


@pytest.mark.parametrize("noise_px, tol", [(0.0, MAX_REL_ERROR_NOISE0), (1.0, MAX_REL_ERROR_NOISE1)])
@pytest.mark.parametrize("scale", [0.8, 1.3])
def test_wrong_focal_is_detected_and_estimated(noise_px, tol, scale):
    m = built_with(room_map("turning", noise_px), scale * F_TRUE)
    r = check_focal(m)
    assert r.f_used == pytest.approx(scale * F_TRUE)
    assert r.observable and not r.plausible and r.warn
    assert abs(r.f_estimated / F_TRUE - 1) < tol
    assert abs(r.ratio - 1 / scale) < tol * 2
    assert "--camera" in r.message and f"hfov_deg={hfov_deg(r.f_estimated, 640):.1f}" in r.message


@pytest.mark.parametrize("noise_px", [0.0, 1.0])
def test_straight_walk_is_reported_unobservable(noise_px):
    m = built_with(room_map("straight", noise_px), 1.3 * F_TRUE)
    r = check_focal(m, FocalCheckConfig(max_iterations=15))
    assert not r.observable and r.plausible and not r.warn
    assert "not observable" in r.message
    assert r.windows and all(w.rel_sigma > FocalCheckConfig().max_rel_sigma for w in r.windows)


@pytest.mark.parametrize("motion", ["straight", "turning"])
def test_screen_matches_the_adjusted_sigma_and_skips_only_flat_windows(motion):
    """The sigma of f at the map's solution (the screen) is the one the adjustment reports at the truth,
    so a straight walk is screened out without iterating and a turning one is adjusted as before."""
    m = room_map(motion, 0.0)
    obs = (m.points.obs_ids[:, 0], m.points.obs_ids[:, 1], m.points.obs_uv)
    cfg = FocalCheckConfig()
    at_truth = focal_sigma_at(m.keyframes.T_wc, m.points.xyz, *obs, m.camera, F_TRUE, cfg)
    fit = adjust_focal(m.keyframes.T_wc, m.points.xyz, *obs, m.camera, F_TRUE, cfg)
    assert at_truth == pytest.approx(fit.sigma_f, rel=1e-3)  # noise-free: level 1, same solution
    r = check_focal(m)
    screened = at_truth / F_TRUE > cfg.screen_factor * cfg.max_rel_sigma
    assert screened == (motion == "straight")
    assert all((w.iterations == 0) == screened for w in r.windows)
    unscreened = check_focal(m, FocalCheckConfig(screen_factor=np.inf))
    assert r.observable == unscreened.observable and r.plausible == unscreened.plausible
    if not screened:
        assert r.f_estimated == unscreened.f_estimated


def test_tiny_map_is_not_checked():
    m = make_map()  # 5 keyframes, every point seen twice
    r = check_focal(m)
    assert r.n_windows == 0 and not r.observable and r.plausible
    assert "not checked" in r.message
    json.dumps(r.summary(), allow_nan=False)


def test_summary_is_plain_json():
    r = check_focal(room_map("turning", 1.0))
    d = json.loads(json.dumps(r.summary(), allow_nan=False))
    assert d["f_used"] == pytest.approx(F_TRUE) and d["windows"][0]["n_keyframes"] >= 5


def test_distorted_observations_are_undistorted():
    m = room_map("turning", 0.0)
    dist = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])
    m.camera = Camera(640, 480, F_TRUE, F_TRUE, 319.5, 239.5, dist)

    # distort the ideal pixels: normalised -> distorted normalised -> pixels
    xn = (m.points.obs_uv - [319.5, 239.5]) / F_TRUE
    pts3 = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    uv_d, _ = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), m.camera.K, dist)
    m.points.obs_uv = uv_d.reshape(-1, 2)
    r = check_focal(m)
    assert r.plausible and abs(r.f_estimated / F_TRUE - 1) < MAX_REL_ERROR_NOISE1


def test_bad_camera_raises():
    m = room_map("turning", 0.0)
    m.camera = Camera(640, 480, float("nan"), F_TRUE, 319.5, 239.5)
    with pytest.raises(GeometryError, match="focal"):
        check_focal(m)


def test_one_broken_window_does_not_move_the_estimate():
    """A window stuck at the wrong f (a broken stretch of the map) is outvoted by the median."""
    from papl_mapper.backend.calibration import WindowFit, _combine

    def win(f: float) -> WindowFit:
        return WindowFit(0, 20, 300, 3000, 30.0, f, 0.005, 10, 0.5)

    f, rel = _combine([win(456.0), win(458.0), win(366.0), win(457.5), win(455.0)])
    assert f == pytest.approx(456.0)
    assert rel < 0.03
