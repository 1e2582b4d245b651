"""Refine one camera pose against the map: points, line segments and vanishing directions.

The PnP pose (points only) drifts in rotation where the points are few or bunched; the lines and
the vanishing directions seen in the frame fix it (paper: tracking with point and line reprojection
and the structural rotation constraint). Cost, with robust Huber weights on each term:

- point reprojection error (px) of every map point seen in the frame;
- the two endpoint-to-line distances (px) of every observed segment to its projected map line;
- for each vanishing direction d_c matched to a world direction d_w, the sign-free deviation of
  R_cw d_w from d_c, two components in the tangent plane of d_c (radians, ~ the angle).

Levenberg-Marquardt on the 6-dof pose with a LEFT perturbation of the world-to-camera pose:
T_cw' = Exp(xi) @ T_cw, xi = (omega, nu), Exp as in geometry.se3 (rotation first). Left on T_cw is
the camera-frame perturbation, so every Jacobian is a function of camera-frame quantities only.

World directions: after the run, the map's axes (`FrameRefiner.from_map`); during registration,
when there are no axes yet, greedy sign-free clusters of R_wc v_c over the registered keyframes
(`RegistrationDirections`). Each direction weighs by the robust spread of its vanishing points
(sigma >= `direction_sigma_deg`; left out above `max_direction_spread_deg`).

Call sites (`track_pnp` takes the extra terms as keywords; without them it is unchanged):
(a) registration, `incremental._pnp`, when `cfg.pnp.refine.in_registration`:
    `dirs_w, sigma = reg_dirs(reg.T_cw)` with one
    `reg_dirs = RegistrationDirections(tracks)` per run, then `track_pnp(..., dirs_w=dirs_w,
    dirs_c=frame_directions(tracks, f), dirs_sigma_deg=sigma)`;
(b) all-frames trajectory, `mapping.frames.frame_poses`: `refiner = FrameRefiner.from_map(tracks, m,
    pnp.refine)` before the loop, then after a successful PnP
    `T_cw, _ = refiner.refine(f, res.T_cw, X[res.inliers], uv[res.inliers])`;
(c) `tracking.pose_from_lines`, for frames with too few points: lines and directions always on, and
    `pose_std` to accept the result only where its terms fix it.
benchmarks/pose_refine.py monkeypatches both exactly so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from papl_mapper.geometry.lines import (
    endpoint_errors,
    plucker_from_endpoints,
    plucker_to_camera,
    projected_line_norm,
    tangent_basis,
)
from papl_mapper.geometry.se3 import invert, retract, skew
from papl_mapper.map import Map
from papl_mapper.tracks import Tracks


@dataclass
class PoseRefineConfig:
    """Which terms refine a tracked pose and how much each one weighs."""

    enabled: bool = True
    """Refine the PnP pose at all (False keeps OpenCV's points-only LM pose)."""
    lines: bool = False
    """Add the endpoint-to-line distances of map lines seen in the frame. Off: no gain in the trajectory
    (benchmarks/RESULTS.md); `mapping.track_lines` turns it on for registration."""
    directions: bool = True
    """Add the rotation term of vanishing directions matched to world directions."""
    directions_below_inliers: int = 100
    """Use the directions only for poses with fewer PnP inliers than this, where points are weak (0:
    always): always on, the frontend's VP noise pulls well-held poses (benchmarks/RESULTS.md)."""
    directions_above_rotation_std_deg: float = 0.0
    """Use the directions only where the points-only rotation is this uncertain (1-sigma, from the
    Gauss-Newton normal matrix at `point_sigma_px`; 0: always)."""
    in_registration: bool = True
    """Also use the directions while frames are registered (world directions from the keyframes so
    far, `RegistrationDirections`); it helps where points are weak (benchmarks/RESULTS.md)."""
    point_sigma_px: float = 1.0
    """Standard deviation of a point's reprojection error."""
    line_sigma_px: float = 1.0
    """Standard deviation of an endpoint's distance to its projected line."""
    direction_sigma_deg: float = 1.0
    """Standard deviation of the angle between a vanishing direction and its world direction (the
    smallest one: a direction whose vanishing points scatter more gets its own, larger sigma)."""
    huber: float = 2.0
    """Huber threshold in units of each term's sigma (errors beyond it count linearly)."""
    max_direction_spread_deg: float = 1.0
    """Directions whose vanishing points scatter more than this (their sigma) are left out: consistent
    directions scatter less, mixed ones more (benchmarks/RESULTS.md)."""
    vertical_only: bool = False
    """Use only the vertical vanishing direction (the frame's `vertical_vp`, the map's vertical axis)."""
    match_direction_deg: float = 3.0
    """A camera vanishing direction matches the nearest world direction within this angle."""
    min_line_norm: float = 1e-3
    """Lines whose image is this close to degenerate (through the camera centre) are left out."""
    lines_below_inliers: int = 0
    """Use the lines only for poses with fewer PnP inliers than this (0: always; `track_pnp`)."""
    line_gate_px: float = 0.0
    """Lines with an observed endpoint farther than this from their projection under the initial pose
    are left out (a wrong track or a badly triangulated line; 0 keeps every line)."""
    iterations: int = 10
    """Most Levenberg-Marquardt iterations."""
    step_tol: float = 1e-8
    """Stop when the update is smaller than this (radians / map units)..."""
    cost_tol: float = 1e-6
    """...or when a step lowers the cost by less than this fraction."""


@dataclass
class RefineStats:
    """What one refinement did: counts of terms, costs, iterations and final errors."""

    n_points: int = 0
    n_lines: int = 0
    n_directions: int = 0
    iterations: int = 0
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    point_rms_px: float = float("nan")
    line_rms_px: float = float("nan")
    direction_rms_deg: float = float("nan")
    rotation_change_deg: float = 0.0
    point_errors_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _huber_weights(e: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss for normalised error norms e."""
    return np.where(e <= k, 1.0, k / np.maximum(e, k))  # (the max only keeps the unused branch finite)


def _huber_cost(e: np.ndarray, k: float) -> float:
    return float(np.sum(np.where(e <= k, 0.5 * e**2, k * (e - 0.5 * k))))


# ---- residuals and Jacobians (left perturbation of T_cw) -------------------------------------------


def point_residuals(
    T_cw: np.ndarray, points_w: np.ndarray, uv: np.ndarray, K: np.ndarray, jacobian: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reprojection errors (N, 2) px of points (N, 3) seen at uv (N, 2); with `jacobian` also
    d r / d xi (N, 2, 6) and the camera depths (N,)."""
    X_c = points_w @ T_cw[:3, :3].T + T_cw[:3, 3]  # (N, 3)
    z = X_c[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    fx, fy = K[0, 0], K[1, 1]
    proj = np.stack([fx * X_c[:, 0] / zs + K[0, 2], fy * X_c[:, 1] / zs + K[1, 2]], -1)
    r = proj - uv
    if not jacobian:
        return r
    J_proj = np.zeros((len(z), 2, 3))
    J_proj[:, 0, 0] = fx / zs
    J_proj[:, 0, 2] = -fx * X_c[:, 0] / zs**2
    J_proj[:, 1, 1] = fy / zs
    J_proj[:, 1, 2] = -fy * X_c[:, 1] / zs**2
    J_pert = np.concatenate([-skew(X_c), np.broadcast_to(np.eye(3), (len(z), 3, 3))], -1)  # (N, 3, 6)
    return r, J_proj @ J_pert, z


def line_residuals(
    T_cw: np.ndarray, L_w: np.ndarray, line_xy: np.ndarray, K: np.ndarray, jacobian: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Signed distances (M, 2) px of observed endpoints (M, 4) to the projected world lines L_w (M, 6);
    with `jacobian` also d r / d xi (M, 2, 6)."""
    L_c = plucker_to_camera(L_w, invert(T_cw))
    if not jacobian:
        return endpoint_errors(K, L_c, line_xy)
    e, J_L = endpoint_errors(K, L_c, line_xy, jacobian=True)  # (M, 2), (M, 2, 6)
    n_c, v_c = L_c[:, :3], L_c[:, 3:]
    # n' = R_d n + nu x (R_d v), v' = R_d v  ->  dn/domega = -[n]x, dn/dnu = -[v]x, dv/domega = -[v]x
    J_pert = np.zeros((len(L_c), 6, 6))
    J_pert[:, :3, :3] = -skew(n_c)
    J_pert[:, :3, 3:] = -skew(v_c)
    J_pert[:, 3:, :3] = -skew(v_c)
    return e, J_L @ J_pert


def direction_residuals(
    T_cw: np.ndarray, dirs_w: np.ndarray, dirs_c: np.ndarray, jacobian: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Sign-free deviation (D, 2) (radians to first order) of R_cw d_w from the observed d_c, in the
    tangent plane of d_c; with `jacobian` also d r / d xi (D, 2, 6) (zero in the translation block)."""
    p = dirs_w @ T_cw[:3, :3].T  # (D, 3) predicted camera directions
    p /= np.linalg.norm(p, axis=-1, keepdims=True)
    d = dirs_c / np.linalg.norm(dirs_c, axis=-1, keepdims=True)
    s = np.where(np.sum(p * d, -1) >= 0, 1.0, -1.0)[:, None]  # a line direction has no sign
    B = tangent_basis(d)  # (D, 3, 2)
    r = s * np.einsum("dik,di->dk", B, p)
    if not jacobian:
        return r
    J = np.zeros((len(p), 2, 6))
    J[:, :, :3] = s[:, :, None] * (np.swapaxes(B, -1, -2) @ -skew(p))
    return r, J


# ---- the optimiser ----------------------------------------------------------------------------------


@dataclass
class _Problem:
    K: np.ndarray
    points_w: np.ndarray
    uv: np.ndarray
    L_w: np.ndarray
    line_xy: np.ndarray
    dirs_w: np.ndarray
    dirs_c: np.ndarray
    dirs_sigma_rad: np.ndarray  # (D,)
    cfg: PoseRefineConfig

    def blocks(
        self, T_cw: np.ndarray, jacobian: bool = True
    ) -> list[tuple[np.ndarray, np.ndarray | None, float | np.ndarray]]:
        """(residual (n, k), Jacobian (n, k, 6) or None, sigma or (n,) sigmas) per term; one robust
        term per row."""
        out: list[tuple[np.ndarray, np.ndarray | None, float | np.ndarray]] = []
        if len(self.points_w):
            res = point_residuals(T_cw, self.points_w, self.uv, self.K, jacobian)
            r, J = res[:2] if jacobian else (res, None)
            out.append((r, J, self.cfg.point_sigma_px))
        if len(self.L_w):
            res = line_residuals(T_cw, self.L_w, self.line_xy, self.K, jacobian)
            r, J = res if jacobian else (res, None)
            # each endpoint distance is its own robust term: (M, 2) -> (2M, 1)
            out.append((r.reshape(-1, 1), None if J is None else J.reshape(-1, 1, 6), self.cfg.line_sigma_px))
        if len(self.dirs_w):
            res = direction_residuals(T_cw, self.dirs_w, self.dirs_c, jacobian)
            r, J = res if jacobian else (res, None)
            out.append((r, J, self.dirs_sigma_rad))
        return out

    def cost(self, T_cw: np.ndarray) -> float:
        k = self.cfg.huber
        return sum(_huber_cost(np.linalg.norm(r, axis=-1) / s, k) for r, _, s in self.blocks(T_cw, False))

    def normal_equations(self, T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        H = np.zeros((6, 6))
        g = np.zeros(6)
        cost = 0.0
        k = self.cfg.huber
        for r, J, s in self.blocks(T_cw):
            e = np.linalg.norm(r, axis=-1) / s
            cost += _huber_cost(e, k)
            w = _huber_weights(e, k) / s**2  # (n,)
            Jf = J.reshape(-1, 6)  # (n k, 6)
            Wj = (J * w[:, None, None]).reshape(-1, 6)
            H += Wj.T @ Jf
            g += Wj.T @ r.reshape(-1)
        return H, g, cost


def points_rotation_std_deg(
    T_cw: np.ndarray, points_w: np.ndarray, uv: np.ndarray, K: np.ndarray, sigma_px: float
) -> float:
    """Largest 1-sigma rotation uncertainty (deg) of a pose from its points alone (Gauss-Newton
    covariance sigma^2 (J^T J)^-1, rotation block); inf when the points do not fix the pose."""
    if len(points_w) < 3:
        return float("inf")
    _, J, _ = point_residuals(T_cw, points_w, uv, K, jacobian=True)
    Jf = J.reshape(-1, 6)
    try:
        cov = np.linalg.inv(Jf.T @ Jf) * sigma_px**2
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))))


def pose_std(
    T_cw: np.ndarray,
    points_w: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    *,
    lines_w: np.ndarray | None = None,
    line_xy: np.ndarray | None = None,
    dirs_w: np.ndarray | None = None,
    dirs_c: np.ndarray | None = None,
    config: PoseRefineConfig | None = None,
) -> tuple[float, float]:
    """Largest 1-sigma rotation (deg) and camera-centre (world units) uncertainty of a pose from all its
    terms (Gauss-Newton covariance of the robust cost, each term at its config sigma); inf, inf when
    the terms do not fix the pose. The centre moves by -R^T nu under the left perturbation, so its
    covariance is the nu block's."""
    cfg = config or PoseRefineConfig()
    L_w = _as_plucker(lines_w) if lines_w is not None and len(lines_w) else np.zeros((0, 6))
    xy = np.asarray(line_xy, np.float64).reshape(-1, 4) if len(L_w) else np.zeros((0, 4))
    d_w = np.asarray(dirs_w, np.float64).reshape(-1, 3) if dirs_w is not None else np.zeros((0, 3))
    d_c = np.asarray(dirs_c, np.float64).reshape(-1, 3) if dirs_c is not None else np.zeros((0, 3))
    prob = _Problem(
        K,
        np.asarray(points_w, np.float64).reshape(-1, 3),
        np.asarray(uv, np.float64).reshape(-1, 2),
        L_w,
        xy,
        d_w,
        d_c,
        np.full(len(d_w), np.radians(cfg.direction_sigma_deg)),
        cfg,
    )
    H, _, _ = prob.normal_equations(np.asarray(T_cw, np.float64))
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    if not np.isfinite(cov).all() or np.linalg.cond(H) > 1e14:
        return float("inf"), float("inf")
    rot = np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    centre = np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))
    return float(rot), float(centre)


