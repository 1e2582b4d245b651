"""Similarity transforms (Sim(3)) and Umeyama's least-squares fit between point sets.

One home for the alignment that evaluation (ATE against ground truth), mapping (merging segments)
and scaling (metres) all use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from papl_mapper.errors import GeometryError, InputError


@dataclass
class Sim3:
    """x_ref = scale * R @ x_est + t."""

    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)
    scale: float
    method: str = "Umeyama"

    @property
    def matrix(self) -> np.ndarray:
        """4x4 [sR t; 0 1]."""
        S = np.eye(4)
        S[:3, :3] = self.scale * self.R
        S[:3, 3] = self.t
        return S

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Transform points (..., 3)."""
        return self.scale * x @ self.R.T + self.t

    def apply_poses(self, T_wc: np.ndarray) -> np.ndarray:
        """Transform poses (N, 4, 4): rotation R @ R_wc, centre by the similarity (scale is not a pose)."""
        out = np.array(T_wc, np.float64, copy=True)
        out[:, :3, :3] = self.R @ T_wc[:, :3, :3]
        out[:, :3, 3] = self.apply(T_wc[:, :3, 3])
        return out


def umeyama(
    x: np.ndarray,
    y: np.ndarray,
    with_scale: bool = True,
    R_x: np.ndarray | None = None,
    R_y: np.ndarray | None = None,
    rank_tol: float = 1e-10,
) -> Sim3:
    """Least-squares similarity y ~ s R x + t for (N, 3) point sets (Umeyama 1991).

    Where the points are collinear (the rotation about their line is free) and orientations
    `R_x`, `R_y` (N, 3, 3) are given, the rotation is the chordal mean of R_y R_x^T instead and
    scale and translation are solved for it; `method` says which was used.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays, got {x.shape} and {y.shape}")
    n = len(x)
    if n < 3:
        raise InputError(f"only {n} matched poses; a Sim(3) alignment needs at least 3")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    sigma_x = float((xc**2).sum() / n)
    if sigma_x <= 1e-24 * max(1.0, float((x**2).sum() / n)):
        raise GeometryError(
            f"all {n} estimated positions coincide; the scale and rotation of the alignment are undefined"
        )
    cov = yc.T @ xc / n
    u, d, vt = np.linalg.svd(cov)
    method = "Umeyama"
    if d[1] <= rank_tol * d[0]:
        if R_x is None or R_y is None:
            raise GeometryError(
                f"the {n} matched positions are collinear: the Sim(3) rotation needs orientations"
            )
        M = (R_y @ np.swapaxes(R_x, 1, 2)).sum(axis=0)
        u, _, vt = np.linalg.svd(M)
        s = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
        R = u @ s @ vt
        c = float(np.einsum("ij,ij->", yc, xc @ R.T) / (n * sigma_x)) if with_scale else 1.0
        method = "rotation from orientations (positions collinear)"
    else:
        s = np.eye(3)
        if np.linalg.det(u) * np.linalg.det(vt) < 0:
            s[2, 2] = -1.0
        R = u @ s @ vt
        c = float(np.trace(np.diag(d) @ s) / sigma_x) if with_scale else 1.0
    if with_scale and not c > 0:
        raise GeometryError(
            f"the alignment scale came out {c:.3g}; the estimate does not follow the reference"
        )
    t = my - c * R @ mx
    return Sim3(R, t, c, method)
