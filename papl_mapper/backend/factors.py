"""gtsam factors for lines, axes and the gauge: gtsam.CustomFactor with vectorised numpy inside.

Residuals are whitened (divided by sigma) and robustified per observation (its 2-vector e) inside the
factor, the way gtsam's Robust noise model does it for a whole factor: for cost evaluation the factor
returns sqrt(2 rho(|e|)) e/|e|, so that gtsam's 0.5 |e'|^2 is the Huber cost rho; for linearisation it
returns sqrt(w) e with Jacobian sqrt(w) J, w = rho'(|e|)/|e| (iteratively reweighted least squares; the
exact Jacobian of sqrt(rho) would overshoot Gauss-Newton steps by up to 2x in the linear region).
A soft axis weight w_kj multiplies both by sqrt(w_kj). The factors therefore use a unit noise model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from papl_mapper import geometry as geo


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


def D(i: int) -> int:
    """Key of the private vanishing direction (Unit3) of temporary-VP line i."""
    return gtsam.symbol("d", int(i))


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


@dataclass
class LineTrackSpec:
    """One line factor: a line's (subset of) observations and how its line is parameterised."""

    kind: str  # "anchored" | "temporary_vp" | "orthonormal"
    line: int  # index in its LineGroup
    obs_kf: np.ndarray  # (k,) keyframe rows
    obs_xy: np.ndarray  # (k, 4)
    ref_kf: int = -1
    bearing: np.ndarray | None = None
    axes: np.ndarray | None = None  # (j,) axis indices (anchored)
    sqrt_w: np.ndarray | None = None  # (j,) sqrt of the soft weights


