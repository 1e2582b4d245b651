"""Pyramidal Lucas-Kanade flow with a forward-backward check.

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


def track_klt(
    prev: np.ndarray,
    cur: np.ndarray,
    uv: np.ndarray,
    config: FlowConfig,
    width: int,
    height: int,
    motion: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track (N, 2) pixels from gray image prev to cur: new pixels (N, 2) float32, kept mask (N,).

    `motion` (a homography of the expected image motion) seeds LK forward; the backward pass starts
    from the original pixels. Kept: found forward and backward, the round trip within
    fb_threshold_px, inside the image.
    """
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(uv, np.float32).reshape(-1, 1, 2)
    level = config.levels
    win = (config.win_size, config.win_size)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, config.max_iterations, config.epsilon)
    lk = {"winSize": win, "maxLevel": level, "criteria": crit}
    if motion is not None and config.predict:
        guess = cv2.perspectiveTransform(p0, motion).astype(np.float32)
        seeded = {**lk, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, guess, **seeded)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), **seeded)
    else:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb <= config.fb_threshold_px)
    ok &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= width - 1) & (p1[:, 1] <= height - 1)
    return p1, ok
