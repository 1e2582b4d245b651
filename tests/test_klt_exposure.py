"""Exposure changes in KLT: `exposure_gain` measures a camera's gain between two frames, and
`track_klt` compensates it so that tracks do not slide when the brightness changes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.klt import FlowConfig, exposure_gain, track_klt

W, H = 320, 240
ON = FlowConfig(exposure_gate=0.0025)
SHIFT = np.array([2.3, -1.7])


def _texture(seed: int = 0) -> np.ndarray:
    """A smooth, low-contrast float texture (grey 60..180): KLT's bias under a gain change is large there."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=(H, W)).astype(np.float32), (0, 0), 2.0)
    t = (t - t.min()) / (t.max() - t.min())
    return 60.0 + 120.0 * t


def _pair(gain: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """8-bit frames prev and cur: cur is prev moved by SHIFT and seen with `gain` times the exposure."""
    t = _texture(seed)
    moved = cv2.warpAffine(t, np.float32([[1, 0, SHIFT[0]], [0, 1, SHIFT[1]]]), (W, H), flags=cv2.INTER_CUBIC)
    return _8bit(t), _8bit(moved * gain)


def _8bit(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _corners(img: np.ndarray) -> np.ndarray:
    uv = cv2.goodFeaturesToTrack(img, 200, 0.01, 10, blockSize=3).reshape(-1, 2)
    inside = (uv[:, 0] > 20) & (uv[:, 0] < W - 20) & (uv[:, 1] > 20) & (uv[:, 1] < H - 20)
    return uv[inside]


@pytest.mark.parametrize("gain", [0.94, 1.0, 1.03, 1.08])
def test_exposure_gain_measures_the_cameras_gain(gain: float) -> None:
    prev, cur = _pair(gain)
    uv = _corners(prev)
    estimate = exposure_gain(prev, cur, uv, uv + SHIFT)
    assert abs(estimate - gain) < 0.002


def test_exposure_gain_is_one_without_enough_patches() -> None:
    prev, cur = _pair(1.1)
    uv = _corners(prev)[:5]
    assert exposure_gain(prev, cur, uv, uv + SHIFT) == 1.0
    white = np.full((H, W), 255, np.uint8)  # clipped everywhere: nothing says what the gain is
    uv = _corners(prev)
    assert exposure_gain(white, white, uv, uv + SHIFT) == 1.0


def test_tracks_hold_under_an_exposure_change() -> None:
    prev, cur = _pair(1.06)
    uv = _corners(prev)
    truth = uv + SHIFT
    on, ok_on, gain = track_klt(prev, cur, uv, ON, W, H)
    off, ok_off, gain_off = track_klt(prev, cur, uv, FlowConfig(exposure_gate=0.0), W, H)
    assert abs(gain - 1.06) < 0.005 and gain_off == 1.0
    both = ok_on & ok_off
    assert both.sum() > 0.8 * len(uv)
    steady, _, _ = track_klt(prev, _pair(1.0)[1], uv, FlowConfig(exposure_gate=0.0), W, H)

    def error(found: np.ndarray) -> float:
        return float(np.median(np.linalg.norm(found[both] - truth[both], axis=1)))

    # as well as with a steady exposure (LK's own error on this texture), and well under uncompensated
    assert error(on) < error(steady) + 0.005
    assert error(on) < 0.4 * error(off)


def test_off_by_default() -> None:
    prev, cur = _pair(1.06)
    uv = _corners(prev)
    on, _, gain = track_klt(prev, cur, uv, FlowConfig(), W, H)
    off, _, _ = track_klt(prev, cur, uv, FlowConfig(exposure_gate=0.0), W, H)
    assert gain == 1.0
    np.testing.assert_array_equal(on, off)


def test_no_change_below_the_gate() -> None:
    """Constant exposure leaves the tracks exactly as LK without compensation finds them."""
    prev, cur = _pair(1.0)
    uv = _corners(prev)
    on, ok_on, gain = track_klt(prev, cur, uv, ON, W, H)
    off, ok_off, _ = track_klt(prev, cur, uv, FlowConfig(exposure_gate=0.0), W, H)
    assert abs(gain - 1.0) <= ON.exposure_gate
    np.testing.assert_array_equal(on, off)
    np.testing.assert_array_equal(ok_on, ok_off)
