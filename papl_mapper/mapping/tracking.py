"""Pose tracking against the map: PnP with RANSAC from 3D points to pixels, refined by LM.

Given the map lines seen in the frame and the world directions of the vanishing points, the pose is
then refined with line reprojection and the vanishing-direction rotation constraint too
(mapping/pose_refine.py); without them the points-only LM pose is the result. Where the points are
too few for PnP (blank walls), `pose_from_lines` poses the frame from what is left, as the paper's
tracking does: rotation from its vanishing directions, centre from its lines and points given it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np

from papl_mapper.geometry.lines import endpoint_errors, line_point_dir, plucker_to_camera
from papl_mapper.geometry.resection import centre_equations, rotation_from_directions
from papl_mapper.geometry.se3 import invert, make_T
from papl_mapper.mapping.pose_refine import (
    PoseRefineConfig,
    RefineStats,
    match_directions,
    point_residuals,
    points_rotation_std_deg,
    pose_std,
    refine_pose,
)


@dataclass
class LinePoseConfig:
    """When and how a frame that PnP cannot pose is posed from its lines, points and directions."""

    enabled: bool = True
    """Pose frames with too few point inliers from the map lines they see (`pose_from_lines`); only
    frames PnP fails on are affected."""
    min_lines: int = 2
    """Fewest line inliers: the lines must carry the pose, or the points alone would have."""
    min_constraints: int = 8
    """Fewest equations on the pose from the inliers (2 per point, 2 per line, 2 per direction): the
    6 unknowns and a margin that lets a wrong feature show."""
    hypothesis_px: float = 8.0
    """Inlier threshold (px, points and line endpoints) of the centre hypotheses: the rotation they
    are made under is the guess's about any axis no direction fixes."""
    line_threshold_px: float = 2.0
    """An observed endpoint within this of its projected line counts the line as an inlier."""
    iterations: int = 200
    """Centre hypotheses from random minimal feature sets."""
    max_rotation_std_deg: float = 1.0
    """Largest 1-sigma rotation uncertainty of the final pose from its inliers."""
    max_centre_std: float = 0.02
    """Largest 1-sigma centre uncertainty of the final pose, as a fraction of the median feature depth."""


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
    from_lines: LinePoseConfig = field(default_factory=LinePoseConfig)
    """Where PnP fails: the pose from lines, directions and the few points (when the caller passes lines)."""


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


