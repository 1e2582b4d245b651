"""Two-view initialisation: relative pose and first points from matched normalised coordinates.

Both an essential matrix and a homography are fitted with RANSAC and scored by their truncated
chi-square errors; the homography is chosen when its share of the two scores exceeds
`homography_score_ratio` (planar or low-parallax scenes), as ORB-SLAM does. A pair that a rotation
alone explains (the camera turned in place) is refused as `rotation_only`, before any structure is
triangulated from it. The result is accepted only with enough parallax and enough points in front of
both cameras; otherwise `ok` is False and `reason` says why, so the caller can try a later pair.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from papl_mapper.geometry.se3 import bearings, rotation_angle_deg, rotation_between_rays, skew
from papl_mapper.geometry.two_view import find_essential

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """Thresholds of the two-view initialisation."""

    ransac_threshold_px: float = 1.5
    """RANSAC inlier threshold in pixels (converted to normalised units with the focal length)."""
    min_inliers: int = 60
    """Fewest RANSAC inliers for a usable model."""
    min_parallax_deg: float = 1.0
    """Median parallax of the triangulated points below which the baseline is too short (ORB-SLAM's)."""
    min_triangulated: int = 50
    """Fewest points in front of both cameras with good parallax."""
    strong_parallax_deg: float = 2.0
    """Points with at least this parallax count as well triangulated when pairs are compared."""
    homography_score_ratio: float = 0.45
    """Prefer the homography when S_H / (S_H + S_E) of the truncated chi-square scores exceeds this."""
    rotation_parallax_deg: float = 0.3
    """A pair whose matches a pure rotation explains to this median angle has no parallax (turn in place)."""
    ambiguity_deg: float = 2.0
    """Two pose hypotheses are different when their rotations differ by more than this."""
    max_rotation_std_deg: float = 1.0
    """Largest 1-sigma uncertainty of the relative rotation (matches at 1 px): the points of a pair
    crowded into a narrow strip of the image fit an essential matrix that leaves rotation and
    translation entangled, and the map built on it drifts from the start."""


@dataclass
class InitResult:
    """Relative pose of view 2 (`R_21`, `t_21` with |t| = 1: x2 = R_21 x1 + t_21) and triangulated points."""

    ok: bool
    reason: str
    R_21: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_21: np.ndarray = field(default_factory=lambda: np.zeros(3))
    points_1: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) in camera-1 frame
    point_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) match indices
    model: str = ""
    inliers: int = 0
    median_parallax_deg: float = 0.0
    strong_points: int = 0
    """Triangulated points with at least `strong_parallax_deg` of parallax: how good the pair is."""
    rotation_only: bool = False
    """The matches agree with a pure rotation (`R_21`): no baseline to triangulate from."""
    rotation_std_deg: float = float("nan")
    """1-sigma uncertainty of `R_21` from the triangulated matches at 1 px (`relative_pose_std`)."""
    direction_std_deg: float = float("nan")
    """...and of the direction of `t_21`."""


def triangulate_normalised(
    R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear triangulation of normalised matches (N,2); returns points in frame 1, depths in 1 and 2."""
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([R_21, t_21.reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))  # (4, N)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X[:3] / X[3]).T  # (N, 3)
    z1 = X[:, 2]
    z2 = (X @ R_21.T + t_21)[:, 2]
    return X, z1, z2


def parallax_deg(R_21: np.ndarray, t_21: np.ndarray, X1: np.ndarray) -> np.ndarray:
    """(N,) angle at each point between the rays to the two camera centres."""
    c2 = -R_21.T @ t_21  # centre of camera 2 in frame 1
    a = X1 / np.linalg.norm(X1, axis=1, keepdims=True)
    b = X1 - c2
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def _check_pose(
    R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray, cfg: InitConfig
) -> tuple[int, np.ndarray, np.ndarray, float]:
    """Count good points (in front of both views, finite, enough parallax) for one pose hypothesis."""
    X, z1, z2 = triangulate_normalised(R, t, x1, x2)
    good = mask & np.isfinite(X).all(axis=1) & (z1 > 0) & (z2 > 0)
    par = np.zeros(len(X))
    if good.any():
        par[good] = parallax_deg(R, t, X[good])
    good &= par > 0.1 * cfg.min_parallax_deg
    median = float(np.median(par[good])) if good.any() else 0.0
    return int(good.sum()), good, X, median


def sampson_errors(R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) first-order geometric (Sampson) distances of normalised matches to E = [t]x R."""
    E = skew(t_21) @ R_21
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.sum(h2 * Ex1, axis=1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-300))


