"""Keyframe rotations averaged from pairwise two-view geometry: a second start for the global BA.

Registration chains PnP poses. Where keyframes see the scene with little parallax (a photo set, a pan),
small errors of early points turn later rotations into a consistent but wrong configuration, a local
minimum the global BA does not leave. The relative rotation of two keyframes from their essential
matrix needs no structure, and averaged over every well-covisible pair (robustly, on SO(3)) it holds
no such drift; global SfM (GLOMAP) starts from it. Here it checks the BA's rotations: where they miss
the pairwise rotations far more than the averaged ones do, the BA runs again from the averaged
rotations, first holding them (camera positions and points found for them, as GLOMAP's global
positioning does) then freeing everything, and of the two maps the one at the lower cost over the
same observations is kept (maximum likelihood decides, not the check).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from scipy.sparse import coo_matrix

from papl_mapper.backend import BAConfig, global_ba
from papl_mapper.backend.ba import ProgressFn
from papl_mapper.errors import GeometryError, OptimizationError
from papl_mapper.geometry.se3 import rotation_alignment, rotation_angle_deg
from papl_mapper.geometry.two_view import find_essential
from papl_mapper.map import Map
from papl_mapper.mapping.second_start import point_cost, with_poses

log = logging.getLogger(__name__)


@dataclass
class RotationCheckConfig:
    """Settings of the rotation-averaging check after the first global BA."""

    enabled: bool = True
    """Average pairwise rotations and, where the BA's rotations disagree, try the BA from them."""
    neighbours: int = 6
    """Each keyframe is paired with this many keyframes it shares most points with."""
    min_shared: int = 30
    """Fewest shared points for a pair's essential matrix."""
    ransac_threshold_px: float = 1.0
    """Essential-matrix inlier threshold (pixels)."""
    min_inlier_ratio: float = 0.5
    """A pair whose essential matrix keeps fewer of its shared points is left out: the observations
    are the BA's inliers, so a poor fit means a degenerate pair (no baseline), not outliers."""
    sigma_deg: float = 0.1
    """Standard deviation of one pairwise rotation (degrees); a Huber loss beyond 1.345 sigma."""
    check_deg: float = 0.2
    """The BA's rotations start a second BA when they miss the pairwise rotations by more than this at
    the median pair (twice `sigma_deg`: beyond a pair's own noise; the second BA is kept only where it
    reaches the lower cost)..."""
    check_ratio: float = 3.0
    """...and by this many times more than the averaged rotations do (where the pairwise rotations are
    noisy, as from a rolling-shutter camera, both miss them alike: no second start)."""


@dataclass
class RotationCheck:
    """What the check found: the pairs used, how far the BA's and the averaged rotations miss them at the
    median pair, the largest keyframe disagreement, and when a second BA ran, both costs."""

    pairs: int = 0
    residual_ba_deg: float = 0.0
    residual_averaged_deg: float = 0.0
    max_disagreement_deg: float = 0.0
    second_start: bool = False
    cost_kept: float | None = None
    cost_other: float | None = None
    kept: str = "registration"

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def covisible_pairs(m: Map, neighbours: int, min_shared: int) -> list[tuple[int, int]]:
    """Keyframe row pairs (i < j): each keyframe with the `neighbours` others it shares the most points
    with, at least `min_shared`."""
    n = len(m.keyframes)
    if n < 2 or not len(m.points.obs_ids):
        return []
    kf_row = np.searchsorted(m.keyframes.ids, m.points.obs_ids[:, 1])
    pt_row = np.searchsorted(m.points.ids, m.points.obs_ids[:, 0])
    A = coo_matrix((np.ones(len(kf_row)), (kf_row, pt_row)), shape=(n, len(m.points))).tocsr()
    A.data[:] = 1.0  # a point seen twice by one keyframe counts once
    shared = (A @ A.T).tocsr()  # sparse: a long recording's keyframes each see a few others
    shared.setdiag(0)
    shared.eliminate_zeros()
    pairs = set()
    for i in range(n):
        lo, hi = shared.indptr[i], shared.indptr[i + 1]
        cols, counts = shared.indices[lo:hi], shared.data[lo:hi]
        best = np.argsort(-counts, kind="stable")[:neighbours]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in cols[best[counts[best] >= min_shared]])
    return sorted(pairs)


