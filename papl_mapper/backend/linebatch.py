"""Line factors evaluated in one vectorised numpy pass per representation, served to gtsam per factor.

gtsam calls a CustomFactor's Python function once per factor; doing the line algebra there pays numpy's
per-call overhead once per factor, far too slow for thousands of lines (the batched cost is in
benchmarks/RESULTS.md, ba_scale). Here every factor of a kind shares one `LineBatch`: the first factor
called with new variable values triggers one vectorised evaluation of ALL units (line x axis x
observation) -- residuals and Jacobian blocks scattered into a preallocated buffer -- and each factor
then returns its slice.
Freshness is exact, not assumed: each factor compares its own variables (read from the Values it was
given) with the snapshot the batch was computed from and recomputes on any difference.

Robust loss and soft weights are as described in `factors.py` (Huber per observation, IRLS Jacobian).
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from papl_mapper import geometry as geo
from papl_mapper.backend.factors import AX, RS, D, F, R, U, W, X, _dim, huber_cost_residual, huber_sqrt_weight
from papl_mapper.backend.problem import KIND_ANCHORED, KIND_ORTHO, KIND_TVP, LineGroup

_POSE, _VEC, _UNIT, _ROT, _VEC2 = 0, 1, 2, 3, 4
KIND_FIXDIR = "fixed_direction"  # the 2-parameter baseline: L = (P x d, d), P = P0 + B(d) (a, b)


class LineBatch:
    """All line factors of one representation kind (anchored, temporary-VP or orthonormal)."""

    def __init__(
        self,
        kind: str,
        grp: LineGroup,
        K: np.ndarray,
        T_const: np.ndarray,
        pose_var: np.ndarray,
        axis_dirs: np.ndarray,
        axis_var: np.ndarray,
        sigma_px: float,
        huber_k: float,
        offset: bool = False,
    ) -> None:
        self.kind, self.grp, self.K = kind, grp, K
        self.offset = offset and kind in (KIND_ANCHORED, KIND_TVP)  # (r, s) per line instead of r
        self.T_const, self.pose_var = T_const, pose_var
        self.axis_dirs, self.axis_var = axis_dirs, axis_var
        self.sigma, self.k = sigma_px, huber_k
        if kind == KIND_FIXDIR:  # direction (its axis at the start) and reference point per line, held fixed
            self.P0, self.d = geo.line_point_dir(grp.L0)
            self.Bd = geo.tangent_basis(self.d)
        if kind == KIND_ORTHO:  # (U, W) of line i describe it in its own frame (problem.LineGroup)
            self.to_world = geo.local_to_world(grp.frame_origin, grp.frame_scale)
        self.snap: dict | None = None
        self.has_jac = False
        self.n_evaluations = 0
        self.factors: list[gtsam.CustomFactor] = []
        self._layout()

    # ---- layout: units, factors, keys and Jacobian blocks ------------------------------------

    def _layout(self) -> None:
        grp, kind = self.grp, self.kind
        u_line, u_axis, u_obs, u_w, u_row = [], [], [], [], []
        offs: dict[str, list[int]] = {name: [] for name in ("p0", "p1", "ref", "obs")}
        self.f_units: list[tuple[int, int]] = []
        self.f_keys: list[list[int]] = []
        self.f_checks: list[list[tuple[int, int, int]]] = []
        self.f_blocks: list[list[tuple[int, int, int]]] = []  # (offset, rows, dim) per key
        total = 0
        for i in range(len(grp)):
            s, e = int(grp.obs_start[i]), int(grp.obs_start[i + 1])
            if kind == KIND_ANCHORED:
                axes = np.flatnonzero(grp.weights[i] > 0)
                sqrt_w = np.sqrt(grp.weights[i, axes])
            else:
                axes, sqrt_w = np.array([-1]), np.ones(1)
            for obs_list in [list(range(s, e))]:
                kl = _KeyList()
                add = kl.add
                if kind == KIND_ORTHO:
                    c0, c1 = add(U(i), (_ROT, i)), add(W(i), (_VEC, i))
                    c_ax = {-1: c1}
                elif kind == KIND_FIXDIR:
                    c0 = add(F(i), (_VEC2, i))
                    c_ax = {}
                elif self.offset:
                    c0 = add(RS(kind, i), (_VEC2, i))
                else:
                    c0 = add(R(kind, i), (_VEC, i))
                if kind == KIND_TVP:
                    c_ax = {-1: add(D(i), (_UNIT, i))}
                elif kind == KIND_ANCHORED:
                    c_ax = {int(a): add(AX(a), (_UNIT, int(a))) for a in axes if self.axis_var[a]}
                ref = int(grp.ref_kf[i]) if kind != KIND_FIXDIR else -1
                c_ref = add(X(ref), (_POSE, ref)) if ref >= 0 and self.pose_var[ref] else -1
                c_obs = [
                    add(X(grp.obs_kf[o]), (_POSE, int(grp.obs_kf[o]))) if self.pose_var[grp.obs_kf[o]] else -1
                    for o in obs_list
                ]
                keys, checks = kl.keys, kl.checks
                rows = 2 * len(axes) * len(obs_list)
                dims = [_dim(key) for key in keys]
                blocks = []
                for d in dims:
                    blocks.append((total, rows, d))
                    total += rows * d
                u0 = len(u_line)
                for j, a in enumerate(axes):
                    for n_o, o in enumerate(obs_list):
                        row = 2 * (j * len(obs_list) + n_o)
                        u_line.append(i)
                        u_axis.append(int(a))
                        u_obs.append(o)
                        u_w.append(sqrt_w[j])
                        u_row.append(row)
                        offs["p0"].append(blocks[c0][0])
                        cax = c_ax.get(int(a), -1) if kind != KIND_ORTHO else c_ax[-1]
                        offs["p1"].append(blocks[cax][0] if cax >= 0 else -1)
                        offs["ref"].append(blocks[c_ref][0] if c_ref >= 0 else -1)
                        offs["obs"].append(blocks[c_obs[n_o]][0] if c_obs[n_o] >= 0 else -1)
                self.f_units.append((u0, len(u_line)))
                self.f_keys.append(keys)
                self.f_checks.append(checks)
                self.f_blocks.append(blocks)
        self.u_line = np.array(u_line, np.int64)
        self.u_axis = np.array(u_axis, np.int64)
        self.u_obs = np.array(u_obs, np.int64)
        self.u_w = np.array(u_w, np.float64)
        self.u_row = np.array(u_row, np.int64)
        self.buffer = np.zeros(total)
        d0, d1 = {KIND_ORTHO: (3, 1), KIND_FIXDIR: (2, 1)}.get(kind, (2 if self.offset else 1, 2))
        self._idx = {
            name: _block_index(np.array(offs[name], np.int64), self.u_row, dim)
            for name, dim in (("p0", d0), ("p1", d1), ("ref", 6), ("obs", 6))
        }
        self.f_views = [
            [self.buffer[o : o + r * d].reshape(r, d) for o, r, d in blocks] for blocks in self.f_blocks
        ]

    # ---- factors -----------------------------------------------------------------------------

    def make_factors(self) -> list[gtsam.CustomFactor]:
        """One gtsam.CustomFactor per track with a unit noise model."""
        out = []
        for f, keys in enumerate(self.f_keys):
            u0, u1 = self.f_units[f]
            out.append(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * (u1 - u0)), keys, self._fn(f)))
        self.factors = out
        return out

    def _fn(self, f: int) -> Callable:
        u0, u1 = self.f_units[f]
        checks = self.f_checks[f]
        views = self.f_views[f]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
            jac = H is not None
            if not self._fresh(checks, values) or (jac and not self.has_jac):
                self.compute(values, jac)
            if not jac:
                return self.res_cost[u0:u1].ravel()
            for i, view in enumerate(views):
                H[i] = view
            return self.res_lin[u0:u1].ravel()

        return error

    def cost(self, values: gtsam.Values) -> float:
        """The summed cost of every factor of the batch at `values` (gtsam's 0.5 |r|^2 per factor)."""
        self.compute(values, False)
        return 0.5 * float(np.sum(self.res_cost**2))

    def _fresh(self, checks: list[tuple[int, int, int]], values: gtsam.Values) -> bool:
        """Whether `values` holds, bit for bit, the variables of these checks that the batch was computed
        from (bytes comparison: five times cheaper than np.array_equal, and as exact)."""
        snap = self.snap
        if snap is None:
            return False
        raw = snap["bytes"]
        for code, key, idx in checks:
            if code == _POSE:
                if values.atPose3(key).matrix().tobytes() != raw["T"][idx]:
                    return False
            elif code == _VEC:
                if values.atVector(key)[0] != snap["s"][idx]:
                    return False
            elif code == _VEC2:
                if values.atVector(key).tobytes() != raw["ab"][idx]:
                    return False
            elif code == _UNIT:
                if values.atUnit3(key).point3().tobytes() != raw["v"][idx]:
                    return False
            elif values.atRot3(key).matrix().tobytes() != raw["U"][idx]:
                return False
        return True

    # ---- the vectorised evaluation --------------------------------------------------------------

    def _snapshot(self, values: gtsam.Values, jac: bool) -> dict:
        snap = self._read(values, jac)
        snap["bytes"] = {
            name: [row.tobytes() for row in snap[name]] for name in ("T", "ab", "v", "U") if name in snap
        }
        return snap

    def _read(self, values: gtsam.Values, jac: bool) -> dict:
        """The batch's variables out of `values` as arrays (constant poses from T_const)."""
        grp, kind = self.grp, self.kind
        n = len(grp)
        T = self.T_const.copy()
        for i in np.flatnonzero(self.pose_var):
            T[i] = values.atPose3(X(i)).matrix()
        snap: dict = {"T": T}
        if kind == KIND_FIXDIR:
            snap["ab"] = np.array([values.atVector(F(i)) for i in range(n)]).reshape(n, 2)
            return snap
        if kind == KIND_ORTHO:
            snap["U"] = np.array([values.atRot3(U(i)).matrix() for i in range(n)]).reshape(n, 3, 3)
            snap["s"] = np.array([values.atVector(W(i))[0] for i in range(n)])
            return snap
        if self.offset:
            snap["ab"] = np.array([values.atVector(RS(kind, i)) for i in range(n)]).reshape(n, 2)
        else:
            snap["s"] = np.array([values.atVector(R(kind, i))[0] for i in range(n)])
        if kind == KIND_TVP:
            u3 = [values.atUnit3(D(i)) for i in range(n)]
        else:
            u3 = [values.atUnit3(AX(a)) if self.axis_var[a] else None for a in range(len(self.axis_dirs))]
        v = np.array([u.point3() if u is not None else self.axis_dirs[a] for a, u in enumerate(u3)]).reshape(
            -1, 3
        )
        snap["v"] = v
        B = np.zeros((len(u3), 3, 2))
        if jac:
            for a, u in enumerate(u3):
                if u is not None:
                    B[a] = u.basis()
        snap["B"] = B
        return snap

    def compute(self, values: gtsam.Values, jac: bool) -> None:
        """Evaluate every unit at `values`: residuals (cost and IRLS forms) and, with `jac`, the blocks."""
        self.n_evaluations += 1
        snap = self._snapshot(values, jac)
        grp, kind, K = self.grp, self.kind, self.K
        line, obs = self.u_line, self.u_obs
        T = snap["T"]
        if kind == KIND_FIXDIR:
            L, J_par = self.lines_from(snap["ab"], line, jac)
        elif kind == KIND_ORTHO:
            Uu, phi = snap["U"][line], snap["s"][line]
            M = self.to_world[line]
            L = geo.plucker_from_ortho(Uu, phi, M)
            J_par = geo.ortho_jacobian(Uu, phi, M) if jac else None
        else:
            vi = line if kind == KIND_TVP else self.u_axis
            if self.offset:
                out = geo.anchored_offset_plucker(
                    snap["v"][vi],
                    snap["ab"][line],
                    grp.bearing[line],
                    grp.offset_dir[line],
                    T[grp.ref_kf[line]],
                    jac,
                )
            else:
                out = geo.anchored_plucker(
                    snap["v"][vi], snap["s"][line], grp.bearing[line], T[grp.ref_kf[line]], jac
                )
            L = out[0] if jac else out
        T_obs = T[grp.obs_kf[obs]]
        xy = grp.obs_xy[obs]
        w = self.u_w[:, None]
        if not jac:
            e = geo.endpoint_errors(K, geo.plucker_to_camera(L, T_obs), xy) / self.sigma
            self.res_cost = huber_cost_residual(e, self.k) * w
            self.res_lin = e * huber_sqrt_weight(e, self.k) * w
            self.snap, self.has_jac = snap, False
            return
        Lc, J_xc, J_L = geo.plucker_to_camera(L, T_obs, jacobians=True)
        e, J_e = geo.endpoint_errors(K, Lc, xy, jacobian=True)
        e /= self.sigma
        J_e /= self.sigma
        self.res_cost = huber_cost_residual(e, self.k) * w
        wgt = huber_sqrt_weight(e, self.k) * w  # (U, 1)
        self.res_lin = e * wgt
        J_e *= wgt[..., None]
        J_eL = J_e @ J_L  # (U, 2, 6)
        buf = self.buffer
        buf[:] = 0.0
        if kind == KIND_FIXDIR:
            blocks = {"p0": J_eL @ J_par}
        elif kind == KIND_ORTHO:
            blocks = {"p0": J_eL @ J_par[..., :3], "p1": J_eL @ J_par[..., 3:]}
        else:
            _, J_v, J_r, J_ref = out
            Bu = snap["B"][vi]
            J_r = J_r if self.offset else J_r[..., None]
            blocks = {"p0": J_eL @ J_r, "p1": J_eL @ (J_v @ Bu), "ref": J_eL @ J_ref}
        blocks["obs"] = J_e @ J_xc
        for name in ("p0", "p1", "obs"):
            if name not in blocks:
                continue
            sel, idx = self._idx[name]
            if len(sel):
                buf[idx] = blocks[name][sel]
        if "ref" in blocks:  # may share a key (hence rows) with the observation block: accumulate
            sel, idx = self._idx["ref"]
            if len(sel):
                np.add.at(buf, idx, blocks["ref"][sel])
        self.snap, self.has_jac = snap, True

    def lines_from(self, ab: np.ndarray, line: np.ndarray, jac: bool = False):
        """Fixed-direction lines (..., 6) for positions ab (n, 2) at rows `line`, and dL/dab (..., 6, 2)."""
        P = self.P0[line] + np.einsum("nij,nj->ni", self.Bd[line], ab[line])
        d = self.d[line]
        L = np.concatenate([np.cross(P, d), d], -1)
        if not jac:
            return L, None
        J = np.zeros(L.shape + (2,))
        J[..., :3, :] = -geo.skew(d) @ self.Bd[line]
        return L, J


class _KeyList:
    """The keys of one factor in first-use order, with what to compare for freshness."""

    def __init__(self) -> None:
        self.keys: list[int] = []
        self.checks: list[tuple[int, int, int]] = []
        self.pos: dict[int, int] = {}

    def add(self, key: int, check: tuple[int, int]) -> int:
        if key not in self.pos:
            self.pos[key] = len(self.keys)
            self.keys.append(key)
            self.checks.append((check[0], key, check[1]))
        return self.pos[key]


def _block_index(off: np.ndarray, row: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Units with a block (off >= 0) and their (n, 2, dim) flat buffer indices (row-major blocks)."""
    sel = np.flatnonzero(off >= 0)
    idx = off[sel, None, None] + (row[sel, None, None] + np.arange(2)[None, :, None]) * dim + np.arange(dim)
    return sel, idx
