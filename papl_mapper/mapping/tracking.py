"""Pose tracking against the map: PnP with RANSAC from 3D points to pixels, refined by LM.

Given the map lines seen in the frame and the world directions of the vanishing points, the pose is
then refined with line reprojection and the vanishing-direction rotation constraint too
(mapping/pose_refine.py); without them the points-only LM pose is the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from papl_mapper.mapping.pose_refine import (
    PoseRefineConfig,
    RefineStats,
    match_directions,
    points_rotation_std_deg,
    refine_pose,
)


@dataclass
class PnPConfig:
    """Thresholds of PnP tracking."""

    ransac_threshold_px: float = 2.0
    """Reprojection error under which a correspondence is an inlier."""
    min_inliers: int = 12
    """Fewest inliers for the pose to count as tracked."""
    iterations: int = 200
    """RANSAC iterations."""
    refine: PoseRefineConfig = field(default_factory=PoseRefineConfig)
    """Refinement with lines and vanishing directions after PnP (when the caller passes them)."""


@dataclass
class PnPResult:
    """World-to-camera pose `T_cw`, the inlier mask and the inlier RMS reprojection error (px)."""

    ok: bool
    T_cw: np.ndarray = field(default_factory=lambda: np.eye(4))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rms_px: float = float("nan")
    reason: str = ""
    refine: RefineStats | None = None
    """Statistics of the line / direction refinement, None when it did not run."""


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
    *,
    lines_w: np.ndarray | None = None,
    line_xy: np.ndarray | None = None,
    dirs_w: np.ndarray | None = None,
    dirs_c: np.ndarray | None = None,
    dirs_sigma_deg: np.ndarray | None = None,
    seed: int = 0,
) -> PnPResult:
    """Pose from 3D world points (N,3) seen at undistorted pixels (N,2); a guess seeds the search.

    Optional refinement terms: map lines seen in the frame (M,2,3) world endpoints or (M,6) Pluecker
    with their segments (M,4) px, and world directions (A,3) with the frame's vanishing directions
    (V,3) (NaN rows skipped, matched sign-free within `config.refine.match_direction_deg`), optionally
    with a sigma (A,) in degrees per world direction. `seed` seeds OpenCV's RANSAC.
    """
    cfg = config or PnPConfig()
    points_w = np.asarray(points_w, np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    n = len(points_w)
    if n < max(4, cfg.min_inliers):
        return PnPResult(False, reason=f"only {n} map points matched (need {cfg.min_inliers})")
    use_guess = T_cw_guess is not None
    rvec = cv2.Rodrigues(T_cw_guess[:3, :3])[0] if use_guess else np.zeros((3, 1))
    tvec = T_cw_guess[:3, 3].reshape(3, 1).copy() if use_guess else np.zeros((3, 1))
    cv2.setRNGSeed(seed)
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
    stats = None
    rc = cfg.refine
    has_lines = rc.lines and lines_w is not None and line_xy is not None and len(lines_w) > 0
    has_lines = has_lines and (rc.lines_below_inliers <= 0 or int(mask.sum()) < rc.lines_below_inliers)
    has_dirs = rc.directions and dirs_w is not None and dirs_c is not None and len(dirs_w) > 0
    weak = rc.directions_below_inliers <= 0 or int(mask.sum()) < rc.directions_below_inliers
    if has_dirs and weak and rc.directions_above_rotation_std_deg > 0:
        std = points_rotation_std_deg(T_cw, points_w[mask], pixels[mask], K, rc.point_sigma_px)
        weak = std > rc.directions_above_rotation_std_deg
    has_dirs = has_dirs and weak
    if rc.enabled and (has_lines or has_dirs):
        d_w = d_c = sig = None
        if has_dirs:
            d_w, d_c, idx = match_directions(T_cw[:3, :3], dirs_w, dirs_c, rc.match_direction_deg)
            sig = None if dirs_sigma_deg is None else np.asarray(dirs_sigma_deg, np.float64)[idx]
        T_cw, stats = refine_pose(
            T_cw,
            points_w[mask],
            pixels[mask],
            K,
            lines_w=lines_w,
            line_xy=line_xy,
            dirs_w=d_w,
            dirs_c=d_c,
            dirs_sigma_deg=sig,
            config=rc,
        )
    proj = (points_w @ T_cw[:3, :3].T + T_cw[:3, 3]) @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - pixels, axis=1)
    mask = (proj[:, 2] > 0) & (err < cfg.ransac_threshold_px)
    if mask.sum() < cfg.min_inliers:
        return PnPResult(
            False, T_cw, mask, reason=f"{int(mask.sum())} inliers after refinement", refine=stats
        )
    rms = float(np.sqrt(np.mean(err[mask] ** 2)))
    return PnPResult(True, T_cw, mask, rms, f"{int(mask.sum())}/{n} inliers, rms {rms:.2f} px", stats)
