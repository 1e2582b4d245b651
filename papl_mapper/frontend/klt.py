"""Pyramidal Lucas-Kanade flow with a forward-backward check and exposure compensation.

(OpenCV's Python binding takes only images, not prebuilt pyramids, so each call pyramids both.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class FlowConfig:
    """Settings of the KLT tracker shared by points and line samples."""

    win_size: int = 15
    """Side of the LK window in pixels (odd). 11 halves the LK cost but gave mixed mapping results
    (better on some synthetic walks, worse on the garage and the demo), so 15 stays the default."""
    levels: int = 3
    """Pyramid levels above the full-resolution image."""
    fb_threshold_px: float = 1.0
    """Largest forward-backward round-trip error of a kept track."""
    max_iterations: int = 10
    """LK iterations per level."""
    epsilon: float = 0.03
    """LK convergence threshold in pixels."""
    predict: bool = True
    """Start LK from the image motion of the previous frame pair (a homography fitted to its flow),
    so fast turns, whose flow exceeds what the pyramid can find from zero, keep their tracks."""
    exposure_gate: float = 0.0
    """Compensate an exposure change between the two images (a relative gain, `exposure_gain`) larger
    than this; 0 never does. LK assumes constant brightness, and on low-contrast texture its tracks
    slide under a changing gain; 0.0025 keeps them and stays above what the gain reads where the
    exposure is constant. Off by default: the tracks are closer to the ground truth with it, but the
    maps of KITTI and of the demo came out less accurate (benchmarks/results/notes.md)."""


def predict_flow(flow_from: np.ndarray, flow_to: np.ndarray) -> np.ndarray | None:
    """Homography (3, 3) of the image motion seen in one frame pair's flow; None when too little flow.

    Fitted with RANSAC so moving objects and parallax outliers do not bend it.
    """
    if len(flow_from) < 12:
        return None
    H, inl = cv2.findHomography(flow_from, flow_to, cv2.RANSAC, 3.0)
    if H is None or inl is None or inl.sum() < 0.5 * len(flow_from):
        return None
    return H


#: Patches darker or brighter than these grey levels (near black, clipped) say nothing about the gain.
GAIN_RANGE = (16.0, 240.0)
#: Half side of the patches whose brightness is compared: the same pixels of the scene in both images.
GAIN_PATCH_RADIUS = 3
#: Fewest usable patches for a gain.
GAIN_MIN_PATCHES = 12


def patch_means(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,) mean brightness of the square patch centred on each (sub-)pixel position, sampled bilinearly."""
    r = GAIN_PATCH_RADIUS
    side = 2 * r + 1
    off = np.arange(-r, r + 1, dtype=np.float32)
    uv = np.asarray(uv, np.float32)
    map_x = np.broadcast_to(uv[:, 0, None, None] + off[None, None, :], (len(uv), side, side))
    map_y = np.broadcast_to(uv[:, 1, None, None] + off[None, :, None], (len(uv), side, side))
    patches = cv2.remap(
        img,
        np.ascontiguousarray(map_x).reshape(-1, side),
        np.ascontiguousarray(map_y).reshape(-1, side),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return patches.reshape(len(uv), side * side).mean(axis=1, dtype=np.float64)


def exposure_gain(prev: np.ndarray, cur: np.ndarray, uv_prev: np.ndarray, uv_cur: np.ndarray) -> float:
    """Exposure of cur relative to prev from pixels tracked between them (N, 2 each); 1 when unknown.

    The median brightness ratio of the patches around the tracked pixels: a camera's exposure or
    gain change scales every pixel alike (through a gamma curve too), while the scene's own
    brightness changes with the view only here and there.
    """
    if len(uv_prev) < GAIN_MIN_PATCHES:
        return 1.0
    a, b = patch_means(prev, uv_prev), patch_means(cur, uv_cur)
    lo, hi = GAIN_RANGE
    use = (a > lo) & (a < hi) & (b > lo) & (b < hi)
    if use.sum() < GAIN_MIN_PATCHES:
        return 1.0
    return float(np.median(b[use] / a[use]))


def track_klt(
    prev: np.ndarray,
    cur: np.ndarray,
    uv: np.ndarray,
    config: FlowConfig,
    width: int,
    height: int,
    motion: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Track (N, 2) pixels from gray image prev to cur: new pixels (N, 2) float32, kept mask (N,) and
    the exposure gain compensated (1 when none was).

    `motion` (a homography of the expected image motion) seeds LK forward; the backward pass starts
    from the original pixels. An exposure change beyond `exposure_gate`, measured on the forward
    pass, is compensated by scaling prev to cur's exposure and tracking again from the forward pass.
    Kept: found forward and backward, the round trip within fb_threshold_px, inside the image.
    """
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool), 1.0
    p0 = np.ascontiguousarray(uv, np.float32).reshape(-1, 1, 2)
    level = config.levels
    win = (config.win_size, config.win_size)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, config.max_iterations, config.epsilon)
    lk = {"winSize": win, "maxLevel": level, "criteria": crit}
    seeded = {**lk, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}
    predicted = motion is not None and config.predict
    if predicted:
        guess = cv2.perspectiveTransform(p0, motion).astype(np.float32)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, guess, **seeded)
    else:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
    gain = 1.0
    if config.exposure_gate > 0:
        found = st1.ravel() == 1
        measured = exposure_gain(prev, cur, p0.reshape(-1, 2)[found], p1.reshape(-1, 2)[found])
        if abs(measured - 1.0) > config.exposure_gate:
            gain = measured
            prev = cv2.convertScaleAbs(prev, alpha=gain)  # prev as cur's exposure would have seen it
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, p1, **seeded)
    if predicted:
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), **seeded)
    else:
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb <= config.fb_threshold_px)
    ok &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= width - 1) & (p1[:, 1] <= height - 1)
    return p1, ok, gain
