"""Focal-length self-calibration of a finished map: is the focal length it was built with plausible?

A wrong focal length (no camera file, so a 60 deg field-of-view guess, or the file of another camera)
still gives a map, only a warped one. The bundle itself measures f where the walk turns: adjusting
poses, points and one shared focal length f (fx = fy = f, principal point held) moves f to the value the
image motion supports. A straight walk leaves f free (scaling f and the lateral coordinates of the scene
together changes no image); the check then says so instead of guessing.

A wrong f warps the whole trajectory (turns come out too wide or too narrow, drift piles up), and one
global adjustment from that start stops near the wrong f (benchmarks/results/notes.md). Short windows
of consecutive keyframes are nearly undistorted by that, so each window is adjusted alone and the
estimate is the median over the windows that pin f down.

The adjustment is a small Levenberg-Marquardt in numpy with the points eliminated (Schur complement),
not gtsam: gtsam's GeneralSFMFactor2 zeroes (and prints) every observation whose point falls behind
the camera during the iterations, which lets the optimiser lower the cost by pushing points behind.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from papl_mapper import geometry as geo
from papl_mapper.errors import GeometryError
from papl_mapper.map import Map
from papl_mapper.rows import unique_rows

log = logging.getLogger(__name__)

GAUGE_SIGMA = 1e-3
"""Sigma of the prior holding the gauge distance (first keyframe to the farthest), relative to it."""


@dataclass
class FocalCheckConfig:
    """Settings of the focal-length plausibility check run after mapping."""

    enabled: bool = True
    """Run the check (a few seconds: one small bundle adjustment per window)."""
    warn_ratio: float = 0.05
    """Warn when the estimated focal length differs from the used one by more than this fraction...
    (a few per cent of focal error already multiplies the trajectory error; maps made with the true f
    come out well within it: benchmarks/focal_check.py, results/focal_check.json)"""
    n_sigma: float = 3.0
    """... and by more than this many standard deviations of the estimate."""
    max_rel_sigma: float = 0.03
    """f counts as observable when its standard deviation is below this fraction of f (for one window
    and for the combined estimate)."""
    window_keyframes: int = 20
    """Consecutive keyframes adjusted together."""
    max_windows: int = 12
    """Windows used at most: the non-overlapping ones whose camera turns most (turns pin f down)."""
    max_points_per_window: int = 300
    """Points per window at most (those seen by the most keyframes of the window first)."""
    min_views: int = 3
    """Points seen from fewer keyframes of a window are left out (two views constrain f little)."""
    min_window_keyframes: int = 5
    """A window with fewer keyframes holding such points is skipped."""
    sigma_px: float = 1.0
    """Standard deviation of a point observation, pixels; the estimate's sigma is scaled by the
    residual level but never below this."""
    huber_k: float = 1.345
    """Huber threshold in standard deviations."""
    max_error_px: float = 8.0
    """Observations reprojecting further than this with the map's camera are left out as outliers."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per window at most (a window of a map built with a badly wrong f
    needs many; fewer left the demo's estimate short of the truth: benchmarks/results/notes.md)."""
    screen_factor: float = 2.0
    """A window whose f is already this many times less observable than max_rel_sigma at the map's
    solution is not adjusted: its geometry (how the camera turns) decides what it can pin down, and
    adjusting it would only creep along the flat direction up to max_iterations."""
    f_prior_rel_sigma: float = 0.3
    """A weak prior on f (this fraction of the used f, 1 sigma) keeps a window solvable when f is not
    observable there; it pulls an estimate of relative sigma s by about (s / this)^2 of the way."""


@dataclass
class WindowFit:
    """One window's adjustment with a free focal length (iterations 0: screened out, not adjusted)."""

    first_keyframe_id: int
    n_keyframes: int
    n_points: int
    n_observations: int
    rotation_deg: float
    """Largest rotation of a keyframe of the window from its first one."""
    f: float
    rel_sigma: float
    iterations: int
    rms_px: float