def relative_rotation(
    uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, cfg: RotationCheckConfig, seed: int = 0
) -> np.ndarray | None:
    """R_ba (camera a to camera b) from matched pixels by the essential matrix, or None where the pair
    is degenerate (too few inliers, or too few of them in front of both cameras: no baseline)."""
    cv2.setRNGSeed(seed)  # OpenCV's generator is per thread: seeded per call, any thread gives one answer
    E, mask = find_essential(uv_a, uv_b, K, cv2.USAC_ACCURATE, cfg.ransac_threshold_px)
    need = cfg.min_inlier_ratio * len(uv_a)
    if E is None or mask is None or mask.sum() < need:
        return None
    inl = mask.ravel().astype(bool)
    K_inv = np.linalg.inv(K)
    f_a = np.column_stack([uv_a[inl], np.ones(inl.sum())]) @ K_inv.T
    f_b = np.column_stack([uv_b[inl], np.ones(inl.sum())]) @ K_inv.T
    f_a /= np.linalg.norm(f_a, axis=1, keepdims=True)
    f_b /= np.linalg.norm(f_b, axis=1, keepdims=True)
    R1, R2, t = cv2.decomposeEssentialMat(E[:3])
    best, best_front = None, -1
    for R in (R1, R2):
        for sign in (1.0, -1.0):
            front = _in_front(R, sign * t.ravel(), f_a, f_b)
            if front > best_front:
                best, best_front = R, front
    return best if best_front >= need else None


def _in_front(R: np.ndarray, t: np.ndarray, f_a: np.ndarray, f_b: np.ndarray) -> int:
    """How many unit ray pairs meet in front of both cameras (x_b = R x_a + t): depths d_a, d_b of the
    closest approach of d_a R f_a + t and d_b f_b, by least squares per pair."""
    g = f_a @ R.T
    c = np.sum(g * f_b, axis=1)
    det = 1.0 - c**2
    gt, ft = g @ t, f_b @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        d_a = (-gt + c * ft) / det
        d_b = (-c * gt + ft) / det
    return int(np.sum((det > 1e-12) & (d_a > 0) & (d_b > 0)))


