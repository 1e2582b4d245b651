"""Registering a frame from its matches with the last keyframe when it sees too few mapped points for PnP.

Across a wide baseline (a photo set, a jump) most tracks a frame shares with the previous keyframe
are only two views long, so they are not in the map yet, and PnP on the few mapped points fails.
Those shared tracks still fix the relative rotation and the direction of travel (an essential
matrix); only the length of the step is missing, one number, which the mapped points the frame
sees give even when they are too few for PnP: each one's depth along its ray, under the relative
pose, scales the unit baseline, and the median of those scales is taken where they agree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from papl_mapper.geometry.two_view import find_essential, normalised
from papl_mapper.mapping.initialise import relative_pose_std
from papl_mapper.mapping.tracking import PnPResult
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class RelativePoseConfig:
    """Settings of registration from the relative pose to the last keyframe."""

    enabled: bool = True
    """Try it where PnP fails for lack of mapped points."""
    min_matches: int = 25
    """Fewest verified shared tracks with the keyframe (inliers of the essential matrix): as many as a
    feature pair needs to be verified (`FeatureConfig.min_inliers`); photos a few seconds apart may
    share no more."""
    min_scale_points: int = 4
    """Fewest mapped points whose scales agree."""
    scale_tolerance: float = 0.15
    """A mapped point agrees when its scale is within this fraction of the median."""
    ransac_threshold_px: float = 1.5
    """Essential-matrix inlier threshold."""
    max_reprojection_px: float = 3.0
    """Largest reprojection error, in the frame, of a mapped point that agrees."""
    max_rotation_std_deg: float = 1.0
    """Largest 1-sigma uncertainty of the relative rotation from the verified matches at 1 px
    (`initialise.relative_pose_std`), as for initialisation: matches crowded into a narrow strip of
    the image fit an essential matrix that entangles rotation and translation."""


def _ray_scales(xf: np.ndarray, Xg: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per point the s with x_f parallel to R X_g + s t (least squares on the cross product)."""
    a = np.cross(xf, Xg @ R.T)
    b = np.cross(xf, np.broadcast_to(t, xf.shape))
    return -np.sum(a * b, axis=1) / np.maximum(np.sum(b * b, axis=1), 1e-300)


def register_relative(
    tracks: Tracks,
    f: int,
    g: int,
    T_cw_g: np.ndarray,
    points_w: dict[int, np.ndarray],
    cfg: RelativePoseConfig,
    seed: int = 0,
) -> PnPResult:
    """Pose T_cw of frame f from its shared tracks with keyframe g (pose T_cw_g) and the mapped points
    (`seed` seeds OpenCV's RANSAC)."""
    K = tracks.camera.K
    id_f, uv_f = tracks.points_in(f)
    id_g, uv_g = tracks.points_in(g)
    common, i_f, i_g = np.intersect1d(id_f, id_g, assume_unique=True, return_indices=True)
    if len(common) < cfg.min_matches:
        return PnPResult(False, reason=f"{len(common)} tracks shared with keyframe {g}")
    cv2.setRNGSeed(seed)
    E, mask = find_essential(uv_g[i_g], uv_f[i_f], K, cv2.USAC_FAST, cfg.ransac_threshold_px)
    if E is None or mask is None or E.shape != (3, 3) or mask.sum() < cfg.min_matches:
        return PnPResult(False, reason=f"no essential matrix with {cfg.min_matches} inliers against {g}")
    n, R, t, mask = cv2.recoverPose(E, uv_g[i_g], uv_f[i_f], K, mask=mask.copy())
    inl = mask.ravel() > 0
    if inl.sum() < cfg.min_matches:
        return PnPResult(False, reason=f"{int(inl.sum())} matches in front of both views")
    t = t.ravel() / np.linalg.norm(t)
    x_g, x_f = normalised(uv_g[i_g][inl], K), normalised(uv_f[i_f][inl], K)
    rot_std, _ = relative_pose_std(R, t, x_g, x_f, 1.0 / K[0, 0])
    if rot_std > cfg.max_rotation_std_deg:
        return PnPResult(
            False, reason=f"relative rotation to {g} not fixed by its matches ({rot_std:.2f} deg)"
        )
    mapped = np.array([c in points_w for c in common.tolist()], bool) & inl
    if mapped.sum() < cfg.min_scale_points:
        return PnPResult(False, reason=f"{int(mapped.sum())} mapped points to scale the step")
    Xw = np.stack([points_w[int(c)] for c in common[mapped]])
    Xg = Xw @ T_cw_g[:3, :3].T + T_cw_g[:3, 3]
    xf = np.column_stack([uv_f[i_f][mapped], np.ones(int(mapped.sum()))]) @ np.linalg.inv(K).T
    s = _ray_scales(xf, Xg, R, t)
    s_med = float(np.median(s))
    if not np.isfinite(s_med) or s_med <= 0:
        return PnPResult(False, reason="mapped points give no positive step length")
    agree = np.abs(s - s_med) <= cfg.scale_tolerance * s_med
    if agree.sum() < cfg.min_scale_points:  # e.g. two clusters either side of an even count's median
        return PnPResult(False, reason=f"only {int(agree.sum())} mapped points agree on the step length")
    T_fg = np.eye(4)
    T_fg[:3, :3], T_fg[:3, 3] = R, float(np.median(s[agree])) * t
    T_cw = T_fg @ T_cw_g
    Xc = Xw @ T_cw[:3, :3].T + T_cw[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = Xc @ K.T
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - uv_f[i_f][mapped], axis=1)
    good = agree & (Xc[:, 2] > 0) & (err < cfg.max_reprojection_px)
    if good.sum() < cfg.min_scale_points:
        return PnPResult(False, reason=f"only {int(good.sum())} mapped points agree on the step length")
    inliers = np.zeros(len(id_f), bool)
    inliers[i_f[mapped][good]] = True
    rms = float(np.sqrt(np.mean(err[good] ** 2)))
    return PnPResult(
        True,
        T_cw=T_cw,
        inliers=inliers[np.array([t in points_w for t in id_f.tolist()], bool)],  # rows of the mapped ids
        rms_px=rms,
        reason=f"relative pose to keyframe {g}: {int(inl.sum())} matches, {int(good.sum())} scale points, "
        f"rotation {rot_std:.2f} deg (1 sigma)",
    )