@dataclass
class FocalCheck:
    """Outcome of `check_focal`. `f_estimated` is NaN when no window could be adjusted."""

    f_used: float
    f_estimated: float
    ratio: float
    """f_estimated / f_used."""
    rel_sigma: float
    """Standard deviation of f_estimated as a fraction of it (from the windows' spread and their own
    sigmas; inf when not computed)."""
    observable: bool
    """The walk pins f down to max_rel_sigma or better."""
    plausible: bool
    """False when the used f is implausible (off by more than warn_ratio and n_sigma standard deviations,
    which a walk pinning f down less than max_rel_sigma can still show): the caller warns with `message`."""
    message: str
    hfov_used_deg: float
    hfov_estimated_deg: float
    n_windows: int = 0
    """Windows adjusted."""
    n_informative: int = 0
    """Windows whose own estimate of f is observable (the median runs over these)."""
    time_s: float = 0.0
    windows: list[WindowFit] = field(default_factory=list)

    @property
    def warn(self) -> bool:
        """The job should warn (log, summary, report)."""
        return not self.plausible

    def summary(self) -> dict[str, Any]:
        """Plain-JSON form for summary.json and the report (NaN and inf become None)."""

        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, list):
                return [clean(x) for x in v]
            return v

        return clean(asdict(self))


def hfov_deg(f: float, width: int) -> float:
    """Horizontal field of view (degrees) of a focal length f in pixels on an image `width` pixels wide."""
    return math.degrees(2.0 * math.atan(width / 2.0 / f)) if f > 0 else math.nan


def check_focal(m: Map, config: FocalCheckConfig | None = None, seed: int = 0) -> FocalCheck:
    """Estimate the focal length from the map's point bundle, window by window, and judge the used one
    (`seed` draws the point subsample of a window with too many points)."""
    config = config or FocalCheckConfig()
    t0 = time.perf_counter()
    cam = m.camera
    f_used = float(math.sqrt(cam.fx * cam.fy))
    if not (math.isfinite(f_used) and f_used > 0):
        raise GeometryError(f"focal check: the map's camera has focal lengths fx={cam.fx}, fy={cam.fy}")
    fits: list[WindowFit] = []
    for rows in _choose_windows(m, config):
        # later windows start at the median of the informative ones so far (the prior stays at f_used)
        known = [w.f for w in fits if w.rel_sigma < config.max_rel_sigma]
        fit = _fit_window(m, rows, f_used, config, float(np.median(known)) if known else None, seed)
        if fit is not None:
            log.debug(
                "focal check: window from keyframe %d (%d keyframes, %d points, turning %.1f deg): "
                "f %.1f px +- %.2f%% after %d iterations",
                fit.first_keyframe_id,
                fit.n_keyframes,
                fit.n_points,
                fit.rotation_deg,
                fit.f,
                100 * fit.rel_sigma,
                fit.iterations,
            )
            fits.append(fit)
    fits.sort(key=lambda w: w.first_keyframe_id)
    good = [w for w in fits if w.rel_sigma < config.max_rel_sigma]
    f_est, rel_sigma = _combine(good)
    observable = bool(len(good) >= 1 and rel_sigma < config.max_rel_sigma)
    ratio = f_est / f_used
    deviates = abs(ratio - 1.0) > config.warn_ratio and abs(ratio - 1.0) > config.n_sigma * rel_sigma * ratio
    r = FocalCheck(
        f_used=f_used,
        f_estimated=f_est,
        ratio=ratio,
        rel_sigma=rel_sigma,
        observable=observable,
        plausible=not deviates,
        message="",
        hfov_used_deg=hfov_deg(f_used, cam.width),
        hfov_estimated_deg=hfov_deg(f_est, cam.width),
        n_windows=len(fits),
        n_informative=len(good),
        time_s=time.perf_counter() - t0,
        windows=fits,
    )
    r.message = _message(r, len(fits))
    return r


