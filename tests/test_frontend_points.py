"""Point tracks (KLT with forward-backward check, replenishment, keyframe ORB descriptors) and keyframes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.keyframes import KeyframeConfig, KeyframeSelector
from papl_mapper.frontend.klt import FlowConfig, track_klt
from papl_mapper.frontend.points import PointConfig, PointTracker

W, H = 480, 360
SUBPIXEL_TOL_PX = 0.15  # KLT error on a smooth texture moved by a known shift
NOISY_TOL_PX = 0.5  # with sensor noise


def _texture(seed: int = 0, w: int = 800, h: int = 600) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (h // 6, w // 6)).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (0, 0), 1.5)


def _view(tex: np.ndarray, dx: float, dy: float, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """The W x H window of the texture whose top-left lies at (100 + dx, 80 + dy)."""
    M = np.float32([[1, 0, -(100 + dx)], [0, 1, -(80 + dy)]])
    img = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC)
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("noise, tol", [(0.0, SUBPIXEL_TOL_PX), (3.0, NOISY_TOL_PX)])
def test_klt_recovers_known_shift(noise, tol):
    tex = _texture()
    a = _view(tex, 0, 0, noise, 1)
    b = _view(tex, 2.3, -1.7, noise, 2)  # content moves by (-2.3, +1.7) in the image
    pts = cv2.goodFeaturesToTrack(a, 200, 0.01, 10).reshape(-1, 2)
    pts = pts[(pts[:, 0] > 10) & (pts[:, 0] < W - 10) & (pts[:, 1] > 10) & (pts[:, 1] < H - 10)]
    new, ok, _ = track_klt(a, b, pts, FlowConfig(), W, H)
    assert ok.mean() > 0.95
    err = np.linalg.norm(new[ok] - pts[ok] - [-2.3, 1.7], axis=1)
    assert np.median(err) < tol


def test_forward_backward_check_drops_occluded_points():
    tex = _texture()
    a = _view(tex, 0, 0)
    b = _view(tex, 1.0, 0.0)
    b[100:200, 100:200] = _view(_texture(7), 0, 0)[100:200, 100:200]  # a different patch: occlusion
    pts = np.array([[150.0, 150.0], [160, 140], [300, 250], [350, 100]], np.float32)
    _, ok, _ = track_klt(a, b, pts, FlowConfig(), W, H)
    assert list(ok) == [False, False, True, True]


def test_tracker_ids_persist_and_replenish():
    tex = _texture()
    cfg = PointConfig(max_points=150, replenish_below=0.95)
    tr = PointTracker(cfg, FlowConfig(), W, H)
    prev = None
    first_ids = None
    for k in range(12):
        img = _view(tex, 3.0 * k, 0.0, 1.0, k)
        tr.step(img, prev)
        if k == 0:
            first_ids = dict(zip(tr.ids.tolist(), tr.uv.tolist(), strict=True))
            assert len(tr.ids) >= 0.85 * cfg.max_points
        prev = img
    # tracks that survived moved by exactly -3 px per frame; their ids did not change
    alive = [i for i in tr.ids.tolist() if i in first_ids]
    assert len(alive) > 50
    for i in alive[:50]:
        row = tr.ids.tolist().index(i)
        np.testing.assert_allclose(tr.uv[row], np.array(first_ids[i]) + [-33.0, 0.0], atol=0.5)
    # replenished where points left the image (on the right, new content)
    assert len(tr.ids) >= cfg.replenish_below * cfg.max_points
    assert len(np.unique(tr.ids)) == len(tr.ids)
    assert tr.ids.max() >= cfg.max_points  # new ids were issued


def test_keyframes_by_parallax_survival_and_density_cap():
    cfg = KeyframeConfig(min_parallax_px=10.0, min_survival=0.5, min_gap_frames=3, max_gap_frames=100)
    sel = KeyframeSelector(cfg)
    ids = np.arange(100)
    base = np.random.default_rng(0).uniform(0, 400, (100, 2))
    kfs = [k for k in range(30) if sel.update(ids, base + [2.0 * k, 0.0])]  # 2 px per frame
    assert kfs == [0, 5, 10, 15, 20, 25]  # 10 px parallax every 5 frames
    sel = KeyframeSelector(cfg)
    kfs = [k for k in range(10) if sel.update(ids, base + [20.0 * k, 0.0])]  # 20 px per frame
    assert kfs == [0, 3, 6, 9]  # capped by min_gap_frames
    sel = KeyframeSelector(cfg)
    flags = []
    for k in range(10):  # no motion, but tracks die: 10 per frame
        flags.append(sel.update(ids[10 * k :], base[10 * k :]))
    # survival 40/100 < 0.5 at frame 6; at frame 9 only 10 common tracks (< min_common_tracks 12)
    assert [k for k, f in enumerate(flags) if f] == [0, 6, 9]
    sel = KeyframeSelector(KeyframeConfig(max_gap_frames=7))
    assert [k for k in range(20) if sel.update(ids, base)] == [0, 7, 14]


def test_density_cap_holds_dense_video_back_but_not_photos():
    """The same 20 px of parallax per frame: at 30 fps the cap keeps every third frame; photos a second
    apart (or a recording read with a large step) each become a keyframe."""
    cfg = KeyframeConfig(min_parallax_px=10.0, min_gap_frames=3, min_gap_s=0.5)
    ids = np.arange(100)
    base = np.random.default_rng(0).uniform(0, 400, (100, 2))
    for dt, expected in ((1 / 30, [0, 3, 6, 9]), (1.0, list(range(10))), (0.2, [0, 3, 6, 9])):
        sel = KeyframeSelector(cfg)
        kfs = [k for k in range(10) if sel.update(ids, base + [20.0 * k, 0.0], t=k * dt)]
        assert kfs == expected, dt
    sel = KeyframeSelector(cfg)  # photos without parallax stay non-keyframes
    assert [k for k in range(5) if sel.update(ids, base, t=float(k))] == [0]
