"""Focal-length self-calibration of a finished map: is the focal length the map was built with plausible?

A wrong focal length (no camera file, so a 60 deg field-of-view guess, or the file of another camera)
still gives a map, only a distorted one. The bundle itself measures f when the walk rotates the camera:
a point bundle adjusted with one shared focal length f (fx = fy = f, principal point held) moves f to the
value the image motion supports. `check_focal` does that (gtsam, points only, Huber loss), reads the
uncertainty of f from the marginal covariance scaled by the residual level, and says whether f is
observable (a straight walk without turns leaves it free: scaling f and the lateral coordinates of the
scene together changes no image) and whether the used f is implausible.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import cv2
import gtsam
import numpy as np

from papl_mapper.errors import GeometryError
from papl_mapper.map import Camera, Map

log = logging.getLogger(__name__)


@dataclass
class FocalCheckConfig:
    """Settings of the focal-length plausibility check run after mapping."""

    enabled: bool = True
    """Run the check (it costs one points-only bundle adjustment with a focal-length variable)."""
    warn_ratio: float = 0.10
    """Warn when the estimated focal length differs from the used one by more than this fraction."""
    n_sigma: float = 3.0
    """... and by more than this many standard deviations of the estimate."""
    max_rel_sigma: float = 0.04
    """f counts as observable when its standard deviation is below this fraction of f."""
    max_points: int = 3000
    """Points used at most (those seen by the most keyframes first), to bound the run time."""
    min_views: int = 3
    """Points seen from fewer keyframes are left out (two views constrain f little)."""
    min_keyframes: int = 4
    """Fewer usable keyframes: the check reports 'not observable' without optimising."""
    sigma_px: float = 1.0
    """Standard deviation of a point observation, pixels (the result is rescaled by the residual level)."""
    huber_k: float = 1.345
    """Huber threshold in standard deviations."""
    max_error_px: float = 8.0
    """Observations reprojecting further than this with the used focal length are left out as outliers."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations at most."""
    f_prior_rel_sigma: float = 0.3
    """A weak prior on f (this fraction of the used f, 1 sigma) keeps the system solvable when f is not
    observable; it moves an observable estimate by (its rel. sigma / this)^2 of the way, e.g. 0.2% at 1%."""
    seed: int = 0
    """Seed of the point subsample."""


@dataclass
class FocalCheck:
    """Outcome of `check_focal`. `f_estimated` is NaN when the check could not run (too little data)."""

    f_used: float
    f_estimated: float
    ratio: float
    """f_estimated / f_used."""
    rel_sigma: float
    """Standard deviation of f_estimated as a fraction of it (inf when not computed)."""
    observable: bool
    """The bundle pins f down to max_rel_sigma or better."""
    plausible: bool
    """False when the used f is implausible: the caller should warn with `message`."""
    message: str
    hfov_used_deg: float
    hfov_estimated_deg: float
    n_keyframes: int = 0
    n_points: int = 0
    n_observations: int = 0
    rms_px_used: float = math.nan
    """Point reprojection RMS (inliers) with the used f, after adjusting poses and points."""
    rms_px_estimated: float = math.nan
    """... and with the estimated f."""
    iterations: int = 0
    time_s: float = 0.0

    def summary(self) -> dict[str, Any]:
        """Plain-JSON form for summary.json and the report (NaN/inf become None)."""
        out = {}
        for k, v in asdict(self).items():
            if isinstance(v, float) and not math.isfinite(v):
                v = None
            out[k] = v
        return out


def hfov_deg(f: float, width: int) -> float:
    """Horizontal field of view (degrees) of a focal length f in pixels on an image `width` pixels wide."""
    return math.degrees(2.0 * math.atan(width / 2.0 / f)) if f > 0 else math.nan