def _combine(good: list[WindowFit]) -> tuple[float, float]:
    """Median of the windows' f, and its relative sigma: the larger of the spread-based one (MAD) and
    the windows' own sigmas combined; one window gives its own sigma."""
    if not good:
        return math.nan, math.inf
    f = np.array([w.f for w in good])
    s = np.array([w.rel_sigma for w in good])
    med = float(np.median(f))
    own = float(1.0 / math.sqrt(np.sum(1.0 / s**2)))
    if len(good) < 3:
        return med, max(own, float(np.ptp(np.log(f))) / 2.0)
    mad = 1.4826 * float(np.median(np.abs(np.log(f) - math.log(med))))
    return med, max(own, 1.2533 * mad / math.sqrt(len(good)))


# ---- windows ---------------------------------------------------------------------------------------


def _choose_windows(m: Map, config: FocalCheckConfig) -> list[np.ndarray]:
    """Rows of consecutive keyframes (by id), non-overlapping, at most max_windows of those turning most,
    most turning first; all keyframes in one window when there are few."""
    order = np.argsort(m.keyframes.ids)
    n, w = len(order), max(config.window_keyframes, 2)
    if n < config.min_window_keyframes:
        return []
    if n <= w:
        return [order]
    starts = list(range(0, n - w + 1, w))
    if n - starts[-1] - w >= config.min_window_keyframes:
        starts.append(n - w)
    R = m.keyframes.T_wc[:, :3, :3]
    spans = []
    for s in starts:
        rows = order[s : s + w]
        rel = np.einsum("ji,njk->nik", R[rows[0]], R[rows])  # R0^T R
        spans.append(float(np.max(np.linalg.norm(geo.so3_log(rel), axis=-1))))
    best = np.argsort(spans)[::-1][: config.max_windows]
    return [order[starts[i] : starts[i] + w] for i in best]  # most turning first


@dataclass
class _Data:
    """A window's bundle: keyframe and point rows of the map, and observations indexing into those."""

    kf_rows: np.ndarray  # (N,)
    pt_rows: np.ndarray  # (P,)
    obs_pt: np.ndarray  # (K,) index into pt_rows
    obs_kf: np.ndarray  # (K,) index into kf_rows
    obs_uv: np.ndarray  # (K, 2) undistorted pixels


def _select(
    m: Map, kf_rows: np.ndarray, config: FocalCheckConfig, max_error_px: float, seed: int
) -> _Data | None:
    """Observations by the keyframes `kf_rows` of points seen from >= min_views of them, in front and
    reprojecting within max_error_px with the map's camera; None when too little is left."""
    pts, kfs = m.points, m.keyframes
    if len(pts) == 0 or len(pts.obs_ids) == 0:
        return None
    in_win = np.isin(pts.obs_ids[:, 1], kfs.ids[kf_rows])
    obs_ids = pts.obs_ids[in_win]
    p_sort, k_sort = np.argsort(pts.ids), np.argsort(kfs.ids)
    p_row = p_sort[np.searchsorted(pts.ids, obs_ids[:, 0], sorter=p_sort)]
    k_row = k_sort[np.searchsorted(kfs.ids, obs_ids[:, 1], sorter=k_sort)]
    uv = _undistort(m, pts.obs_uv[in_win])
    err = _reprojection_px(kfs.T_wc, pts.xyz, p_row, k_row, uv, m.camera.fx, m.camera.fy, m.camera)
    ok = err < max_error_px
    p_row, k_row, uv = p_row[ok], k_row[ok], uv[ok]
    pairs = unique_rows(np.stack([p_row, k_row], 1))
    views = np.bincount(pairs[:, 0], minlength=len(pts))
    keep = np.flatnonzero(views >= config.min_views)
    if len(keep) > config.max_points_per_window:
        rng = np.random.default_rng(seed)
        order = np.lexsort((rng.random(len(keep)), -views[keep]))  # most views first, random ties
        keep = np.sort(keep[order[: config.max_points_per_window]])
    sel = np.isin(p_row, keep)
    p_row, k_row, uv = p_row[sel], k_row[sel], uv[sel]
    used = np.unique(k_row)
    if len(used) < config.min_window_keyframes or len(keep) < 10:
        return None
    return _Data(used, keep, np.searchsorted(keep, p_row), np.searchsorted(used, k_row), uv)


