"""Triangulation of points (multi-view midpoint) and lines (plane intersection, two- and multi-view)."""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.lines import plucker_from_homogeneous_points

MIN_DEPTH_FRACTION = 0.01
"""A triangulated point's depth in each of its cameras must exceed this fraction of its distance from the
farthest of them (the rays of a real point that near one camera would barely reach the others')."""


def triangulate_points(
    point_index: np.ndarray,
    T_wc: np.ndarray,
    K: np.ndarray,
    uv: np.ndarray,
    n_points: int,
    min_angle_deg: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view midpoint triangulation: X minimising the summed squared distance to the viewing rays.

    point_index (K,) which point each observation belongs to; T_wc (K, 4, 4), uv (K, 2) pixels.
    Returns X (P, 3) and ok (P,): False with fewer than two rays, a ray parallax below `min_angle_deg`,
    or a point behind any of its cameras or on one's centre (MIN_DEPTH_FRACTION).
    """
    rays_c = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K).T
    rays = np.einsum("kij,kj->ki", T_wc[:, :3, :3], rays_c)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    C = T_wc[:, :3, 3]
    A_obs = np.eye(3) - rays[:, :, None] * rays[:, None, :]  # (K, 3, 3) projector orthogonal to the ray
    A = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(A, point_index, A_obs)
    np.add.at(b, point_index, np.einsum("kij,kj->ki", A_obs, C))
    # parallax: the largest angle between any ray and the mean ray of its point
    mean_ray = np.zeros((n_points, 3))
    np.add.at(mean_ray, point_index, rays)
    mean_ray /= np.maximum(np.linalg.norm(mean_ray, axis=1, keepdims=True), 1e-300)
    cosines = np.sum(rays * mean_ray[point_index], axis=1)
    min_cos = np.full(n_points, 1.0)
    np.minimum.at(min_cos, point_index, cosines)
    count = np.bincount(point_index, minlength=n_points)
    ok = (count >= 2) & (min_cos < np.cos(np.radians(min_angle_deg / 2.0)))
    A[~ok] = np.eye(3)
    X = np.linalg.solve(A, b[..., None])[..., 0]
    depth = np.sum((X[point_index] - C) * rays, axis=1)
    in_front = np.ones(n_points, bool)
    np.logical_and.at(in_front, point_index, clear_of_camera(point_index, X, C, depth))
    ok &= in_front & np.isfinite(X).all(axis=1)
    return X, ok


def clear_of_camera(point_index: np.ndarray, X: np.ndarray, C: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(K,) whether each observation's point lies in front of its camera and off its centre: depth above
    MIN_DEPTH_FRACTION of the point's distance from the farthest of its cameras.

    Where one camera's ray passes through another's centre, the rays meet there (a midpoint, or a bundle
    adjustment sliding a two-view point there, fits both views exactly), whatever the second camera saw;
    and a point that near a centre projects with f / depth pixels per unit, which leaves a bundle
    adjustment's linear system indeterminate. point_index (K,) rows of X (P, 3); C (K, 3) the observing
    camera centres; depth (K,) the point's depth in each."""
    farthest = np.zeros(len(X))
    np.maximum.at(farthest, point_index, np.linalg.norm(X[point_index] - C, axis=1))
    return depth > MIN_DEPTH_FRACTION * farthest[point_index]


def max_reprojection_px(
    point_index: np.ndarray, T_cw: np.ndarray, K: np.ndarray, uv: np.ndarray, X: np.ndarray
) -> np.ndarray:
    """(P,) each triangulated point's largest reprojection error (pixels) over its observations, inf
    where it lies behind one of them. point_index (K,), T_cw (K, 4, 4) world to camera, uv (K, 2),
    X (P, 3) as `triangulate_points` returns them."""
    Xc = np.einsum("kij,kj->ki", T_cw[:, :3, :3], X[point_index]) + T_cw[:, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = Xc @ K.T
        err = np.where(Xc[:, 2] > 0, np.linalg.norm(proj[:, :2] / proj[:, 2:3] - uv, axis=1), np.inf)
    worst = np.zeros(len(X))
    np.maximum.at(worst, point_index, err)
    return worst


def observation_planes(T_wc: np.ndarray, K: np.ndarray, obs_xy: np.ndarray) -> np.ndarray:
    """(K, 4) unit-normal world planes (a, d), a . X + d = 0, through each camera centre and image segment."""
    p1 = np.concatenate([obs_xy[:, :2], np.ones((len(obs_xy), 1))], 1)
    p2 = np.concatenate([obs_xy[:, 2:], np.ones((len(obs_xy), 1))], 1)
    l = np.cross(p1, p2)
    n_c = l @ K  # K^T l as rows
    n_w = np.einsum("kij,kj->ki", T_wc[:, :3, :3], n_c)
    norm = np.linalg.norm(n_w, axis=1, keepdims=True)
    n_w = n_w / np.maximum(norm, 1e-300)
    d = -np.sum(n_w * T_wc[:, :3, 3], axis=1, keepdims=True)
    return np.concatenate([n_w, d], 1)


def triangulate_line_two_view(plane_a: np.ndarray, plane_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of two planes (..., 4) -> Pluecker (..., 6) (|v| = 1) and the sine of their angle.

    The point is the one closest to the origin: X = A^T (A A^T)^-1 (-d) for A = [a1; a2].
    """
    a1, a2 = plane_a[..., :3], plane_b[..., :3]
    v = np.cross(a1, a2)
    sin = np.linalg.norm(v, axis=-1) / (np.linalg.norm(a1, axis=-1) * np.linalg.norm(a2, axis=-1))
    A = np.stack([a1, a2], -2)  # (..., 2, 3)
    rhs = -np.stack([plane_a[..., 3], plane_b[..., 3]], -1)
    G = A @ np.swapaxes(A, -1, -2)
    G = G + np.eye(2) * 1e-300
    X = np.einsum("...ji,...j->...i", A, np.linalg.solve(G, rhs[..., None])[..., 0])
    vn = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)
    return np.concatenate([np.cross(X, vn), vn], -1), sin


def triangulate_lines(
    line_index: np.ndarray,
    T_wc: np.ndarray,
    K: np.ndarray,
    obs_xy: np.ndarray,
    n_lines: int,
    min_angle_deg: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view line triangulation: the 2D null space of each line's stacked observation planes.

    The two right singular vectors with the smallest singular values are two homogeneous points of the
    line (either may be at infinity); their join is the line. Lines whose planes span less than
    `min_angle_deg` (e.g. the line lies along the baseline, or one view) are returned with ok False.
    Returns Pluecker L_w (M, 6) with |v| = 1 and ok (M,).
    """
    planes = observation_planes(T_wc, K, obs_xy)
    count = np.bincount(line_index, minlength=n_lines)
    kmax = max(int(count.max()) if len(count) else 0, 2)
    order = np.argsort(line_index, kind="stable")
    starts = np.concatenate([[0], np.cumsum(count)[:-1]])
    slot = np.arange(len(line_index)) - starts[line_index[order]]
    stacked = np.zeros((n_lines, kmax, 4))  # zero rows do not change the null space
    stacked[line_index[order], slot] = planes[order]
    _, s, Vt = np.linalg.svd(stacked, full_matrices=True)
    L = plucker_from_homogeneous_points(Vt[:, 3], Vt[:, 2])
    vn = np.linalg.norm(L[:, 3:], axis=1)
    ok = (count >= 2) & (s[:, 1] > np.sin(np.radians(min_angle_deg)) * s[:, 0]) & (vn > 1e-12)
    L = L / np.where(vn > 1e-12, vn, 1.0)[:, None]
    return L, ok & np.isfinite(L).all(axis=1)
