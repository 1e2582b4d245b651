"""Relative camera rotation between two frames from their common point tracks.

Used to carry the vertical vanishing direction from frame to frame (x_cur = R x_prev), so the
vertical prior follows pitch and roll instead of lagging behind them.
"""

from __future__ import annotations

import cv2
import numpy as np

from papl_mapper.geometry.se3 import kabsch_rotation
from papl_mapper.geometry.two_view import find_essential


def common_points(
    ids_a: np.ndarray, uv_a: np.ndarray, ids_b: np.ndarray, uv_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) in a and in b of the track ids both frames see."""
    _, ia, ib = np.intersect1d(ids_a, ids_b, assume_unique=True, return_indices=True)
    return uv_a[ia], uv_b[ib]


def relative_rotation(
    uv_a: np.ndarray,
    uv_b: np.ndarray,
    K: np.ndarray,
    min_points: int = 15,
    threshold_px: float = 1.0,
    min_inlier_ratio: float = 0.5,
    max_angle_deg: float = 20.0,
) -> np.ndarray | None:
    """R (3, 3) with x_b = R x_a (camera frames) from undistorted correspondences, or None.

    Essential matrix with RANSAC, then the cheirality check of recoverPose. Without parallax
    (the flow is explained by a rotation alone) the homography K R K^-1 gives the rotation. None
    when there are too few points or inliers, or the rotation exceeds max_angle_deg.
    """
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    n = len(uv_a)
    if n < min_points:
        return None
    flow = np.linalg.norm(uv_b - uv_a, axis=1)
    if np.median(flow) < 0.05:
        return np.eye(3)
    R = _rotation_from_homography(uv_a, uv_b, K, threshold_px, min_inlier_ratio)
    if R is None:
        E, mask = find_essential(uv_a, uv_b, K, cv2.RANSAC, threshold_px)
        if (
            E is None
            or E.shape != (3, 3)
            or mask is None
            or mask.sum() < max(min_points, min_inlier_ratio * n)
        ):
            return None
        _, R, _, _ = cv2.recoverPose(E, uv_a, uv_b, K, mask=mask.copy())
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    return R if angle <= max_angle_deg else None


def rotation_from_bearings(
    uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, iterations: int = 4, scale_px: float = 2.0
) -> np.ndarray | None:
    """Least-squares rotation (Kabsch, robustly reweighted) with x_b = R x_a, ignoring translation.

    Fast (no RANSAC). Translation parallax leaks into the rotation mostly as yaw for sideways and
    forward walking, which barely moves the vertical; used to carry the vertical prior.
    """
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    if len(uv_a) < 3:
        return None
    Kinv = np.linalg.inv(K)
    a = np.column_stack([uv_a, np.ones(len(uv_a))]) @ Kinv.T
    b = np.column_stack([uv_b, np.ones(len(uv_b))]) @ Kinv.T
    a /= np.linalg.norm(a, axis=1)[:, None]
    b /= np.linalg.norm(b, axis=1)[:, None]
    w = np.ones(len(a))
    c = scale_px / K[0, 0]  # residual scale in radians
    R = np.eye(3)
    for _ in range(iterations):
        R = kabsch_rotation(a, b, w)
        r = np.linalg.norm(b - a @ R.T, axis=1)
        w = 1.0 / (1.0 + (r / c) ** 2)  # Cauchy weights
    return R


def _rotation_from_homography(
    uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, threshold_px: float, min_inlier_ratio: float
) -> np.ndarray | None:
    """The nearest rotation to K^-1 H K when a homography explains almost all the flow (no parallax)."""
    H, mask = cv2.findHomography(uv_a, uv_b, cv2.RANSAC, threshold_px)
    if H is None or mask is None or mask.mean() < max(0.9, min_inlier_ratio):
        return None
    M = np.linalg.inv(K) @ H @ K
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return None
    # a plane-induced homography with translation is not a rotation: check that R explains the flow
    x = np.column_stack([uv_a, np.ones(len(uv_a))]) @ (K @ R @ np.linalg.inv(K)).T
    err = np.linalg.norm(x[:, :2] / x[:, 2:3] - uv_b, axis=1)
    return R if np.mean(err <= 2 * threshold_px) >= 0.9 else None