def check_focal(m: Map, config: FocalCheckConfig | None = None) -> FocalCheck:
    """Estimate the focal length from the map's point bundle and judge the one it was built with."""
    config = config or FocalCheckConfig()
    t0 = time.perf_counter()
    cam = m.camera
    f_used = float(math.sqrt(cam.fx * cam.fy))
    if not f_used > 0:
        raise GeometryError(f"focal check: the map's camera has focal lengths fx={cam.fx}, fy={cam.fy}")
    data = _select(m, config, config.max_error_px)
    if data is None:
        return _unobservable(m, f_used, config, t0, "too few keyframes or multi-view points")
    T = m.keyframes.T_wc[data.kf_rows]
    xyz = m.points.xyz[data.pt_rows]
    depth = float(np.median(np.linalg.norm(xyz - T[0, :3, 3], axis=1)))
    if np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1).max() < 1e-6 * depth:
        return _unobservable(m, f_used, config, t0, "the keyframes do not translate")
    held = _adjust(T, xyz, data, cam, f_used, config, free_f=False)
    free = _adjust(held.T_wc, held.xyz, data, cam, f_used, config, free_f=True)
    f_est = free.f
    rel_sigma = free.sigma_f / f_est if f_est > 0 else math.inf
    observable = bool(rel_sigma < config.max_rel_sigma)
    ratio = f_est / f_used
    deviates = abs(ratio - 1.0) > config.warn_ratio and abs(f_est - f_used) > config.n_sigma * free.sigma_f
    result = FocalCheck(
        f_used=f_used,
        f_estimated=f_est,
        ratio=ratio,
        rel_sigma=rel_sigma,
        observable=observable,
        plausible=not (observable and deviates),
        message="",
        hfov_used_deg=hfov_deg(f_used, cam.width),
        hfov_estimated_deg=hfov_deg(f_est, cam.width),
        n_keyframes=len(data.kf_rows),
        n_points=len(data.pt_rows),
        n_observations=len(data.obs_uv),
        rms_px_used=held.rms_px,
        rms_px_estimated=free.rms_px,
        iterations=held.iterations + free.iterations,
        time_s=time.perf_counter() - t0,
    )
    result.message = _message(result, config)
    return result


def refit_focal(m: Map, f: float, config: FocalCheckConfig | None = None) -> Map:
    """A copy of `m` whose camera has fx = fy = f and whose keyframe poses and multi-view points are
    adjusted to it (points-only BA; lines, other points and distortion unchanged). Used to compare maps
    at two focal lengths and by tests to make a map consistent with a wrong focal length."""
    config = config or FocalCheckConfig()
    data = _select(m, config, math.inf)
    if data is None:
        raise GeometryError(
            "refit_focal: the map has too few keyframes or points seen from several keyframes"
        )
    cam = replace(m.camera, fx=float(f), fy=float(f))
    fit = _adjust(
        m.keyframes.T_wc[data.kf_rows], m.points.xyz[data.pt_rows], data, cam, float(f), config, False
    )
    out = copy.deepcopy(m)
    out.camera = cam
    out.keyframes.T_wc[data.kf_rows] = fit.T_wc
    out.points.xyz[data.pt_rows] = fit.xyz
    return out


# ---- data ----------------------------------------------------------------------------------------


@dataclass
class _Data:
    """The bundle used: keyframe and point rows of the map, and observations indexing into those."""

    kf_rows: np.ndarray  # (N,)
    pt_rows: np.ndarray  # (P,)
    obs_pt: np.ndarray  # (K,) index into pt_rows
    obs_kf: np.ndarray  # (K,) index into kf_rows
    obs_uv: np.ndarray  # (K, 2) undistorted pixels


