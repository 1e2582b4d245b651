"""Camera pose from known structure when points are too few for PnP: rotation from matched directions,
then the camera centre from points and lines given that rotation (linear).

Given the rotation R_cw, a world point X seen at bearing b gives two linear equations on the camera
centre C, b x R_cw (X - C) = 0; a world line through P0 seen as a segment gives ONE: C lies in the plane
through the line whose world normal is R_cw^T n_c, n_c = K^T (p1 x p2) the back-projected plane of the
segment. (The plane must also contain the line's direction, but that condition involves R only.) So the
centre needs two points, a point and a line, or three lines whose planes are not parallel to one
direction (vertical lines alone leave the height free). Each equation's residual is a distance in world
units (of C from the point's ray, of C from the line's plane), so points and lines mix without weights.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.lines import line_point_dir
from papl_mapper.geometry.se3 import kabsch_rotation, skew


def rotation_from_directions(R_guess: np.ndarray, dirs_w: np.ndarray, dirs_c: np.ndarray) -> np.ndarray:
    """R_cw taking world directions (D, 3) to their matched camera directions (D, 3), sign-free.

    Each camera direction's sign is taken to agree with the guess (a line direction has none); two or
    more non-parallel pairs fix the rotation (Kabsch); one pair turns the guess by the smallest
    rotation that aligns it, leaving the rotation about that direction to the guess; none: the guess.
    """
    R_guess = np.asarray(R_guess, np.float64)
    dirs_w = np.asarray(dirs_w, np.float64).reshape(-1, 3)
    dirs_c = np.asarray(dirs_c, np.float64).reshape(-1, 3)
    if not len(dirs_w):
        return R_guess.copy()
    dirs_w = dirs_w / np.linalg.norm(dirs_w, axis=1, keepdims=True)
    dirs_c = dirs_c / np.linalg.norm(dirs_c, axis=1, keepdims=True)
    pred = dirs_w @ R_guess.T  # (D, 3) where the guess puts them
    dirs_c = dirs_c * np.where(np.sum(pred * dirs_c, 1) >= 0, 1.0, -1.0)[:, None]
    if len(dirs_w) >= 2 and np.linalg.matrix_rank(dirs_w, tol=1e-6) >= 2:
        return kabsch_rotation(dirs_w, dirs_c)
    # one direction: the smallest rotation from where the guess puts it to where it is seen
    a, b = pred[0], dirs_c[0]
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        return R_guess.copy()
    A = skew(axis / s)
    R_delta = np.eye(3) + s * A + (1.0 - c) * A @ A
    return R_delta @ R_guess


def centre_equations(
    R_cw: np.ndarray,
    K: np.ndarray,
    points_w: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    lines_w: np.ndarray | None = None,
    line_xy: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear equations A C = y on the camera centre C given R_cw: two rows per point (N, 3) seen at
    pixels (N, 2), one row per Pluecker line (M, 6) seen as a segment (M, 4) px. Returns A (2N+M, 3),
    y (2N+M,) and the feature of each row (2N+M,): point i is row feature i, line j is N + j."""
    R_cw = np.asarray(R_cw, np.float64)
    K_inv = np.linalg.inv(K)
    rows, rhs, feature = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, np.int64)]
    n = 0
    if points_w is not None and len(points_w):
        X = np.asarray(points_w, np.float64).reshape(-1, 3)
        n = len(X)
        b = np.column_stack([np.asarray(uv, np.float64).reshape(-1, 2), np.ones(n)]) @ K_inv.T
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        M = skew(b) @ R_cw  # (N, 3, 3): [b]x R (X - C) = 0
        # the two rows of [b]x orthogonal to b (the third is their combination): a basis of b's tangent plane
        _, _, Vt = np.linalg.svd(skew(b))
        T = Vt[:, :2, :]  # (N, 2, 3) rows spanning the range of [b]x^T
        A = np.einsum("nki,nij->nkj", T, M)  # (N, 2, 3)
        rows.append(A.reshape(-1, 3))
        rhs.append(np.einsum("nkj,nj->nk", A, X).reshape(-1))
        feature.append(np.repeat(np.arange(n), 2))
    if lines_w is not None and len(lines_w):
        L = np.asarray(lines_w, np.float64).reshape(-1, 6)
        xy = np.asarray(line_xy, np.float64).reshape(-1, 4)
        p1 = np.column_stack([xy[:, :2], np.ones(len(xy))])
        p2 = np.column_stack([xy[:, 2:], np.ones(len(xy))])
        n_c = np.cross(p1, p2) @ K  # K^T l per row
        n_w = n_c @ R_cw
        n_w /= np.linalg.norm(n_w, axis=1, keepdims=True)
        P0, _ = line_point_dir(L)
        rows.append(n_w)
        rhs.append(np.sum(n_w * P0, 1))
        feature.append(n + np.arange(len(L)))
    return np.concatenate(rows), np.concatenate(rhs), np.concatenate(feature)


def centre_from_rotation(
    R_cw: np.ndarray,
    K: np.ndarray,
    points_w: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    lines_w: np.ndarray | None = None,
    line_xy: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares camera centre C (3,) given R_cw from points and lines (see `centre_equations`),
    and the singular values (3,) of the equations, largest first: the smallest one near zero means
    the features leave C free along a direction (then C is the minimum-norm solution)."""
    A, y, _ = centre_equations(R_cw, K, points_w, uv, lines_w, line_xy)
    if len(A) == 0:
        return np.zeros(3), np.zeros(3)
    C, _, _, sv = np.linalg.lstsq(A, y, rcond=None)
    return C, np.pad(sv, (0, 3 - len(sv)))
