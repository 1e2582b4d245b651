"""Keys, the per-observation robust loss, and the axis-prior and scale-gauge factors (gtsam.CustomFactor).

Residuals are whitened (divided by sigma) and robustified per observation (its 2-vector e) inside the
factor, the way gtsam's Robust noise model does it for a whole factor: for cost evaluation the factor
returns sqrt(2 rho(|e|)) e/|e|, so that gtsam's 0.5 |e'|^2 is the Huber cost rho; for linearisation it
returns sqrt(w) e with Jacobian sqrt(w) J, w = rho'(|e|)/|e| (iteratively reweighted least squares; the
exact Jacobian of sqrt(rho) would overshoot Gauss-Newton steps by up to 2x in the linear region).
A soft axis weight w_kj multiplies both by sqrt(w_kj). The factors therefore use a unit noise model.
"""

from __future__ import annotations

import gtsam
import numpy as np

from papl_mapper import geometry as geo


def symbols(c: str, index: np.ndarray) -> list[int]:
    """gtsam.symbol(c, i) for every i of `index`, computed in one pass (a symbol key is the character in
    the top byte and the index below it)."""
    return ((ord(c) << 56) + np.asarray(index, np.int64)).tolist()


def X(i: int) -> int:
    """Key of keyframe pose row i."""
    return gtsam.symbol("x", int(i))


def P(i: int) -> int:
    """Key of point i (index into Problem.pt_rows)."""
    return gtsam.symbol("p", int(i))


def AX(i: int) -> int:
    """Key of principal axis i (Unit3)."""
    return gtsam.symbol("a", int(i))


def R(kind: str, i: int) -> int:
    """Key of the inverse depth (Vector1) of line i of an anchored ('r') or temporary-VP ('s') group."""
    return gtsam.symbol("r" if kind == "anchored" else "s", int(i))


def RS(kind: str, i: int) -> int:
    """Key of the (inverse depth, sideways offset px) (Vector2) of line i of an anchored ('g') or
    temporary-VP ('h') group when BAConfig.anchor_offset is on."""
    return gtsam.symbol("g" if kind == "anchored" else "h", int(i))


def D(i: int) -> int:
    """Key of the private vanishing direction (Unit3) of temporary-VP line i."""
    return gtsam.symbol("d", int(i))


def F(i: int) -> int:
    """Key of the 2-dof position (Vector2) of fixed-direction (2-parameter baseline) line i."""
    return gtsam.symbol("f", int(i))


def U(i: int) -> int:
    """Key of orthonormal line i's U (Rot3)."""
    return gtsam.symbol("u", int(i))


def W(i: int) -> int:
    """Key of orthonormal line i's W angle phi (Vector1)."""
    return gtsam.symbol("w", int(i))


def huber_cost_residual(e: np.ndarray, k: float) -> np.ndarray:
    """Per 2-vector (..., 2): e' with 0.5 |e'|^2 = Huber(|e|) (k |e| - k^2/2 beyond k)."""
    a = np.linalg.norm(e, axis=-1, keepdims=True)
    big = a > k
    scale = np.where(big, np.sqrt(np.maximum(2.0 * k * a - k * k, 0.0)) / np.where(big, a, 1.0), 1.0)
    return e * scale


def huber_sqrt_weight(e: np.ndarray, k: float) -> np.ndarray:
    """Per 2-vector (..., 2): sqrt of the IRLS weight min(1, k / |e|), shape (..., 1)."""
    a = np.linalg.norm(e, axis=-1, keepdims=True)
    return np.sqrt(np.minimum(1.0, k / np.maximum(a, 1e-300)))


def _dim(key: int) -> int:
    """Tangent dimension of a variable, from its key's symbol character."""
    c = chr(gtsam.Symbol(key).chr())
    return {"x": 6, "r": 1, "s": 1, "g": 2, "h": 2, "w": 1, "a": 2, "d": 2, "u": 3, "f": 2}[c]


def axis_prior_factor(axis: int, v0: np.ndarray, sigma_rad: float) -> gtsam.CustomFactor:
    """The paper's e_a: keeps an axis near its direction before BA. e = B0^T v / sigma (2-vector)."""
    B0 = geo.tangent_basis(v0)
    key = AX(axis)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        u3 = values.atUnit3(key)
        v = u3.point3()
        if H is not None:
            H[0] = B0.T @ u3.basis() / sigma_rad
        return B0.T @ v / sigma_rad

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [key], error)


def scale_prior_factor(
    row_a: int, T_a: np.ndarray, row_b: int, distance: float, sigma: float
) -> gtsam.CustomFactor:
    """Monocular scale gauge: |c_b - c_a| = distance, with keyframe a held fixed (constant T_a)."""
    key = X(row_b)
    c_a = T_a[:3, 3]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        Tb = values.atPose3(key).matrix()
        dvec = Tb[:3, 3] - c_a
        dist = np.linalg.norm(dvec)
        if H is not None:
            Hm = np.zeros((1, 6))
            Hm[0, 3:] = (dvec / max(dist, 1e-300)) @ Tb[:3, :3] / sigma
            H[0] = Hm
        return np.array([(dist - distance) / sigma])

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [key], error)