def _select(m: Map, config: FocalCheckConfig, max_error_px: float) -> _Data | None:
    """Points seen from >= min_views keyframes in front of them, observations reprojecting within
    max_error_px with the map's camera; None when too little is left."""
    pts, kfs = m.points, m.keyframes
    if len(pts) == 0 or len(kfs) < config.min_keyframes or len(pts.obs_ids) == 0:
        return None
    p_row = np.searchsorted(pts.ids, pts.obs_ids[:, 0], sorter=np.argsort(pts.ids))
    p_row = np.argsort(pts.ids)[p_row]
    k_row = np.argsort(kfs.ids)[np.searchsorted(kfs.ids, pts.obs_ids[:, 1], sorter=np.argsort(kfs.ids))]
    uv = _undistort(m, pts.obs_uv)
    # reprojection with the used camera: drop outliers and points behind cameras
    T = kfs.T_wc[k_row]
    Xc = np.einsum("nji,nj->ni", T[:, :3, :3], pts.xyz[p_row] - T[:, :3, 3])  # R^T (X - c)
    z = Xc[:, 2]
    cam = m.camera
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = np.stack([cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy], 1)
    err = np.linalg.norm(proj - uv, axis=1)
    ok = (z > 0) & np.isfinite(err) & (err < max_error_px)
    p_row, k_row, uv = p_row[ok], k_row[ok], uv[ok]
    # distinct views per point
    pairs = np.unique(np.stack([p_row, k_row], 1), axis=0)
    views = np.bincount(pairs[:, 0], minlength=len(pts))
    keep = np.flatnonzero(views >= config.min_views)
    if len(keep) > config.max_points:
        rng = np.random.default_rng(config.seed)
        order = np.lexsort((rng.random(len(keep)), -views[keep]))  # most views first, random ties
        keep = np.sort(keep[order[: config.max_points]])
    sel = np.isin(p_row, keep)
    p_row, k_row, uv = p_row[sel], k_row[sel], uv[sel]
    kf_rows = np.unique(k_row)
    if len(kf_rows) < config.min_keyframes or len(keep) < 10:
        return None
    p_new = np.searchsorted(keep, p_row)
    k_new = np.searchsorted(kf_rows, k_row)
    return _Data(kf_rows, keep, p_new, k_new, uv)


def _undistort(m: Map, uv: np.ndarray) -> np.ndarray:
    """Observed (distorted) pixels -> pixels of the same K without distortion."""
    dist = np.asarray(m.camera.distortion, np.float64).ravel()
    if not np.any(dist) or len(uv) == 0:
        return np.asarray(uv, np.float64)
    K = m.camera.K
    return cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2)


# ---- optimisation ----------------------------------------------------------------------------------


@dataclass
class _Fit:
    """One points-only adjustment with a shared focal length."""

    T_wc: np.ndarray  # (N, 4, 4)
    xyz: np.ndarray  # (P, 3)
    f: float
    sigma_f: float  # inf when f was held
    rms_px: float
    iterations: int


