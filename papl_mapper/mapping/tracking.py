"""Pose tracking against the map: PnP with RANSAC from 3D points to pixels, refined by LM.

Line reprojection and the vanishing-direction rotation constraint refine this pose later in
the mapping stage; this module gives the robust first estimate and its inliers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass
class PnPConfig:
    """Thresholds of PnP tracking."""

    ransac_threshold_px: float = 2.0
    """Reprojection error under which a correspondence is an inlier."""
    min_inliers: int = 12
    """Fewest inliers for the pose to count as tracked."""
    iterations: int = 200
    """RANSAC iterations."""
    seed: int = 0
    """Seed for OpenCV's RANSAC."""


@dataclass
class PnPResult:
    """World-to-camera pose `T_cw`, the inlier mask and the inlier RMS reprojection error (px)."""

    ok: bool
    T_cw: np.ndarray = field(default_factory=lambda: np.eye(4))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rms_px: float = float("nan")
    reason: str = ""


def _to_T(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


def track_pnp(
    points_w: np.ndarray,
    pixels: np.ndarray,
    K: np.ndarray,
    T_cw_guess: np.ndarray | None = None,
    config: PnPConfig | None = None,
) -> PnPResult:
    """Pose from 3D world points (N,3) seen at undistorted pixels (N,2); a guess seeds the search."""
    cfg = config or PnPConfig()
    points_w = np.asarray(points_w, np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    n = len(points_w)
    if n < max(4, cfg.min_inliers):
        return PnPResult(False, reason=f"only {n} map points matched (need {cfg.min_inliers})")
    use_guess = T_cw_guess is not None
    rvec = cv2.Rodrigues(T_cw_guess[:3, :3])[0] if use_guess else np.zeros((3, 1))
    tvec = T_cw_guess[:3, 3].reshape(3, 1).copy() if use_guess else np.zeros((3, 1))
    cv2.setRNGSeed(cfg.seed)
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        points_w,
        pixels,
        K,
        None,
        rvec,
        tvec,
        useExtrinsicGuess=use_guess,
        iterationsCount=cfg.iterations,
        reprojectionError=cfg.ransac_threshold_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_SQPNP if not use_guess else cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or idx is None or len(idx) < cfg.min_inliers:
        return PnPResult(False, reason=f"PnP found {0 if idx is None else len(idx)} inliers of {n}")
    mask = np.zeros(n, bool)
    mask[idx.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(points_w[mask], pixels[mask], K, None, rvec, tvec)
    T_cw = _to_T(rvec, tvec)
    proj = (points_w @ T_cw[:3, :3].T + T_cw[:3, 3]) @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - pixels, axis=1)
    mask = (proj[:, 2] > 0) & (err < cfg.ransac_threshold_px)
    if mask.sum() < cfg.min_inliers:
        return PnPResult(False, T_cw, mask, reason=f"{int(mask.sum())} inliers after refinement")
    rms = float(np.sqrt(np.mean(err[mask] ** 2)))
    return PnPResult(True, T_cw, mask, rms, f"{int(mask.sum())}/{n} inliers, rms {rms:.2f} px")