def _undistort(m: Map, uv: np.ndarray) -> np.ndarray:
    """Observed (distorted) pixels -> pixels of the same K without distortion."""
    dist = np.asarray(m.camera.distortion, np.float64).ravel()
    if not np.any(dist) or len(uv) == 0:
        return np.asarray(uv, np.float64)
    K = m.camera.K
    return cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2)


def _reprojection_px(
    T: np.ndarray,
    xyz: np.ndarray,
    p_row: np.ndarray,
    k_row: np.ndarray,
    uv: np.ndarray,
    fx: float,
    fy: float,
    cam: Any,
) -> np.ndarray:
    """(K,) pixel distance of each observation to its point's projection (inf behind the camera)."""
    Tk = T[k_row]
    Xc = np.einsum("nji,nj->ni", Tk[:, :3, :3], xyz[p_row] - Tk[:, :3, 3])  # R^T (X - c)
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = np.stack([fx * Xc[:, 0] / z + cam.cx, fy * Xc[:, 1] / z + cam.cy], 1)
        err = np.linalg.norm(proj - uv, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


def _fit_window(
    m: Map,
    rows: np.ndarray,
    f_used: float,
    config: FocalCheckConfig,
    f_start: float | None = None,
    seed: int = 0,
) -> WindowFit | None:
    data = _select(m, rows, config, config.max_error_px, seed)
    if data is None:
        return None
    T = m.keyframes.T_wc[data.kf_rows]
    if np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1).max() <= 0:
        return None  # no translation: no scale gauge, no depths
    rel = np.einsum("ji,njk->nik", T[0, :3, :3], T[:, :3, :3])
    fit = WindowFit(
        first_keyframe_id=int(m.keyframes.ids[data.kf_rows[0]]),
        n_keyframes=len(data.kf_rows),
        n_points=len(data.pt_rows),
        n_observations=len(data.obs_uv),
        rotation_deg=float(np.degrees(np.max(np.linalg.norm(geo.so3_log(rel), axis=-1)))),
        f=f_used,
        rel_sigma=math.inf,
        iterations=0,
        rms_px=math.nan,
    )
    xyz = m.points.xyz[data.pt_rows]
    start_sigma = focal_sigma_at(T, xyz, data.obs_pt, data.obs_kf, data.obs_uv, m.camera, f_used, config)
    if start_sigma / f_used > config.screen_factor * config.max_rel_sigma:
        fit.rel_sigma = start_sigma / f_used
        return fit
    res = adjust_focal(
        T,
        m.points.xyz[data.pt_rows],
        data.obs_pt,
        data.obs_kf,
        data.obs_uv,
        m.camera,
        f_used,
        config,
        f_start=f_start,
    )
    fit.f, fit.iterations, fit.rms_px = res.f, res.iterations, res.rms_px
    fit.rel_sigma = res.sigma_f / res.f if res.f > 0 else math.inf
    return fit


# ---- adjustment ------------------------------------------------------------------------------------


@dataclass
class FocalFit:
    """Result of `adjust_focal`."""

    T_wc: np.ndarray  # (N, 4, 4)
    xyz: np.ndarray  # (P, 3)
    f: float
    sigma_f: float
    """Standard deviation of f (marginal over poses and points), scaled by the residual level (never
    below sigma_px); inf when f was held."""
    rms_px: float
    """RMS of the observations within 3 Huber thresholds, pixels."""
    iterations: int
    converged: bool