def _adjust(
    T: np.ndarray,
    xyz: np.ndarray,
    data: _Data,
    cam: Camera,
    f0: float,
    config: FocalCheckConfig,
    free_f: bool,
) -> _Fit:
    """Points-only BA with a shared focal length f (fx = fy = f, principal point held), held at f0 unless
    free_f. The gauge: the first keyframe held, and its distance to the farthest keyframe. The standard
    deviation of a free f is its marginal one, scaled by the residual level (never below sigma_px)."""
    f_key = gtsam.symbol("k", 0)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, Ti in enumerate(T):
        values.insert(_xk(i), gtsam.Pose3(Ti))
    for j, X in enumerate(xyz):
        values.insert(_pk(j), np.asarray(X, np.float64))
    values.insert(f_key, gtsam.Cal3f(f0, cam.cx, cam.cy))
    graph.add(gtsam.PriorFactorPose3(_xk(0), gtsam.Pose3(T[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    far = int(np.argmax(np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)))
    dist = float(np.linalg.norm(T[far, :3, 3] - T[0, :3, 3]))
    graph.add(
        gtsam.RangeFactorPose3(_xk(0), _xk(far), dist, gtsam.noiseModel.Isotropic.Sigma(1, 1e-3 * dist))
    )
    graph.add(_focal_prior(f_key, f0, config.f_prior_rel_sigma * f0 if free_f else 1e-6 * f0))
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k),
        gtsam.noiseModel.Isotropic.Sigma(2, config.sigma_px),
    )
    for j, k, uv in zip(data.obs_pt, data.obs_kf, data.obs_uv, strict=True):
        graph.add(gtsam.GeneralSFMFactor2Cal3f(uv, noise, _xk(k), _pk(j), f_key))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(1e-5)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    out = opt.optimize()
    T_new = np.stack([out.atPose3(_xk(i)).matrix() for i in range(len(T))])
    xyz_new = np.stack([out.atPoint3(_pk(j)) for j in range(len(xyz))])
    f = float(out.atCal3f(f_key).f())
    err = _reprojection_px(T_new, xyz_new, data, f, cam)
    inl = err[err < config.huber_k * config.sigma_px * 3]
    rms = float(np.sqrt(np.mean(inl**2))) if len(inl) else math.nan
    sigma = math.inf
    if free_f:
        try:
            sigma = float(math.sqrt(max(gtsam.Marginals(graph, out).marginalCovariance(f_key)[0, 0], 0.0)))
        except RuntimeError:  # indeterminate system: f (or more) is not observable
            sigma = math.inf
        n_res = 2 * len(data.obs_uv)
        n_par = 6 * (len(T) - 1) + 3 * len(xyz) + 1
        level = math.sqrt(2.0 * float(opt.error()) / max(n_res - n_par, 1))
        sigma *= max(level, 1.0)
    return _Fit(T_new, xyz_new, f, sigma, rms, int(opt.iterations()))


def _xk(i: int) -> int:
    return gtsam.symbol("x", int(i))


def _pk(j: int) -> int:
    return gtsam.symbol("p", int(j))


def _focal_prior(key: int, f0: float, sigma: float) -> gtsam.CustomFactor:
    """(f - f0) / sigma on a Cal3f variable (gtsam wraps no PriorFactor for Cal3f)."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        if H is not None:
            H[0] = np.array([[1.0 / sigma]])
        return np.array([(values.atCal3f(key).f() - f0) / sigma])

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [key], error)


def _reprojection_px(T: np.ndarray, xyz: np.ndarray, data: _Data, f: float, cam: Camera) -> np.ndarray:
    """(K,) pixel distance of each observation to its point's projection with focal f (inf behind)."""
    Tk = T[data.obs_kf]
    Xc = np.einsum("nji,nj->ni", Tk[:, :3, :3], xyz[data.obs_pt] - Tk[:, :3, 3])  # R^T (X - c)
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = f * Xc[:, :2] / z[:, None] + np.array([cam.cx, cam.cy])
        err = np.linalg.norm(proj - data.obs_uv, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


# ---- outcome -------------------------------------------------------------------------------------


def _unobservable(m: Map, f_used: float, config: FocalCheckConfig, t0: float, why: str) -> FocalCheck:
    r = FocalCheck(
        f_used=f_used,
        f_estimated=math.nan,
        ratio=math.nan,
        rel_sigma=math.inf,
        observable=False,
        plausible=True,
        message="",
        hfov_used_deg=hfov_deg(f_used, m.camera.width),
        hfov_estimated_deg=math.nan,
        time_s=time.perf_counter() - t0,
    )
    r.message = f"focal length not checked: {why}"
    return r


def _message(r: FocalCheck, config: FocalCheckConfig) -> str:
    est = f"{r.f_estimated:.0f} px +- {100 * r.rel_sigma:.1f}% (hfov {r.hfov_estimated_deg:.1f} deg)"
    used = f"{r.f_used:.0f} px (hfov {r.hfov_used_deg:.1f} deg)"
    if not r.observable:
        return (
            f"focal length not observable from this walk (estimate {est}; needs turns, not a straight walk): "
            f"the used {used} could not be checked"
        )
    if r.plausible:
        return f"focal length plausible: used {used}, the map supports {est}"
    return (
        f"focal length looks wrong: the map was built with {used} but its points support {est} "
        f"({100 * (r.ratio - 1):+.0f}%); give the camera's intrinsics with --camera FILE or run again with "
        f"--set hfov_deg={r.hfov_estimated_deg:.1f}"
    )