def average_rotations(
    R_init: np.ndarray, measurements: list[tuple[int, int, np.ndarray]], sigma_deg: float
) -> np.ndarray:
    """(N, 3, 3) world-from-camera rotations fitting R_b^T R_a = R_ba for each (a, b, R_ba), robustly
    (Huber), started from `R_init`; the first rotation is held (the gauge)."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(3, np.radians(sigma_deg)),
    )
    for a, b, R_ba in measurements:
        graph.add(gtsam.BetweenFactorRot3(a, b, gtsam.Rot3(R_ba.T), noise))
    graph.add(gtsam.PriorFactorRot3(0, gtsam.Rot3(R_init[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    values = gtsam.Values()
    for i, R in enumerate(R_init):
        values.insert(i, gtsam.Rot3(R))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return np.array([result.atRot3(i).matrix() for i in range(len(R_init))])


def averaged_rotations(
    m: Map, cfg: RotationCheckConfig, seed: int = 0, workers: int = 2
) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """The map's keyframe rotations averaged from the pairwise rotations of covisible keyframes (those
    no pair reaches keep their own), and those pairwise rotations (a, b, R_ba); `workers` threads
    estimate the pairs (OpenCV releases the GIL), the results kept in pair order."""
    T = m.keyframes.T_wc
    obs_kf = np.searchsorted(m.keyframes.ids, m.points.obs_ids[:, 1])
    order = np.argsort(obs_kf, kind="stable")
    bounds = np.searchsorted(obs_kf[order], np.arange(len(T) + 1))
    pairs = covisible_pairs(m, cfg.neighbours, cfg.min_shared)

    def estimate(pair: tuple[int, int]) -> np.ndarray | None:
        rows_a, rows_b = (order[bounds[k] : bounds[k + 1]] for k in pair)
        _, ia, ib = np.intersect1d(
            m.points.obs_ids[rows_a, 0], m.points.obs_ids[rows_b, 0], return_indices=True
        )
        return relative_rotation(
            m.points.obs_uv[rows_a[ia]], m.points.obs_uv[rows_b[ib]], m.camera.K, cfg, seed
        )

    with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="rotations") as pool:
        rotations = list(pool.map(estimate, pairs))
    measurements = [(a, b, R) for (a, b), R in zip(pairs, rotations, strict=True) if R is not None]
    if not measurements:
        return T[:, :3, :3].copy(), []
    return average_rotations(T[:, :3, :3], measurements, cfg.sigma_deg), measurements


def pair_residual_deg(R_wc: np.ndarray, measurements: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """(M,) angle between each measured R_ba and the one the rotations `R_wc` give (R_b^T R_a)."""
    a, b = (np.array([mm[i] for mm in measurements]) for i in (0, 1))
    R_ba = np.array([mm[2] for mm in measurements])
    return rotation_angle_deg(R_ba, np.swapaxes(R_wc[b], 1, 2) @ R_wc[a])


def disagreement_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """(N,) angle of each R_a[i] from R_b[i] after the common rotation G (R_a ~ G R_b) that fits best."""
    return rotation_angle_deg(R_a, rotation_alignment(R_b, R_a) @ R_b)


def with_rotations(m: Map, R_wc: np.ndarray) -> Map:
    """A copy of `m` with the keyframe rotations `R_wc` (camera centres kept) and its points triangulated
    anew from those poses; a point the new poses cannot triangulate turns with its first keyframe."""
    T_new = m.keyframes.T_wc.copy()
    T_new[:, :3, :3] = R_wc
    return with_poses(m, T_new)


def rotation_checked(
    m: Map,
    ba: BAConfig,
    cfg: RotationCheckConfig,
    max_error_px: float,
    progress: ProgressFn | None = None,
    seed: int = 0,
) -> tuple[Map, RotationCheck]:
    """`m` (a map after its global BA) checked against its averaged rotations: where they disagree by more
    than `cfg.check_deg`, a global BA from the averaged rotations, and of the two the map whose point
    cost over the same observations (errors capped at `max_error_px`) is lower."""
    check = RotationCheck()
    if len(m.keyframes) < 3 or not ba.optimize_poses:  # poses held by the BA are the user's to keep
        return m, check
    R_ba = m.keyframes.T_wc[:, :3, :3]
    R_avg, measurements = averaged_rotations(m, cfg, seed)
    check.pairs = len(measurements)
    if not measurements:
        return m, check
    check.residual_ba_deg = float(np.median(pair_residual_deg(R_ba, measurements)))
    check.residual_averaged_deg = float(np.median(pair_residual_deg(R_avg, measurements)))
    check.max_disagreement_deg = float(disagreement_deg(R_ba, R_avg).max())
    cost = point_cost(m, ba.point_sigma_px, ba.huber_k, max_error_px)
    check.cost_kept = cost
    if check.residual_ba_deg <= max(cfg.check_deg, cfg.check_ratio * check.residual_averaged_deg):
        return m, check
    check.second_start = True
    try:
        # positions and points from the averaged rotations first (held), then everything: started from
        # the registration's positions with free rotations, the BA turns back into the registration's fit
        held = global_ba(with_rotations(m, R_avg), ba, progress, hold_rotations=True).map
        other = global_ba(held, ba, progress).map
    except (GeometryError, OptimizationError) as exc:
        log.info(
            "rotation check: the BA from averaged rotations failed (%s); the registration's start kept", exc
        )
        return m, check
    other.metadata = dict(m.metadata)
    check.cost_other = point_cost(other, ba.point_sigma_px, ba.huber_k, max_error_px)
    better = check.cost_other < cost
    log.info(
        "rotation check: the keyframe rotations miss %d pairwise two-view rotations by %.2f deg (median; "
        "their average by %.2f deg, up to %.2f deg from the BA's); the BA restarted from the averaged "
        "rotations ends at cost %.6g against %.6g: %s",
        check.pairs,
        check.residual_ba_deg,
        check.residual_averaged_deg,
        check.max_disagreement_deg,
        check.cost_other,
        cost,
        "kept" if better else "not kept",
    )
    if better:
        check.kept, check.cost_kept, check.cost_other = "averaged", check.cost_other, cost
        return other, check
    return m, check