def _as_plucker(lines_w: np.ndarray) -> np.ndarray:
    lines_w = np.asarray(lines_w, np.float64)
    if lines_w.shape[-2:] == (2, 3):
        return plucker_from_endpoints(lines_w[:, 0], lines_w[:, 1])
    return lines_w.reshape(-1, 6)


def refine_pose(
    T_cw: np.ndarray,
    points_w: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    *,
    lines_w: np.ndarray | None = None,
    line_xy: np.ndarray | None = None,
    dirs_w: np.ndarray | None = None,
    dirs_c: np.ndarray | None = None,
    dirs_sigma_deg: np.ndarray | None = None,
    config: PoseRefineConfig | None = None,
) -> tuple[np.ndarray, RefineStats]:
    """Refine a world-to-camera pose by robust LM on points (N,3)/(N,2) px, lines (M,2,3) world endpoints
    or (M,6) Pluecker with observed segments (M,4) px, and matched directions d_w (D,3) / d_c (D,3).

    `dirs_sigma_deg` (D,) are per-direction sigmas (at least the config's; NaN = the config's).
    Returns the refined T_cw and the statistics; the input pose comes back when nothing improves it.
    """
    cfg = config or PoseRefineConfig()
    T0 = np.asarray(T_cw, np.float64)
    points_w = np.asarray(points_w, np.float64).reshape(-1, 3)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if cfg.lines and lines_w is not None and line_xy is not None and len(lines_w):
        L_w = _as_plucker(lines_w)
        line_xy = np.asarray(line_xy, np.float64).reshape(-1, 4)
        L_c = plucker_to_camera(L_w, invert(T0))
        keep = projected_line_norm(K, L_c) > cfg.min_line_norm
        if cfg.line_gate_px > 0:
            with np.errstate(invalid="ignore"):
                keep &= np.abs(endpoint_errors(K, L_c, line_xy)).max(axis=1) <= cfg.line_gate_px
        L_w, line_xy = L_w[keep], line_xy[keep]
    else:
        L_w, line_xy = np.zeros((0, 6)), np.zeros((0, 4))
    if cfg.directions and dirs_w is not None and dirs_c is not None and len(dirs_w):
        dirs_w = np.asarray(dirs_w, np.float64).reshape(-1, 3)
        dirs_c = np.asarray(dirs_c, np.float64).reshape(-1, 3)
    else:
        dirs_w, dirs_c = np.zeros((0, 3)), np.zeros((0, 3))
    sig = np.full(len(dirs_w), cfg.direction_sigma_deg)
    if dirs_sigma_deg is not None and len(dirs_w):
        spread = np.asarray(dirs_sigma_deg, np.float64).reshape(-1)
        keep = ~(spread > cfg.max_direction_spread_deg)  # NaN (unknown spread) is kept
        dirs_w, dirs_c, sig = dirs_w[keep], dirs_c[keep], np.fmax(sig[keep], spread[keep])
    prob = _Problem(K, points_w, uv, L_w, line_xy, dirs_w, dirs_c, np.radians(sig), cfg)
    stats = RefineStats(n_points=len(points_w), n_lines=len(L_w), n_directions=len(dirs_w))
    T = T0.copy()
    if len(points_w) + len(L_w) + len(dirs_w) == 0:
        return T, _final_stats(prob, T, T0, stats)
    H, g, cost = prob.normal_equations(T)
    stats.cost_initial = cost
    lam = 1e-4  # Marquardt: relative to the diagonal of H
    for it in range(cfg.iterations):
        stats.iterations = it + 1
        try:
            xi = np.linalg.solve(H + lam * np.diag(np.maximum(np.diag(H), 1e-12)), -g)
        except np.linalg.LinAlgError:
            break
        T_new = _left_retract(T, xi)
        new_cost = prob.cost(T_new)
        if new_cost < cost:
            T, lam = T_new, lam / 10.0
            small = np.linalg.norm(xi) < cfg.step_tol or cost - new_cost < cfg.cost_tol * cost
            if small:
                break
            H, g, cost = prob.normal_equations(T)
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    return T, _final_stats(prob, T, T0, stats)


