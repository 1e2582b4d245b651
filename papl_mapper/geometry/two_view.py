"""OpenCV's essential-matrix estimation with degenerate input reported as no model, the pixel
Sampson distance of matches to an essential matrix, and pixels to normalised coordinates.

Matches that fit no unique essential matrix (a camera standing still, a pure rotation, exact and
noise-free) make OpenCV 5.1's five-point solver raise (`solvePoly`'s assertion on a vanishing leading
coefficient) where earlier versions returned no model or a degenerate one. Every caller already treats
"no model" as a refusal, so the error becomes that.
"""

from __future__ import annotations

import cv2
import numpy as np


def normalised(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of an undistorted pinhole camera K in normalised coordinates (K^-1 applied)."""
    return (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def find_essential(
    pts_a: np.ndarray,
    pts_b: np.ndarray,
    K: np.ndarray,
    method: int,
    threshold_px: float,
    confidence: float = 0.999,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(E, inlier mask) of matched pixels (N, 2) under camera K by `method` (cv2.RANSAC, cv2.USAC_FAST,
    ...), or (None, None) where OpenCV finds none or refuses the input as degenerate."""
    try:
        return cv2.findEssentialMat(pts_a, pts_b, K, method, confidence, threshold_px)
    except cv2.error:
        return None, None


def sampson_px(E: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,) Sampson distances (pixels) of matched pixels (N, 2 each) to the epipolar geometry of E
    (x_b^T E x_a = 0 in normalised coordinates) under camera K."""
    K_inv = np.linalg.inv(K)
    F = K_inv.T @ E @ K_inv
    xa = np.column_stack([pts_a, np.ones(len(pts_a))])
    xb = np.column_stack([pts_b, np.ones(len(pts_b))])
    Fa, Ftb = xa @ F.T, xb @ F
    num = np.sum(xb * Fa, axis=1) ** 2
    return np.sqrt(num / (Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Ftb[:, 0] ** 2 + Ftb[:, 1] ** 2))