def _pose_update(R_21: np.ndarray, t_21: np.ndarray) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """(R, unit t) at 5 local coordinates: a rotation vector applied on the left, and a step of t on the
    tangent plane of the unit sphere (renormalised)."""
    t0 = t_21 / np.linalg.norm(t_21)
    basis = np.linalg.svd(t0.reshape(1, 3))[2][1:]  # (2, 3) tangent of the unit sphere at t0

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = t0 + p[3:] @ basis
        return cv2.Rodrigues(p[:3])[0] @ R_21, t / np.linalg.norm(t)

    return unpack


def refine_relative_pose(
    R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the robust Sampson error over (R, unit t): 5 DoF, Huber at `scale` (normalised units)."""
    unpack = _pose_update(R_21, t_21)
    sol = least_squares(
        lambda p: sampson_errors(*unpack(p), x1, x2), np.zeros(5), loss="huber", f_scale=scale
    )
    return unpack(sol.x)


def relative_pose_std(
    R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray, sigma: float
) -> tuple[float, float]:
    """1-sigma uncertainty (deg) of the rotation and of the translation direction of a relative pose
    explained by normalised matches (N, 2) whose Sampson errors have deviation `sigma`: the largest
    axes of the Gauss-Newton covariance over the 5 DoF (central differences; inf where singular)."""
    unpack = _pose_update(R_21, t_21)
    h = 1e-6
    J = np.empty((len(x1), 5))
    for k in range(5):
        d = np.zeros(5)
        d[k] = h
        J[:, k] = (sampson_errors(*unpack(d), x1, x2) - sampson_errors(*unpack(-d), x1, x2)) / (2 * h)
    try:
        cov = np.linalg.inv(J.T @ J) * sigma**2
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    rot = np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    direction = np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))
    return float(rot), float(direction)


def _homography_poses(H: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    n, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
    out = []
    for R, t in zip(Rs, ts, strict=True):
        t = t.ravel()
        norm = np.linalg.norm(t)
        if norm > 1e-9:
            out.append((R, t / norm))
    return out


_CHI2_1DOF, _CHI2_2DOF = 3.841, 5.991  # 95% gates of one- and two-dimensional errors


def homography_score(H: np.ndarray, x1: np.ndarray, x2: np.ndarray, sigma: float) -> float:
    """ORB-SLAM's score of a homography: truncated chi-square of the transfer errors both ways."""
    score = 0.0
    for A, a, b in ((H, x1, x2), (np.linalg.inv(H), x2, x1)):
        p = np.column_stack([a, np.ones(len(a))]) @ A.T
        with np.errstate(divide="ignore", invalid="ignore"):
            chi = np.sum((p[:, :2] / p[:, 2:3] - b) ** 2, axis=1) / sigma**2
        chi = np.where(np.isfinite(chi), chi, np.inf)
        score += float(np.sum(np.where(chi < _CHI2_2DOF, _CHI2_2DOF - chi, 0.0)))
    return score


def essential_score(E: np.ndarray, x1: np.ndarray, x2: np.ndarray, sigma: float) -> float:
    """ORB-SLAM's score of an epipolar model: truncated chi-square of the point-to-epipolar-line
    distances both ways, on the same scale as `homography_score`."""
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    score = 0.0
    for lines, pts in ((h1 @ E.T, h2), (h2 @ E, h1)):
        num = np.sum(lines * pts, axis=1) ** 2
        chi = num / np.maximum(lines[:, 0] ** 2 + lines[:, 1] ** 2, 1e-300) / sigma**2
        score += float(np.sum(np.where(chi < _CHI2_1DOF, _CHI2_2DOF - chi, 0.0)))
    return score


def initialise_two_view(
    x1: np.ndarray, x2: np.ndarray, focal_px: float, config: InitConfig | None = None, seed: int = 0
) -> InitResult:
    """Estimate the relative pose from normalised matches x1, x2 (N,2) (undistorted, K^-1 applied);
    `seed` seeds OpenCV's RANSAC."""
    cfg = config or InitConfig()
    x1 = np.asarray(x1, np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, np.float64).reshape(-1, 2)
    if len(x1) != len(x2):
        raise ValueError(f"match arrays differ in length: {len(x1)} vs {len(x2)}")
    if len(x1) < max(8, cfg.min_inliers):
        return InitResult(False, f"only {len(x1)} matches (need {cfg.min_inliers})")
    thr = cfg.ransac_threshold_px / focal_px
    cv2.setRNGSeed(seed)
    E, mask_e = find_essential(x1, x2, np.eye(3), cv2.RANSAC, thr)
    # A transfer error has 2 DoF, an epipolar distance 1: widen the gate by sqrt(5.99 / 3.84).
    H, mask_h = cv2.findHomography(x1, x2, cv2.RANSAC, thr * np.sqrt(5.99 / 3.84))
    n_e = int(mask_e.sum()) if mask_e is not None else 0
    n_h = int(mask_h.sum()) if mask_h is not None else 0
    if max(n_e, n_h) < cfg.min_inliers:
        return InitResult(False, f"no model with {cfg.min_inliers} inliers (E: {n_e}, H: {n_h})")
    inl = (mask_e if n_e >= n_h else mask_h).ravel().astype(bool)
    R_rot, rot_err = rotation_between_rays(bearings(x1[inl]), bearings(x2[inl]))
    rot_median = float(np.median(rot_err))
    if rot_median < cfg.rotation_parallax_deg:
        return InitResult(
            False,
            f"a rotation explains the matches to {rot_median:.2f} deg: turned in place, no parallax",
            R_21=R_rot,
            inliers=int(inl.sum()),
            rotation_only=True,
        )
    sigma = 1.0 / focal_px
    s_e = essential_score(E[:3], x1, x2, sigma) if E is not None and n_e >= cfg.min_inliers else 0.0
    s_h = homography_score(H, x1, x2, sigma) if H is not None and n_h >= cfg.min_inliers else 0.0
    use_h = s_h / max(s_e + s_h, 1e-300) > cfg.homography_score_ratio
    candidates: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    if use_h:
        mh = mask_h.ravel().astype(bool)
        candidates = [("homography", R, t, mh) for R, t in _homography_poses(H)]
    elif s_e > 0:
        R1, R2, t = cv2.decomposeEssentialMat(E[:3])
        me = mask_e.ravel().astype(bool)
        candidates = [("essential", R, s * t.ravel(), me) for R in (R1, R2) for s in (1, -1)]
    if not candidates:
        return InitResult(False, f"no usable model (E score {s_e:.0f}, H score {s_h:.0f})")
    scored = [(_check_pose(R, t, x1, x2, m, cfg), name, R, t) for name, R, t, m in candidates]
    scored.sort(key=lambda s: -s[0][0])
    (n_good, good, X, median), name, R, t = scored[0]
    # Ambiguity: a different hypothesis explaining almost as many points means the geometry is weak.
    for (n_other, *_), _, R_other, _ in scored[1:]:
        if n_other > 0.7 * n_good and rotation_angle_deg(R_other, R) > cfg.ambiguity_deg:
            return InitResult(False, "two pose hypotheses explain the matches equally well (low parallax)")
    if name == "essential":
        # Inliers gated around the minimal-sample model are biased towards it: refine, re-gate, repeat.
        for _ in range(3):
            R, t = refine_relative_pose(R, t, x1[good], x2[good], thr)
            gate = np.abs(sampson_errors(R, t, x1, x2)) < thr
            n_good, good, X, median = _check_pose(R, t, x1, x2, gate, cfg)
    par = parallax_deg(R, t, X[good]) if good.any() else np.zeros(0)
    rot_std, dir_std = relative_pose_std(R, t, x1[good], x2[good], 1.0 / focal_px)
    result = InitResult(
        ok=False,
        strong_points=int((par >= cfg.strong_parallax_deg).sum()),
        reason="",
        R_21=R,
        t_21=t,
        points_1=X[good],
        point_index=np.flatnonzero(good),
        model=name,
        inliers=n_e if name == "essential" else n_h,
        median_parallax_deg=median,
        rotation_std_deg=rot_std,
        direction_std_deg=dir_std,
    )
    fixed = f"rotation {rot_std:.2f} deg, translation direction {dir_std:.1f} deg (1 sigma)"
    if median < cfg.min_parallax_deg:
        result.reason = f"median parallax {median:.2f} deg < {cfg.min_parallax_deg} deg: baseline too short"
    elif n_good < cfg.min_triangulated:
        result.reason = f"only {n_good} points triangulated in front of both views"
    elif rot_std > cfg.max_rotation_std_deg:
        result.reason = f"{name}: relative pose not fixed by its {n_good} points: {fixed}"
    else:
        result.ok = True
        result.reason = f"{name}: {n_good} points, median parallax {median:.2f} deg, {fixed}"
    log.debug("two-view init: %s", result.reason)
    return result
