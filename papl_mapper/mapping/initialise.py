"""Two-view initialisation: relative pose and first points from matched normalised coordinates.

Both an essential matrix and a homography are fitted with RANSAC; the homography is chosen when
it explains nearly as many matches (planar or low-parallax scenes, as ORB-SLAM does). The
result is accepted only with enough parallax and enough points triangulated in front of both
cameras; otherwise `ok` is False and `reason` says why, so the caller can try a later frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """Thresholds of the two-view initialisation."""

    ransac_threshold_px: float = 1.5
    """RANSAC inlier threshold in pixels (converted to normalised units with the focal length)."""
    min_inliers: int = 60
    """Fewest RANSAC inliers for a usable model."""
    min_parallax_deg: float = 1.5
    """Median parallax angle of triangulated points below which the baseline is too short."""
    min_triangulated: int = 50
    """Fewest points in front of both cameras with good parallax."""
    homography_ratio: float = 0.85
    """Prefer the homography when its inliers reach this fraction of the essential matrix's."""
    seed: int = 0
    """Seed for OpenCV's RANSAC."""


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


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def sampson_errors(R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) first-order geometric (Sampson) distances of normalised matches to E = [t]x R."""
    E = _skew(t_21) @ R_21
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.sum(h2 * Ex1, axis=1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-300))


def refine_relative_pose(
    R_21: np.ndarray, t_21: np.ndarray, x1: np.ndarray, x2: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the robust Sampson error over (R, unit t): 5 DoF, Huber at `scale` (normalised units)."""
    t0 = t_21 / np.linalg.norm(t_21)
    basis = np.linalg.svd(t0.reshape(1, 3))[2][1:]  # (2, 3) tangent of the unit sphere at t0

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = cv2.Rodrigues(p[:3])[0] @ R_21
        t = t0 + p[3:] @ basis
        return R, t / np.linalg.norm(t)

    sol = least_squares(
        lambda p: sampson_errors(*unpack(p), x1, x2), np.zeros(5), loss="huber", f_scale=scale
    )
    return unpack(sol.x)


def _homography_poses(H: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    n, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
    out = []
    for R, t in zip(Rs, ts, strict=True):
        t = t.ravel()
        norm = np.linalg.norm(t)
        if norm > 1e-9:
            out.append((R, t / norm))
    return out


def initialise_two_view(
    x1: np.ndarray, x2: np.ndarray, focal_px: float, config: InitConfig | None = None
) -> InitResult:
    """Estimate the relative pose from normalised matches x1, x2 (N,2) (undistorted, K^-1 applied)."""
    cfg = config or InitConfig()
    x1 = np.asarray(x1, np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, np.float64).reshape(-1, 2)
    if len(x1) != len(x2):
        raise ValueError(f"match arrays differ in length: {len(x1)} vs {len(x2)}")
    if len(x1) < max(8, cfg.min_inliers):
        return InitResult(False, f"only {len(x1)} matches (need {cfg.min_inliers})")
    thr = cfg.ransac_threshold_px / focal_px
    cv2.setRNGSeed(cfg.seed)
    E, mask_e = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.RANSAC, 0.999, thr)
    # A transfer error has 2 DoF, an epipolar distance 1: widen the gate by sqrt(5.99 / 3.84).
    H, mask_h = cv2.findHomography(x1, x2, cv2.RANSAC, thr * np.sqrt(5.99 / 3.84))
    n_e = int(mask_e.sum()) if mask_e is not None else 0
    n_h = int(mask_h.sum()) if mask_h is not None else 0
    candidates: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    if E is not None and n_e >= cfg.min_inliers:
        E = E[:3]
        R1, R2, t = cv2.decomposeEssentialMat(E)
        me = mask_e.ravel().astype(bool)
        for R in (R1, R2):
            for s in (1, -1):
                candidates.append(("essential", R, s * t.ravel(), me))
    if H is not None and n_h >= cfg.min_inliers and n_h >= cfg.homography_ratio * n_e:
        mh = mask_h.ravel().astype(bool)
        candidates = [("homography", R, t, mh) for R, t in _homography_poses(H)] + candidates
    if not candidates:
        return InitResult(False, f"no model with {cfg.min_inliers} inliers (E: {n_e}, H: {n_h})")
    scored = [(_check_pose(R, t, x1, x2, m, cfg), name, R, t) for name, R, t, m in candidates]
    scored.sort(key=lambda s: -s[0][0])
    (n_good, good, X, median), name, R, t = scored[0]
    # Ambiguity: a second hypothesis explaining almost as many points means the geometry is weak.
    if len(scored) > 1 and scored[1][0][0] > 0.7 * n_good and not np.allclose(scored[1][2], R, atol=1e-3):
        return InitResult(False, "two pose hypotheses explain the matches equally well (low parallax)")
    if name == "essential":
        # Inliers gated around the minimal-sample model are biased towards it: refine, re-gate, repeat.
        for _ in range(3):
            R, t = refine_relative_pose(R, t, x1[good], x2[good], thr)
            gate = np.abs(sampson_errors(R, t, x1, x2)) < thr
            n_good, good, X, median = _check_pose(R, t, x1, x2, gate, cfg)
    result = InitResult(
        ok=False,
        reason="",
        R_21=R,
        t_21=t,
        points_1=X[good],
        point_index=np.flatnonzero(good),
        model=name,
        inliers=n_e if name == "essential" else n_h,
        median_parallax_deg=median,
    )
    if median < cfg.min_parallax_deg:
        result.reason = f"median parallax {median:.2f} deg < {cfg.min_parallax_deg} deg: baseline too short"
    elif n_good < cfg.min_triangulated:
        result.reason = f"only {n_good} points triangulated in front of both views"
    else:
        result.ok = True
        result.reason = f"{name}: {n_good} points, median parallax {median:.2f} deg"
    log.debug("two-view init: %s", result.reason)
    return result
