"""KLT motion prediction: `predict_flow` fits the image motion, `track_klt(motion=)` starts LK from it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.klt import FlowConfig, predict_flow, track_klt

W, H = 480, 360
SUBPIXEL_TOL_PX = 0.3  # tracking error with the predicted motion on a smooth texture
MIN_KEPT_PREDICTED = 0.8  # fraction of tracks kept within tolerance with prediction
MAX_KEPT_UNPREDICTED = 0.3  # ... and at most this fraction without it
H_TOL = 0.5  # pixels: largest transfer error of the fitted homography over the image


def _texture(seed: int = 0, w: int = 1000, h: int = 800) -> np.ndarray:
    """A smooth random texture larger than the views (so moved views stay filled)."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (h // 6, w // 6)).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (0, 0), 1.5)


def _window(tex: np.ndarray, x0: float, y0: float) -> np.ndarray:
    """Homography mapping texture pixels to the pixels of the W x H view whose top-left is (x0, y0)."""
    return np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]])


def _render(tex: np.ndarray, H_view_tex: np.ndarray) -> np.ndarray:
    img = cv2.warpPerspective(tex, H_view_tex, (W, H), flags=cv2.INTER_CUBIC)
    return np.clip(img, 0, 255).astype(np.uint8)


def _motion(dx: float, dy: float, angle_deg: float) -> np.ndarray:
    """Image motion (3, 3): rotation by angle_deg about the image centre, then a shift (dx, dy)."""
    c = np.array([W / 2, H / 2])
    R = cv2.getRotationMatrix2D(tuple(c), angle_deg, 1.0)
    M = np.vstack([R, [0, 0, 1]])
    M[:2, 2] += [dx, dy]
    return M


def _transfer(Hm: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(np.asarray(uv, np.float64).reshape(-1, 1, 2), Hm).reshape(-1, 2)


def _pair(dx: float, dy: float, angle_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two views related by a known image motion; corners of the first whose image stays inside."""
    tex = _texture()
    A = _window(tex, 260, 220)
    motion = _motion(dx, dy, angle_deg)
    a, b = _render(tex, A), _render(tex, motion @ A)
    pts = cv2.goodFeaturesToTrack(a, 300, 0.01, 10).reshape(-1, 2)
    moved = _transfer(motion, pts)
    inside = np.all((moved > 15) & (moved < [W - 15, H - 15]), axis=1)
    inside &= np.all((pts > 15) & (pts < [W - 15, H - 15]), axis=1)
    return a, b, pts[inside].astype(np.float32), motion


@pytest.mark.parametrize("dx, dy, angle_deg", [(60.0, 0.0, 0.0), (-55.0, 25.0, 3.0)])
def test_prediction_keeps_tracks_under_large_motion(dx, dy, angle_deg):
    a, b, pts, motion = _pair(dx, dy, angle_deg)
    assert len(pts) > 50
    truth = _transfer(motion, pts)
    cfg = FlowConfig()

    def kept_accurate(guess: np.ndarray | None) -> float:
        new, ok, _ = track_klt(a, b, pts, cfg, W, H, motion=guess)
        err = np.linalg.norm(new - truth, axis=1)
        return float(np.mean(ok & (err < SUBPIXEL_TOL_PX)))

    # the prediction is the motion fitted to the flow of a previous frame pair: off by a little
    predicted = _motion(dx + 1.5, dy - 1.0, angle_deg + 0.3)
    assert kept_accurate(predicted) >= MIN_KEPT_PREDICTED
    assert kept_accurate(None) <= MAX_KEPT_UNPREDICTED
    # predict=False in the config ignores a given motion
    new, ok, _ = track_klt(a, b, pts, FlowConfig(predict=False), W, H, motion=predicted)
    assert np.mean(ok & (np.linalg.norm(new - truth, axis=1) < SUBPIXEL_TOL_PX)) <= MAX_KEPT_UNPREDICTED


def test_prediction_keeps_small_motion_accurate():
    """A prediction of zero motion (identity) must not hurt tracking a small shift."""
    a, b, pts, motion = _pair(2.3, -1.7, 0.0)
    new, ok, _ = track_klt(a, b, pts, FlowConfig(), W, H, motion=np.eye(3))
    err = np.linalg.norm(new - _transfer(motion, pts), axis=1)
    assert ok.mean() > 0.95
    assert np.median(err[ok]) < SUBPIXEL_TOL_PX


@pytest.mark.parametrize("noise_px, outlier_fraction", [(0.0, 0.0), (0.5, 0.0), (0.5, 0.3)])
def test_predict_flow_recovers_known_homography(noise_px, outlier_fraction):
    rng = np.random.default_rng(3)
    truth = _motion(40.0, -12.0, 4.0)
    truth[2, :2] = [2e-5, -1e-5]  # a little perspective
    n = 200
    src = rng.uniform([0, 0], [W, H], (n, 2))
    dst = _transfer(truth, src) + rng.normal(0, noise_px, (n, 2))
    bad = rng.random(n) < outlier_fraction
    dst[bad] += rng.uniform(-80, 80, (int(bad.sum()), 2))  # moving objects, KLT failures
    Hm = predict_flow(src.astype(np.float32), dst.astype(np.float32))
    assert Hm is not None
    grid = np.stack(np.meshgrid(np.linspace(0, W, 9), np.linspace(0, H, 7)), axis=-1).reshape(-1, 2)
    err = np.linalg.norm(_transfer(Hm, grid) - _transfer(truth, grid), axis=1)
    assert err.max() < H_TOL


def test_predict_flow_none_without_enough_flow():
    rng = np.random.default_rng(4)
    src = rng.uniform([0, 0], [W, H], (11, 2)).astype(np.float32)
    assert predict_flow(src, src + 5) is None  # fewer than 12 tracks
    assert predict_flow(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)) is None
    # enough tracks but no consistent motion (pure noise): no prediction rather than a wrong one
    src = rng.uniform([0, 0], [W, H], (100, 2)).astype(np.float32)
    dst = rng.uniform([0, 0], [W, H], (100, 2)).astype(np.float32)
    assert predict_flow(src, dst) is None