def adjust_focal(
    T_wc: np.ndarray,
    xyz: np.ndarray,
    obs_pt: np.ndarray,
    obs_kf: np.ndarray,
    obs_uv: np.ndarray,
    cam: Any,
    f0: float,
    config: FocalCheckConfig | None = None,
    free_f: bool = True,
    f_start: float | None = None,
) -> FocalFit:
    """Bundle-adjust poses T_wc (N,4,4), points xyz (P,3) and one focal length f (fx = fy = f, principal
    point cam.cx, cam.cy held) to observations obs_uv (K,2) of point obs_pt by keyframe obs_kf; f starts
    at f0 and is held there unless free_f. Gauge: the first pose held, and its distance to the farthest.
    Levenberg-Marquardt with Huber weights and the points eliminated by the Schur complement."""
    # the systems are small (~100 unknowns after the Schur step): BLAS threads only cost here, most of
    # all under load (other jobs on the cores)
    with threadpool_limits(limits=1, user_api="blas"):
        cfg = config or FocalCheckConfig()
        return _adjust_focal(T_wc, xyz, obs_pt, obs_kf, obs_uv, cam, f0, cfg, free_f, f_start)


def focal_sigma_at(
    T_wc: np.ndarray,
    xyz: np.ndarray,
    obs_pt: np.ndarray,
    obs_kf: np.ndarray,
    obs_uv: np.ndarray,
    cam: Any,
    f: float,
    config: FocalCheckConfig,
) -> float:
    """Standard deviation of f (pixels, unscaled by the residual level) from the normal equations at the
    given poses, points and f: what this window's geometry can pin f down to, before any adjustment."""
    T = np.asarray(T_wc, np.float64)
    far, d0 = _scale_gauge(T)
    pp = np.array([cam.cx, cam.cy])
    with threadpool_limits(limits=1, user_api="blas"):
        sys_ = _normal_equations(
            T,
            np.asarray(xyz, np.float64),
            f,
            pp,
            obs_pt,
            obs_kf,
            obs_uv,
            config,
            far,
            d0,
            GAUGE_SIGMA * d0,
            True,
            f,
        )
        return math.sqrt(max(_marginal_f(sys_), 0.0))


def _scale_gauge(T: np.ndarray) -> tuple[int, float]:
    """The keyframe farthest from the first (row) and its distance: the monocular scale gauge."""
    far = int(np.argmax(np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)))
    return far, float(np.linalg.norm(T[far, :3, 3] - T[0, :3, 3]))


def _adjust_focal(
    T_wc: np.ndarray,
    xyz: np.ndarray,
    obs_pt: np.ndarray,
    obs_kf: np.ndarray,
    obs_uv: np.ndarray,
    cam: Any,
    f0: float,
    config: FocalCheckConfig,
    free_f: bool,
    f_start: float | None,
) -> FocalFit:
    T = np.array(T_wc, np.float64)
    X = np.array(xyz, np.float64)
    N, P = len(T), len(X)
    pp = np.array([cam.cx, cam.cy])
    f = float(f0 if f_start is None or not free_f else f_start)
    far, d0 = _scale_gauge(T)
    if d0 <= 0:
        raise GeometryError("focal adjustment: the keyframes do not translate (no scale gauge)")
    s_prior = config.f_prior_rel_sigma * f0
    s_gauge = GAUGE_SIGMA * d0
    k_huber = config.huber_k * config.sigma_px

    def cost_at(T: np.ndarray, X: np.ndarray, f: float) -> float:
        e, _ = _residuals(T, X, f, pp, obs_pt, obs_kf, obs_uv)
        a = np.linalg.norm(e, axis=1)
        rho = np.where(a <= k_huber, 0.5 * a**2, k_huber * a - 0.5 * k_huber**2) / config.sigma_px**2
        d = np.linalg.norm(T[far, :3, 3] - T[0, :3, 3])
        prior = ((f - f0) / s_prior) ** 2 if free_f else 0.0
        return float(np.sum(rho) + 0.5 * ((d - d0) / s_gauge) ** 2 + 0.5 * prior)

    lam = 1e-3
    cost = cost_at(T, X, f)
    it, converged = 0, False
    for it in range(1, config.max_iterations + 1):  # noqa: B007
        sys_ = _normal_equations(T, X, f, pp, obs_pt, obs_kf, obs_uv, config, far, d0, s_gauge, free_f, f0)
        accepted = False
        while lam < 1e10:
            step = _solve(sys_, lam)
            if step is None:
                lam *= 10
                continue
            dpose, df, dX = step
            T_new = _retract(T, dpose)
            X_new = X + dX
            f_new = f + df
            new_cost = cost_at(T_new, X_new, f_new) if f_new > 0 else math.inf
            if new_cost < cost:
                rel = (cost - new_cost) / max(cost, 1e-300)
                T, X, f, cost = T_new, X_new, f_new, new_cost
                lam = max(lam / 10, 1e-9)
                accepted = True
                break
            lam *= 10
        if not accepted or rel < 1e-7:
            converged = True
            break
    sigma = math.inf
    if free_f:
        sys_ = _normal_equations(T, X, f, pp, obs_pt, obs_kf, obs_uv, config, far, d0, s_gauge, free_f, f0)
        var = _marginal_f(sys_)
        e, z = _residuals(T, X, f, pp, obs_pt, obs_kf, obs_uv)
        a = np.linalg.norm(e, axis=1)
        dof = max(2 * len(a) - 6 * (N - 1) - 3 * P, 1)
        level = math.sqrt(float(np.sum(np.minimum(a, 3 * k_huber) ** 2)) / dof) / config.sigma_px
        sigma = math.sqrt(max(var, 0.0)) * max(level, 1.0)
    e, _ = _residuals(T, X, f, pp, obs_pt, obs_kf, obs_uv)
    a = np.linalg.norm(e, axis=1)
    inl = a[a < 3 * k_huber]
    rms = float(np.sqrt(np.mean(inl**2))) if len(inl) else math.nan
    return FocalFit(T, X, f, sigma, rms, it, converged)