def _left_retract(T_cw: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Exp(xi) @ T_cw."""
    return retract(np.eye(4), xi) @ T_cw


def _final_stats(prob: _Problem, T: np.ndarray, T0: np.ndarray, stats: RefineStats) -> RefineStats:
    stats.cost_final = prob.cost(T)
    if len(prob.points_w):
        e = np.linalg.norm(point_residuals(T, prob.points_w, prob.uv, prob.K), axis=-1)
        stats.point_errors_px = e
        stats.point_rms_px = float(np.sqrt(np.mean(e**2)))
    if len(prob.L_w):
        stats.line_rms_px = float(np.sqrt(np.mean(line_residuals(T, prob.L_w, prob.line_xy, prob.K) ** 2)))
    if len(prob.dirs_w):
        r = direction_residuals(T, prob.dirs_w, prob.dirs_c)
        stats.direction_rms_deg = float(np.degrees(np.sqrt(np.mean(np.sum(r**2, -1)))))
    dR = T[:3, :3] @ T0[:3, :3].T
    stats.rotation_change_deg = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return stats


# ---- vanishing directions: matching and world directions from registered keyframes ---------------


def match_directions(
    R_cw: np.ndarray, dirs_w: np.ndarray, dirs_c: np.ndarray, max_angle_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (world, camera) of directions whose sign-free angle under R_cw is the smallest for both
    and under `max_angle_deg`; camera rows that are NaN are skipped. Returns the matched world
    directions (D, 3), camera directions (D, 3) and the rows of the world ones in dirs_w (D,)."""
    dirs_c = np.asarray(dirs_c, np.float64).reshape(-1, 3)
    dirs_w = np.asarray(dirs_w, np.float64).reshape(-1, 3)
    dirs_c = dirs_c[np.isfinite(dirs_c).all(-1)]
    if not len(dirs_c) or not len(dirs_w):
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    dirs_c = dirs_c / np.linalg.norm(dirs_c, axis=-1, keepdims=True)
    cos = np.abs(dirs_c @ (dirs_w @ R_cw.T).T)  # (C, W)
    best_w = np.argmax(cos, 1)
    best_c = np.argmax(cos, 0)
    ok = (best_c[best_w] == np.arange(len(dirs_c))) & (
        cos[np.arange(len(dirs_c)), best_w] >= np.cos(np.radians(max_angle_deg))
    )
    return dirs_w[best_w[ok]], dirs_c[ok], best_w[ok]


def _rotated_directions(R_wc: np.ndarray, dirs_c: np.ndarray) -> np.ndarray:
    """(n, 3) unit world directions of the finite camera directions dirs_c (N, V, 3) under R_wc (N, 3, 3)."""
    d = np.einsum("nij,nvj->nvi", np.asarray(R_wc, np.float64), np.asarray(dirs_c, np.float64)).reshape(-1, 3)
    d = d[np.isfinite(d).all(-1)]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# median of a Rayleigh distribution (the angle of a 2D isotropic Gaussian deviation) / its sigma
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))