class LineFactorBuilder:
    """Makes the custom factors; knows which poses and axes are variables and the constants otherwise."""

    def __init__(
        self,
        K: np.ndarray,
        T_const: np.ndarray,
        pose_var: np.ndarray,
        axis_dirs: np.ndarray,
        axis_var: np.ndarray,
        sigma_px: float,
        huber_k: float,
    ) -> None:
        self.K = K
        self.T_const = T_const
        self.pose_var = pose_var
        self.axis_dirs = axis_dirs
        self.axis_var = axis_var
        self.sigma = sigma_px
        self.k = huber_k
        self.n_calls = 0

    def make(self, spec: LineTrackSpec) -> gtsam.CustomFactor:
        """A CustomFactor whose residual stacks (axes x observations x 2) endpoint distances."""
        keys: list[int] = []
        key_pos: dict[int, int] = {}

        def add(key: int) -> int:
            if key not in key_pos:
                key_pos[key] = len(keys)
                keys.append(key)
            return key_pos[key]

        if spec.kind == "orthonormal":
            add(U(spec.line))
            add(W(spec.line))
        else:
            add(R(spec.kind, spec.line))
            if spec.kind == "temporary_vp":
                add(D(spec.line))
            else:
                for a in spec.axes:
                    if self.axis_var[a]:
                        add(AX(a))
        ref_col = add(X(spec.ref_kf)) if spec.ref_kf >= 0 and self.pose_var[spec.ref_kf] else -1
        obs_cols = np.array([add(X(k)) if self.pose_var[k] else -1 for k in spec.obs_kf])
        n_obs = len(spec.obs_kf)
        fn = self._fn(spec, keys, ref_col, obs_cols, n_obs)
        n_ax = 1 if spec.kind != "anchored" else len(spec.axes)
        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n_obs * n_ax), keys, fn)

    def _fn(
        self, spec: LineTrackSpec, keys: list[int], ref_col: int, obs_cols: np.ndarray, n_obs: int
    ) -> Callable:
        K = self.K
        sigma, k = self.sigma, self.k
        obs_xy = spec.obs_xy
        T_obs_const = self.T_const[spec.obs_kf]
        var_obs = np.flatnonzero(obs_cols >= 0)
        T_ref_const = self.T_const[spec.ref_kf] if spec.ref_kf >= 0 else None
        kind = spec.kind
        axes = spec.axes
        sqrt_w = spec.sqrt_w if spec.sqrt_w is not None else np.ones(1)
        axis_cols = (
            np.array([keys.index(AX(a)) if self.axis_var[a] else -1 for a in axes])
            if kind == "anchored"
            else None
        )
        axis_const = self.axis_dirs[axes] if kind == "anchored" else None
        bearing = spec.bearing
        builder = self
        dims = [_dim(key) for key in keys]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            builder.n_calls += 1
            jac = H is not None
            T_obs = T_obs_const
            if len(var_obs):
                T_obs = T_obs_const.copy()
                for i in var_obs:
                    T_obs[i] = values.atPose3(keys[obs_cols[i]]).matrix()
            # ---- world line(s) and their Jacobians w.r.t. the line parameters
            if kind == "orthonormal":
                Urot = values.atRot3(keys[0]).matrix()
                phi = values.atVector(keys[1])[0]
                L = geo.plucker_from_ortho(Urot, np.asarray(phi))[None]  # (1, 6)
                J_par = geo.ortho_jacobian(Urot, np.asarray(phi))[None] if jac else None  # (1, 6, 4)
                J_ref = None
            else:
                r = values.atVector(keys[0])[0]
                T_ref = values.atPose3(keys[ref_col]).matrix() if ref_col >= 0 else T_ref_const
                if kind == "temporary_vp":
                    u3 = values.atUnit3(keys[1])
                    v = u3.point3()[None]
                    B = [u3.basis()] if jac else None
                else:
                    v = axis_const.copy()
                    B = [None] * len(axes)
                    for j, col in enumerate(axis_cols):
                        if col >= 0:
                            u3 = values.atUnit3(keys[col])
                            v[j] = u3.point3()
                            if jac:
                                B[j] = u3.basis()
                nj = len(v)
                if jac:
                    L, J_v, J_r, J_ref = geo.anchored_plucker(
                        v,
                        np.full(nj, r),
                        np.broadcast_to(bearing, (nj, 3)),
                        np.broadcast_to(T_ref, (nj, 4, 4)),
                        True,
                    )
                else:
                    L = geo.anchored_plucker(
                        v,
                        np.full(nj, r),
                        np.broadcast_to(bearing, (nj, 3)),
                        np.broadcast_to(T_ref, (nj, 4, 4)),
                    )
            nj = len(L)
            # ---- camera lines and errors for every (axis, observation)
            Lw = np.broadcast_to(L[:, None], (nj, n_obs, 6))
            Tb = np.broadcast_to(T_obs[None], (nj, n_obs, 4, 4))
            if not jac:
                Lc = geo.plucker_to_camera(Lw, Tb)
                e = geo.endpoint_errors(K, Lc, np.broadcast_to(obs_xy, (nj, n_obs, 4))) / sigma
                e = huber_cost_residual(e, k) * sqrt_w[:, None, None]
                return e.ravel()
            Lc, J_xc, J_L = geo.plucker_to_camera(Lw, Tb, jacobians=True)
            e, J_e = geo.endpoint_errors(K, Lc, np.broadcast_to(obs_xy, (nj, n_obs, 4)), jacobian=True)
            e /= sigma
            J_e /= sigma
            wgt = huber_sqrt_weight(e, k) * sqrt_w[:, None, None]  # (nj, n_obs, 1)
            e = e * wgt
            J_e = J_e * wgt[..., None]
            J_eL = J_e @ J_L  # (nj, n_obs, 2, 6): d e' / d L_w
            rows = 2 * nj * n_obs
            out = [np.zeros((rows, dim)) for dim in dims]
            if kind == "orthonormal":
                out[0][:] = (J_eL @ J_par[:, None, :, :3]).reshape(rows, 3)
                out[1][:] = (J_eL @ J_par[:, None, :, 3:]).reshape(rows, 1)
            else:
                out[0][:] = (J_eL @ J_r[:, None, :, None]).reshape(rows, 1)
                if kind == "temporary_vp":
                    out[1][:] = (J_eL @ (J_v[0] @ B[0])).reshape(rows, 2)
                else:
                    for j, col in enumerate(axis_cols):
                        if col >= 0:
                            blk = np.zeros((nj, n_obs, 2, 2))
                            blk[j] = J_eL[j] @ (J_v[j] @ B[j])
                            out[col] += blk.reshape(rows, 2)
                if ref_col >= 0:
                    out[ref_col] += (J_eL @ J_ref[:, None]).reshape(rows, 6)
            J_pose = J_e @ J_xc  # (nj, n_obs, 2, 6)
            for i in var_obs:
                blk = np.zeros((nj, n_obs, 2, 6))
                blk[:, i] = J_pose[:, i]
                out[obs_cols[i]] += blk.reshape(rows, 6)
            for i, o in enumerate(out):
                H[i] = o
            return e.ravel()

        return error


def _dim(key: int) -> int:
    """Tangent dimension of a variable, from its key's symbol character."""
    c = chr(gtsam.Symbol(key).chr())
    return {"x": 6, "r": 1, "s": 1, "w": 1, "a": 2, "d": 2, "u": 3}[c]


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