def pose_from_lines(
    points_w: np.ndarray,
    pixels: np.ndarray,
    K: np.ndarray,
    T_cw_guess: np.ndarray,
    lines_w: np.ndarray,
    line_xy: np.ndarray,
    config: PnPConfig | None = None,
    *,
    dirs_w: np.ndarray | None = None,
    dirs_c: np.ndarray | None = None,
    seed: int = 0,
) -> PnPResult:
    """Pose of a frame whose points are too few for PnP, from map lines (M, 6) Pluecker
    seen as segments (M, 4) px, the few map points (N, 3) at pixels (N, 2) and the vanishing directions.

    The rotation is the guess's turned onto the frame's vanishing directions matched to the world
    directions (`geometry.resection.rotation_from_directions`); given it, centre hypotheses from random
    minimal sets of points and lines (`centre_equations`) are scored by the features they explain;
    the best one is refined on its inliers by LM on point and line reprojection and the directions
    together (the rotation too: one direction leaves the turn about it to the lines and points).
    The pose counts as tracked only when enough lines agree and its inliers fix it (rotation and
    centre uncertainty under `config.from_lines`' limits).
    """
    cfg = config or PnPConfig()
    lc, rc = cfg.from_lines, cfg.refine
    points_w = np.asarray(points_w, np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    L_w = np.asarray(lines_w, np.float64).reshape(-1, 6)
    line_xy = np.asarray(line_xy, np.float64).reshape(-1, 4)
    n, m = len(points_w), len(L_w)
    if m < lc.min_lines:
        return PnPResult(False, reason=f"{n} map points and {m} map lines (need {lc.min_lines} lines)")
    d_w = d_c = np.zeros((0, 3))
    if dirs_w is not None and dirs_c is not None and len(dirs_w):
        d_w, d_c, _ = match_directions(T_cw_guess[:3, :3], dirs_w, dirs_c, rc.match_direction_deg)
    R = rotation_from_directions(T_cw_guess[:3, :3], d_w, d_c)
    A, y, feature = centre_equations(R, K, points_w, pixels, L_w, line_xy)

    def errors(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e_pt = np.linalg.norm(point_residuals(T, points_w, pixels, K), axis=1)
        e_pt[(points_w @ T[2, :3] + T[2, 3]) <= 0] = np.inf
        with np.errstate(invalid="ignore", divide="ignore"):
            e_ln = np.abs(endpoint_errors(K, plucker_to_camera(L_w, invert(T)), line_xy)).max(axis=1)
        return e_pt, np.nan_to_num(e_ln, nan=np.inf)

    def score(e_pt: np.ndarray, e_ln: np.ndarray, thr: float) -> int:
        return 2 * int((e_pt < thr).sum()) + int((e_ln < thr).sum())

    rng = np.random.default_rng(seed)
    C_guess = invert(T_cw_guess)[:3, 3]
    best_C = C_guess
    best = score(*errors(make_T(R, -R @ C_guess)), lc.hypothesis_px)
    rows_of = [np.flatnonzero(feature == k) for k in range(n + m)]
    for _ in range(lc.iterations):
        rows: list[int] = []
        for k in rng.permutation(n + m):
            rows.extend(rows_of[k].tolist())
            if len(rows) >= 3:
                break
        C, _, _, sv = np.linalg.lstsq(A[rows], y[rows], rcond=None)
        if len(sv) < 3 or sv[-1] < 1e-6 * sv[0]:
            continue  # parallel planes: the sample leaves the centre free
        s = score(*errors(make_T(R, -R @ C)), lc.hypothesis_px)
        if s > best:
            best, best_C = s, C
    T = make_T(R, -R @ best_C)
    e_pt, e_ln = errors(T)
    in_pt, in_ln = e_pt < lc.hypothesis_px, e_ln < lc.hypothesis_px
    rc_lines = dataclasses.replace(rc, enabled=True, lines=True, directions=True, line_gate_px=0.0)
    T, stats = refine_pose(
        T,
        points_w[in_pt],
        pixels[in_pt],
        K,
        lines_w=L_w[in_ln],
        line_xy=line_xy[in_ln],
        dirs_w=d_w,
        dirs_c=d_c,
        config=rc_lines,
    )
    e_pt, e_ln = errors(T)
    in_pt, in_ln = e_pt < cfg.ransac_threshold_px, e_ln < lc.line_threshold_px
    n_pt, n_ln = int(in_pt.sum()), int(in_ln.sum())
    d_w, d_c, _ = match_directions(T[:3, :3], d_w, d_c, rc.match_direction_deg)
    constraints = 2 * (n_pt + n_ln + len(d_w))
    what = f"lines: {n_ln}/{m} lines, {n_pt}/{n} points, {len(d_w)} directions"
    if n_ln < lc.min_lines or constraints < lc.min_constraints:
        return PnPResult(False, T, in_pt, reason=f"{what} (too few)", refine=stats)
    rot_std, centre_std = pose_std(
        T,
        points_w[in_pt],
        pixels[in_pt],
        K,
        lines_w=L_w[in_ln],
        line_xy=line_xy[in_ln],
        dirs_w=d_w,
        dirs_c=d_c,
        config=rc_lines,
    )
    depth = np.median(np.concatenate([points_w[in_pt] @ T[2, :3] + T[2, 3], _line_depths(T, L_w[in_ln])]))
    if rot_std > lc.max_rotation_std_deg or centre_std > lc.max_centre_std * depth:
        reason = f"{what}: not fixed ({rot_std:.2f} deg, centre {centre_std / depth:.3f} of depth)"
        return PnPResult(False, T, in_pt, reason=reason, refine=stats)
    rms = float(np.sqrt(np.mean(np.concatenate([e_pt[in_pt], e_ln[in_ln]]) ** 2)))
    return PnPResult(True, T, in_pt, rms, f"{what}, rms {rms:.2f} px", stats)


def _line_depths(T_cw: np.ndarray, L_w: np.ndarray) -> np.ndarray:
    """Distance (M,) from the camera centre to each world line (the depth of its nearest point)."""
    P, _ = line_point_dir(plucker_to_camera(L_w, invert(T_cw)))
    return np.linalg.norm(P, axis=1)