def _spread_deg(d: np.ndarray, axis: np.ndarray) -> float:
    """Robust per-direction sigma (deg) of the unit directions d (n, 3) around a sign-free axis."""
    ang = np.degrees(np.arccos(np.clip(np.abs(d @ axis), 0.0, 1.0)))
    return float(np.median(ang) / _RAYLEIGH_MEDIAN) if len(ang) else float("nan")


def direction_spread_deg(
    dirs_w: np.ndarray, R_wc: np.ndarray, dirs_c: np.ndarray, max_angle_deg: float = 3.0
) -> np.ndarray:
    """Robust sigma (A,) in degrees of the camera vanishing directions dirs_c (N, V, 3) of frames with
    rotations R_wc (N, 3, 3) around each world direction dirs_w (A, 3), over those within
    `max_angle_deg` (NaN for a direction no frame sees)."""
    d = _rotated_directions(R_wc, dirs_c)
    cos_thr = np.cos(np.radians(max_angle_deg))
    out = np.full(len(dirs_w), np.nan)
    for a, axis in enumerate(np.asarray(dirs_w, np.float64).reshape(-1, 3)):
        out[a] = _spread_deg(d[np.abs(d @ axis) >= cos_thr], axis)
    return out


def world_directions(
    R_wc: np.ndarray, dirs_c: np.ndarray, max_angle_deg: float = 3.0, min_support: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Principal world directions (A, 3) from camera vanishing directions dirs_c (N, V, 3) (NaN where
    absent) of N registered frames with rotations R_wc (N, 3, 3): greedy sign-free clusters of the
    rotated directions, each the dominant eigenvector of its members within `max_angle_deg`, largest
    cluster first; clusters with fewer than `min_support` members are dropped. Also returns each
    direction's robust spread (A,) in degrees (see `direction_spread_deg`)."""
    d = _rotated_directions(R_wc, dirs_c)
    if not len(d):
        return np.zeros((0, 3)), np.zeros(0)
    cos_thr = np.cos(np.radians(max_angle_deg))
    near = np.abs(d @ d.T) >= cos_thr  # (n, n)
    alive = np.ones(len(d), bool)
    out, spread = [], []
    while alive.any():
        support = (near & alive[None, :]).sum(1) * alive
        i = int(np.argmax(support))
        if support[i] < min_support:
            break
        axis = d[i]
        for _ in range(3):  # re-centre: members around the current mean, then their dominant direction
            members = alive & (np.abs(d @ axis) >= cos_thr)
            m = d[members]
            axis = np.linalg.eigh(m.T @ m)[1][:, -1]
        members = alive & (np.abs(d @ axis) >= cos_thr)
        if members.sum() < min_support:
            alive[i] = False
            continue
        out.append(axis)
        spread.append(_spread_deg(d[members], axis))
        alive &= ~members
    return np.array(out).reshape(-1, 3), np.array(spread)


class FrameRefiner:
    """Refines tracked poses of frames of one recording against fixed world lines and directions.

    Built once per map (lines by track id, world directions); `refine(f, T_cw, points_w, uv)` adds the
    segments and vanishing directions that frame f observes to the given point correspondences.
    """

    def __init__(
        self,
        tracks: Tracks,
        line_ids: np.ndarray | None = None,
        lines_w: np.ndarray | None = None,
        dirs_w: np.ndarray | None = None,
        config: PoseRefineConfig | None = None,
        dirs_sigma_deg: np.ndarray | None = None,
    ) -> None:
        self.tracks = tracks
        self.K = tracks.camera.K
        self.cfg = config or PoseRefineConfig()
        ids = np.zeros(0, np.int64) if line_ids is None else np.asarray(line_ids, np.int64)
        order = np.argsort(ids)
        self.line_ids = ids[order]
        self.lines_w = np.zeros((0, 6)) if lines_w is None else _as_plucker(lines_w)[order]
        self.dirs_w = np.zeros((0, 3)) if dirs_w is None else np.asarray(dirs_w, np.float64).reshape(-1, 3)
        self.dirs_sigma_deg = (
            np.full(len(self.dirs_w), np.nan) if dirs_sigma_deg is None else np.asarray(dirs_sigma_deg, float)
        )
        rows = np.argsort(tracks.line_frame, kind="stable")
        self._line_rows = np.split(rows, np.searchsorted(tracks.line_frame[rows], np.arange(1, len(tracks))))

    @classmethod
    def from_map(cls, tracks: Tracks, m: Map, config: PoseRefineConfig | None = None) -> FrameRefiner:
        """Lines (ids = line track ids) and axis directions of a finished map; each axis's sigma is the
        spread of the keyframes' vanishing directions around it (keyframe ids are frame rows)."""
        cfg = config or PoseRefineConfig()
        dirs = m.axes.directions
        if cfg.vertical_only:
            dirs = dirs[[m.axes.vertical_index]] if m.axes.vertical_index >= 0 else np.zeros((0, 3))
        kf = np.asarray(m.keyframes.ids, np.int64)
        inside = (kf >= 0) & (kf < len(tracks))
        vp = (
            np.stack([frame_directions(tracks, int(f), cfg.vertical_only) for f in kf[inside]])
            if inside.any()
            else None
        )
        spread = (
            direction_spread_deg(dirs, m.keyframes.T_wc[inside, :3, :3], vp, cfg.match_direction_deg)
            if vp is not None and vp.ndim == 3
            else None
        )
        return cls(tracks, m.lines.ids, m.lines.endpoints_w, dirs, cfg, spread)

    def frame_lines(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """World Pluecker lines (M, 6) and observed segments (M, 4) of the map lines seen in frame f."""
        rows = self._line_rows[f]
        if not len(rows) or not len(self.line_ids):
            return np.zeros((0, 6)), np.zeros((0, 4))
        tid = self.tracks.line_track[rows]
        idx = np.minimum(np.searchsorted(self.line_ids, tid), len(self.line_ids) - 1)
        known = self.line_ids[idx] == tid
        return self.lines_w[idx[known]], self.tracks.line_xy[rows[known]]

    def refine(
        self, f: int, T_cw: np.ndarray, points_w: np.ndarray, uv: np.ndarray
    ) -> tuple[np.ndarray, RefineStats]:
        """Refined T_cw of frame f from its point correspondences plus the frame's lines and directions."""
        if not self.cfg.enabled:
            return T_cw, RefineStats(n_points=len(points_w))
        L_w, xy = self.frame_lines(f) if self.cfg.lines else (None, None)
        d_w, d_c, sig = None, None, None
        if self.cfg.directions:
            vp_c = frame_directions(self.tracks, f, self.cfg.vertical_only)
            d_w, d_c, idx = match_directions(T_cw[:3, :3], self.dirs_w, vp_c, self.cfg.match_direction_deg)
            sig = self.dirs_sigma_deg[idx]
        return refine_pose(
            T_cw,
            points_w,
            uv,
            self.K,
            lines_w=L_w,
            line_xy=xy,
            dirs_w=d_w,
            dirs_c=d_c,
            dirs_sigma_deg=sig,
            config=self.cfg,
        )


def frame_directions(tracks: Tracks, f: int, vertical_only: bool = False) -> np.ndarray:
    """Camera vanishing directions (V, 3) of frame f (NaN rows where absent), or only its vertical one."""
    if not vertical_only:
        return tracks.vp_dirs_c[f]
    v = int(tracks.vertical_vp[f]) if len(tracks.vertical_vp) else -1
    return tracks.vp_dirs_c[f, [v]] if v >= 0 else np.full((1, 3), np.nan)


def directions_from_poses(
    tracks: Tracks,
    T_cw: dict[int, np.ndarray],
    max_angle_deg: float = 3.0,
    min_support: int = 3,
    max_frames: int = 150,
    vertical_only: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """World directions (A, 3) and their spreads (A,) in degrees of the vanishing points of the frames
    registered so far (frame -> T_cw), for tracking while the map has no axes yet (`world_directions`);
    at most `max_frames` frames evenly spread over the registered ones are used (flat cost)."""
    frames = np.sort(np.fromiter(T_cw, np.int64, len(T_cw)))
    if not len(frames):
        return np.zeros((0, 3)), np.zeros(0)
    if len(frames) > max_frames:
        frames = frames[np.unique(np.linspace(0, len(frames) - 1, max_frames).round().astype(int))]
    R_wc = np.swapaxes(np.stack([T_cw[int(f)][:3, :3] for f in frames]), -1, -2)
    d_c = tracks.vp_dirs_c[frames]
    if vertical_only:
        v = tracks.vertical_vp[frames] if len(tracks.vertical_vp) else np.full(len(frames), -1)
        d_c = np.where((np.arange(d_c.shape[1])[None, :] == v[:, None])[..., None], d_c, np.nan)
    return world_directions(R_wc, d_c, max_angle_deg, min_support)


class RegistrationDirections:
    """World directions for tracking during registration, recomputed only when keyframes were added."""

    def __init__(
        self, tracks: Tracks, max_angle_deg: float = 3.0, min_support: int = 3, vertical_only: bool = False
    ) -> None:
        self.tracks = tracks
        self.vertical_only = vertical_only
        self.max_angle_deg = max_angle_deg
        self.min_support = min_support
        self._key: tuple[int, int] = (-1, -1)
        self._dirs = (np.zeros((0, 3)), np.zeros(0))

    def __call__(self, T_cw: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """World directions (A, 3) and spreads (A,) deg of the keyframes in T_cw (frame -> T_cw)."""
        key = (id(T_cw), len(T_cw))
        if key != self._key:
            self._dirs = directions_from_poses(
                self.tracks, T_cw, self.max_angle_deg, self.min_support, vertical_only=self.vertical_only
            )
            self._key = key
        return self._dirs
