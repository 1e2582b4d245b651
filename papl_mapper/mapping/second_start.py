"""Second starts for the global BA: a map moved to other keyframe poses, and the cost that judges them.

A global BA does not leave the basin its start lies in. Where another estimate of the keyframe poses
exists (rotations averaged from pairwise geometry, the recording registered backwards), the BA runs
again from it, and the two results are compared by their robust cost over the same observations:
maximum likelihood decides which map is kept, not the check that proposed the second start.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from papl_mapper.geometry.se3 import invert, project_points
from papl_mapper.geometry.triangulation import triangulate_points
from papl_mapper.map import Map
from papl_mapper.tracks import Tracks


def with_poses(m: Map, T_wc: np.ndarray) -> Map:
    """A copy of `m` with the keyframe poses `T_wc` (N, 4, 4) and its points triangulated anew from them;
    a point the new poses cannot triangulate moves rigidly with its first observing keyframe."""
    kf = m.keyframes
    pts = m.points
    kf_row = np.searchsorted(kf.ids, pts.obs_ids[:, 1])
    pt_row = np.searchsorted(pts.ids, pts.obs_ids[:, 0])
    X, ok = triangulate_points(pt_row, T_wc[kf_row], m.camera.K, pts.obs_uv, len(pts))
    first = np.full(len(pts), len(kf_row))
    np.minimum.at(first, pt_row, np.arange(len(kf_row)))
    X[~ok] = pts.xyz[~ok]  # unobserved points stay where they are
    moved = np.flatnonzero(~ok & (first < len(kf_row)))
    k = kf_row[first[moved]]
    motion = T_wc[k] @ invert(kf.T_wc[k])
    X[moved] = np.einsum("nij,nj->ni", motion[:, :3, :3], pts.xyz[moved]) + motion[:, :3, 3]
    return replace(
        m, keyframes=replace(kf, T_wc=T_wc.copy()), points=replace(pts, xyz=X), metadata=dict(m.metadata)
    )


def point_cost(m: Map, sigma_px: float, huber_k: float, max_error_px: float) -> float:
    """Half the summed Huber loss of the whitened point reprojection errors (gtsam's robust cost) over
    every observation of the map, each error capped at `max_error_px` (the culling limit: beyond it an
    observation is an outlier either way, and a point behind its camera counts as one)."""
    pts = m.points
    kf_row = np.searchsorted(m.keyframes.ids, pts.obs_ids[:, 1])
    pt_row = np.searchsorted(pts.ids, pts.obs_ids[:, 0])
    uv, z = project_points(m.camera.K, m.keyframes.T_wc[kf_row], pts.xyz[pt_row])
    err = np.linalg.norm(uv - pts.obs_uv, axis=1)
    return float(_capped_losses(err, z > 0, sigma_px, huber_k, max_error_px).sum())


def _capped_losses(
    err_px: np.ndarray, valid: np.ndarray, sigma_px: float, huber_k: float, cap_px: float
) -> np.ndarray:
    """Half the Huber loss of each whitened error, capped at `cap_px` (`valid` False: at the cap)."""
    e = np.where(valid, np.minimum(err_px, cap_px), cap_px) / sigma_px
    return np.where(e <= huber_k, 0.5 * e**2, huber_k * e - 0.5 * huber_k**2)


def pose_losses(
    tracks: Tracks,
    frames: np.ndarray,
    T_wc: np.ndarray,
    sigma_px: float,
    huber_k: float,
    max_error_px: float,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """What keyframe poses alone (`T_wc` (N, 4, 4) at frame rows `frames`, ascending) cost on every
    observation of the tracks in those frames: each track seen at least twice is triangulated from the
    poses and refined with them held (Gauss-Newton on the Huber loss), and each observation's capped
    loss (`point_cost`'s) is returned with its track id, in an order that depends only on the tracks
    and frames. A track the poses cannot triangulate (behind a camera) counts at the cap in every view:
    judged this way, two sets of poses are compared on the same data whatever observations each one's
    own BA kept."""
    sel = np.flatnonzero(np.isin(tracks.point_frame, frames))
    ids, point_row = np.unique(tracks.point_track[sel], return_inverse=True)
    keep = np.bincount(point_row, minlength=len(ids))[point_row] >= 2
    sel, point_row = sel[keep], np.unique(point_row[keep], return_inverse=True)[1]
    n_points = int(point_row.max()) + 1 if len(point_row) else 0
    kf_row = np.searchsorted(frames, tracks.point_frame[sel])
    uv = tracks.point_uv[sel]
    K = tracks.camera.K
    X, ok = triangulate_points(point_row, T_wc[kf_row], K, uv, n_points, 0.0)
    X = refit_points(point_row, T_wc[kf_row], K, uv, X, ok, huber_k * sigma_px, iterations)
    uv_hat, z = project_points(K, T_wc[kf_row], X[point_row])
    err = np.linalg.norm(uv_hat - uv, axis=1)
    losses = _capped_losses(err, (z > 0) & ok[point_row], sigma_px, huber_k, max_error_px)
    return losses, tracks.point_track[sel]


def refit_points(
    point_row: np.ndarray,
    T_wc: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    X: np.ndarray,
    ok: np.ndarray,
    huber_px: float,
    iterations: int,
) -> np.ndarray:
    """Points `X` (P, 3) refined with their cameras held: Gauss-Newton on the Huber loss (threshold
    `huber_px` pixels) of observations uv (K, 2) by cameras T_wc (K, 4, 4) of points `point_row` (K,);
    points not `ok` stay. Observations behind their camera weigh nothing."""
    T_cw = invert(T_wc)
    X = X.copy()
    for _ in range(iterations):
        Xc = np.einsum("kij,kj->ki", T_cw[:, :3, :3], X[point_row]) + T_cw[:, :3, 3]
        front = Xc[:, 2] > 1e-9
        z = np.where(front, Xc[:, 2], 1.0)
        r = np.where(front[:, None], (Xc[:, :2] / z[:, None]) @ K[:2, :2].T + K[:2, 2] - uv, 0.0)
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12)) * front
        J = np.zeros((len(z), 2, 3))  # d pixel / d camera-frame point, then / d world point
        J[:, 0, 0], J[:, 0, 2] = K[0, 0] / z, -K[0, 0] * Xc[:, 0] / z**2
        J[:, 1, 1], J[:, 1, 2] = K[1, 1] / z, -K[1, 1] * Xc[:, 1] / z**2
        J = J @ T_cw[:, :3, :3]
        H = np.zeros((len(X), 3, 3))
        g = np.zeros((len(X), 3))
        np.add.at(H, point_row, w[:, None, None] * np.einsum("kai,kaj->kij", J, J))
        np.add.at(g, point_row, w[:, None] * np.einsum("kai,ka->ki", J, r))
        damping = 1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-12  # parallel rays: no jump
        step = np.linalg.solve(H + damping * np.eye(3), g[..., None])[..., 0]
        X -= np.where(ok[:, None] & np.isfinite(step), step, 0.0)
    return X


def paired_z(difference: np.ndarray, group: np.ndarray) -> float:
    """The summed per-observation `difference` (K,) of two candidates' losses over its standard error,
    with the observations summed per `group` (K,) first (a track's observations share its errors, the
    tracks are the independent samples): below -3, the first candidate fits the data significantly
    better. 0 with fewer than two groups or no spread."""
    _, index = np.unique(group, return_inverse=True)
    per_group = np.bincount(index, weights=difference)
    if len(per_group) < 2:
        return 0.0
    spread = per_group.std(ddof=1) * np.sqrt(len(per_group))
    return float(per_group.sum() / spread) if spread > 0 else 0.0