def _residuals(
    T: np.ndarray,
    X: np.ndarray,
    f: float,
    pp: np.ndarray,
    obs_pt: np.ndarray,
    obs_kf: np.ndarray,
    uv: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(K,2) projection minus observation (pixels; points behind get a large constant), (K,3) Xc."""
    Tk = T[obs_kf]
    Xc = np.einsum("nji,nj->ni", Tk[:, :3, :3], X[obs_pt] - Tk[:, :3, 3])  # R^T (X - c)
    z = Xc[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    e = f * Xc[:, :2] / zs[:, None] + pp - uv
    return np.where(front[:, None], e, 1e4), Xc


def projection_jacobians(
    T: np.ndarray, X: np.ndarray, f: float, obs_pt: np.ndarray, obs_kf: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians of each observation's projection (K,2,6) w.r.t. its pose (rotation then camera
    centre, T_wc <- [R exp(dtheta), c + dc]), (K,2,3) w.r.t. its point and (K,2) w.r.t. f."""
    Tk = T[obs_kf]
    Rt = np.swapaxes(Tk[:, :3, :3], 1, 2)  # (K,3,3) R^T
    Xc = np.einsum("nij,nj->ni", Rt, X[obs_pt] - Tk[:, :3, 3])
    x, y, z = Xc[:, 0], Xc[:, 1], np.where(np.abs(Xc[:, 2]) > 1e-9, Xc[:, 2], 1e-9)
    dproj = np.zeros((len(Xc), 2, 3))  # d(u,v)/dXc
    dproj[:, 0, 0] = f / z
    dproj[:, 0, 2] = -f * x / z**2
    dproj[:, 1, 1] = f / z
    dproj[:, 1, 2] = -f * y / z**2
    J_pt = dproj @ Rt
    J_pose = np.concatenate([dproj @ geo.skew(Xc), -J_pt], axis=2)
    J_f = np.stack([x / z, y / z], 1)
    return J_pose, J_pt, J_f


@dataclass
class _System:
    Hcc: np.ndarray  # (C, C) poses 1..N-1 (6 each) then f (1, when free)
    Hcp: np.ndarray  # (C, P, 3)
    Hpp: np.ndarray  # (P, 3, 3)
    gc: np.ndarray  # (C,)
    gp: np.ndarray  # (P, 3)
    n_pose: int
    free_f: bool


def _normal_equations(
    T: np.ndarray,
    X: np.ndarray,
    f: float,
    pp: np.ndarray,
    obs_pt: np.ndarray,
    obs_kf: np.ndarray,
    uv: np.ndarray,
    config: FocalCheckConfig,
    far: int,
    d0: float,
    s_gauge: float,
    free_f: bool,
    f0: float,
) -> _System:
    """Gauss-Newton normal equations with Huber IRLS weights; pose 0 held (left out)."""
    N, P = len(T), len(X)
    e, Xc = _residuals(T, X, f, pp, obs_pt, obs_kf, uv)
    J_pose, J_pt, J_f = projection_jacobians(T, X, f, obs_pt, obs_kf)
    a = np.linalg.norm(e, axis=1)
    k = config.huber_k * config.sigma_px
    w = np.minimum(1.0, k / np.maximum(a, 1e-300)) / config.sigma_px**2
    w[Xc[:, 2] <= 1e-9] = 0.0  # behind: no gradient
    n_pose = 6 * (N - 1)
    C = n_pose + (1 if free_f else 0)
    # camera-side Jacobian (K, 2, C) is sparse: scatter per observation
    Jc = np.zeros((len(e), 2, 7))
    Jc[:, :, :6] = J_pose
    Jc[:, :, 6] = J_f
    cols = np.empty((len(e), 7), np.int64)
    cols[:, :6] = 6 * (obs_kf[:, None] - 1) + np.arange(6)
    cols[:, 6] = n_pose
    valid = np.ones((len(e), 7), bool)
    valid[:, :6] = obs_kf[:, None] > 0
    valid[:, 6] = free_f
    Jc = Jc * valid[:, None, :]
    We = w[:, None] * e
    cols_ = np.where(valid, cols, C)  # held entries go to a spare row/col (index C), cut off below
    C1 = C + 1
    wJc, wJp = w[:, None, None] * Jc, w[:, None, None] * J_pt
    blk = _outer2(Jc, wJc)  # (K,7,7)
    Hcc = _scatter(cols_[:, :, None] * C1 + cols_[:, None, :], blk, C1 * C1).reshape(C1, C1)
    gc = _scatter(cols_, Jc[:, 0] * We[:, :1] + Jc[:, 1] * We[:, 1:], C1)
    cross = _outer2(Jc, wJp)  # (K,7,3)
    idx = (cols_[:, :, None] * P + obs_pt[:, None, None]) * 3 + np.arange(3)[None, None, :]
    Hcp = _scatter(idx, cross, C1 * P * 3).reshape(C1, P, 3)
    pidx = obs_pt[:, None, None] * 9 + np.arange(9).reshape(1, 3, 3)
    Hpp = _scatter(pidx, _outer2(J_pt, wJp), P * 9).reshape(P, 3, 3)
    gp = _scatter(obs_pt[:, None] * 3 + np.arange(3), J_pt[:, 0] * We[:, :1] + J_pt[:, 1] * We[:, 1:], P * 3)
    gp = gp.reshape(P, 3)
    Hcc, gc, Hcp = Hcc[:C, :C], gc[:C], Hcp[:C]
    # scale gauge: |c_far - c_0| = d0
    if far > 0:
        dvec = T[far, :3, 3] - T[0, :3, 3]
        d = float(np.linalg.norm(dvec))
        j = dvec / max(d, 1e-300) / s_gauge
        sl = slice(6 * (far - 1) + 3, 6 * (far - 1) + 6)
        Hcc[sl, sl] += np.outer(j, j)
        gc[sl] += j * (d - d0) / s_gauge
    if free_f:
        s = config.f_prior_rel_sigma * f0
        Hcc[n_pose, n_pose] += 1.0 / s**2
        gc[n_pose] += (f - f0) / s**2
    return _System(Hcc, Hcp, Hpp, gc, gp, n_pose, free_f)


def _outer2(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(K,2,a), (K,2,b) -> (K,a,b) A^T B per observation (two rows: plain products beat einsum 5x)."""
    return A[:, 0, :, None] * B[:, 0, None, :] + A[:, 1, :, None] * B[:, 1, None, :]


def _times_blocks(H: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(C,P,3) x (P,3,3) -> (C,P,3): each point's 3 columns times its 3x3 block."""
    out = H[:, :, 0, None] * B[None, :, 0]
    out += H[:, :, 1, None] * B[None, :, 1]
    out += H[:, :, 2, None] * B[None, :, 2]
    return out


def _scatter(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """Sum `values` into a flat array of `size` at `index` (same shape); bincount, far faster than add.at."""
    return np.bincount(index.ravel(), weights=values.ravel(), minlength=size)


def _solve(sys_: _System, lam: float) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Damped step (Marquardt: H + lam diag(H)); None when the damped system is singular."""
    C = len(sys_.gc)
    Hpp = sys_.Hpp + lam * np.einsum("nii->ni", sys_.Hpp)[:, :, None] * np.eye(3) + 1e-12 * np.eye(3)
    try:
        Hpp_inv = np.linalg.inv(Hpp)
    except np.linalg.LinAlgError:
        return None
    HcpHinv = _times_blocks(sys_.Hcp, Hpp_inv).reshape(C, -1)
    S = sys_.Hcc + lam * np.diag(np.diag(sys_.Hcc)) + 1e-12 * np.eye(C)
    S = S - HcpHinv @ sys_.Hcp.reshape(C, -1).T
    rhs = -(sys_.gc - HcpHinv @ sys_.gp.ravel())
    try:
        dc = np.linalg.solve(S, rhs)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(dc)):
        return None
    b = sys_.gp + (dc @ sys_.Hcp.reshape(C, -1)).reshape(-1, 3)
    dX = -(Hpp_inv @ b[:, :, None])[:, :, 0]
    dpose = np.concatenate([np.zeros(6), dc[: sys_.n_pose]]).reshape(-1, 6)
    df = float(dc[sys_.n_pose]) if sys_.free_f else 0.0
    return dpose, df, dX


def _marginal_f(sys_: _System) -> float:
    """Variance of f from the undamped system (points and poses marginalised)."""
    if not sys_.free_f:
        return math.inf
    try:
        Hpp_inv = np.linalg.inv(sys_.Hpp + 1e-12 * np.eye(3))
        C = len(sys_.gc)
        HcpHinv = _times_blocks(sys_.Hcp, Hpp_inv).reshape(C, -1)
        S = sys_.Hcc - HcpHinv @ sys_.Hcp.reshape(C, -1).T
        e = np.zeros(len(S))
        e[sys_.n_pose] = 1.0
        return float(np.linalg.solve(S, e)[sys_.n_pose])
    except np.linalg.LinAlgError:
        return math.inf


def _retract(T: np.ndarray, dpose: np.ndarray) -> np.ndarray:
    """T_wc <- [R exp(dtheta), c + dc] per pose; dpose (N, 6) = (dtheta, dc)."""
    out = T.copy()
    out[:, :3, :3] = T[:, :3, :3] @ geo.so3_exp(dpose[:, :3])
    out[:, :3, 3] = T[:, :3, 3] + dpose[:, 3:]
    return out


# ---- outcome ----------------------------------------------------------------------------------------


def _message(r: FocalCheck, n_windows: int) -> str:
    used = f"{r.f_used:.0f} px (hfov {r.hfov_used_deg:.1f} deg)"
    if n_windows == 0:
        return f"focal length not checked: too few keyframes or points seen from several keyframes ({used})"
    est = f"{r.f_estimated:.0f} px +- {100 * r.rel_sigma:.1f}% (hfov {r.hfov_estimated_deg:.1f} deg)"
    if not r.plausible:
        return (
            f"focal length looks wrong: the map was built with {used} but its points support {est} "
            f"({100 * (r.ratio - 1):+.0f}%); give the camera's intrinsics with --camera FILE or run again "
            f"without one and with --set hfov_deg={r.hfov_estimated_deg:.1f}"
        )
    if not r.observable:
        return (
            f"focal length not observable from this walk (it needs turns, not a straight walk): the used "
            f"{used} could not be checked"
        )
    return f"focal length plausible: used {used}, the map supports {est}"
