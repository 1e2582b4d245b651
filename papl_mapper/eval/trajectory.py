"""Trajectories: TUM read/write, timestamp association, Umeyama Sim(3) alignment, ATE and RPE.

The association and the alignment follow evo (`evo_ape tum gt est -as`): the shorter trajectory's
stamps are matched to the nearest stamp of the longer one within `max_diff`, and the estimate is
aligned to the reference by Umeyama's closed form with scale, so ATE RMSE agrees with evo.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from papl_mapper.errors import GeometryError, InputError

log = logging.getLogger(__name__)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


@dataclass
class Trajectory:
    """Timestamped camera poses `T_wc` (N, 4, 4) float64, sorted by time."""

    timestamps: np.ndarray  # (N,) float64, seconds
    T_wc: np.ndarray  # (N, 4, 4) float64, camera -> world
    name: str = ""

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, np.float64).reshape(-1)
        self.T_wc = np.asarray(self.T_wc, np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.T_wc):
            raise InputError(
                f"{self.name or 'trajectory'}: {len(self.timestamps)} timestamps for {len(self.T_wc)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.T_wc[:, :3, 3]

    def subset(self, idx: np.ndarray) -> Trajectory:
        """The poses at indices `idx`, in that order."""
        return Trajectory(self.timestamps[idx], self.T_wc[idx], self.name)

    def path_length(self) -> float:
        """Sum of the distances between consecutive camera centres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM file (`t tx ty tz qx qy qz qw` per line, '#' comments); InputError names file and line."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such trajectory file")
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text TUM trajectory ({exc})") from exc
    rows, line_no = [], []
    for k, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(
                f"{path}: line {k} has {len(parts)} values, a TUM row is 't tx ty tz qx qy qz qw' (8 values)"
            )
        try:
            values = [float(v) for v in parts]
        except ValueError as exc:
            raise InputError(f"{path}: line {k} holds a non-number ({exc})") from exc
        if not np.isfinite(values).all():
            raise InputError(f"{path}: line {k} holds NaN or infinite values")
        q_norm = float(np.linalg.norm(values[4:]))
        if q_norm < 1e-6:
            raise InputError(f"{path}: line {k} has a zero quaternion")
        rows.append(values)
        line_no.append(k)
    if not rows:
        raise InputError(f"{path}: holds no poses")
    data, lines = np.asarray(rows, np.float64), np.asarray(line_no)
    t = data[:, 0]
    if np.any(np.diff(t) < 0):
        log.warning("%s: timestamps are not sorted; sorting them", path)
        order = np.argsort(t, kind="stable")
        data, t, lines = data[order], t[order], lines[order]
    dup = np.flatnonzero(np.diff(t) == 0)
    if dup.size:
        i = dup[0]
        raise InputError(
            f"{path}: lines {lines[i]} and {lines[i + 1]} share timestamp {float(t[i])!r}; "
            "each pose needs its own timestamp"
        )
    T = np.repeat(np.eye(4)[None], len(data), axis=0)
    T[:, :3, :3] = Rotation.from_quat(data[:, 4:8]).as_matrix()  # scalar-last (x, y, z, w), normalised
    T[:, :3, 3] = data[:, 1:4]
    return Trajectory(t, T, path.name)


def write_tum(path: str | os.PathLike, traj: Trajectory) -> Path:
    """Write `t tx ty tz qx qy qz qw` rows with full float precision (atomically)."""
    path = Path(path)
    q = Rotation.from_matrix(traj.T_wc[:, :3, :3]).as_quat()  # (N, 4) x y z w
    rows = np.column_stack([traj.timestamps, traj.positions, q])
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as fh:
        fh.write(TUM_HEADER + "\n")
        np.savetxt(fh, rows, fmt="%.17g")
    os.replace(tmp, path)
    return path


def associate(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i1, i2) pairing stamps of `stamps_1` with the nearest of sorted `stamps_2` within max_diff.

    Same rule as evo's `matching_time_indices` (ties go to the earlier stamp), vectorised.
    """
    s1 = np.asarray(stamps_1, np.float64)
    s2 = np.asarray(stamps_2, np.float64)
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    upper = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    diff_ub = s2[upper] - s1
    diff_lb = np.where(upper > 0, s1 - s2[np.maximum(upper - 1, 0)], np.inf)
    in_range = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = in_range & (take_ub | take_lb)
    i2 = np.where(take_ub, upper, upper - 1)
    return np.flatnonzero(ok).astype(np.int64), i2[ok].astype(np.int64)


def associate_trajectories(
    ref: Trajectory, est: Trajectory, max_diff: float
) -> tuple[np.ndarray, np.ndarray]:
    """(i_ref, i_est) of matched poses, starting from the shorter trajectory as evo does."""
    if len(est) <= len(ref):  # evo: the second (estimate) unless the first is strictly shorter
        i_est, i_ref = associate(est.timestamps, ref.timestamps, max_diff)
    else:
        i_ref, i_est = associate(ref.timestamps, est.timestamps, max_diff)
    return i_ref, i_est


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


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """(...) rotation angles in radians of (..., 3, 3) rotations; accurate near 0 and pi."""
    tr = np.trace(R, axis1=-2, axis2=-1)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), 0.5 * (tr - 1.0))


def ate_errors(ref_positions: np.ndarray, est_positions_aligned: np.ndarray) -> np.ndarray:
    """(N,) translation errors between matched, aligned positions."""
    return np.linalg.norm(ref_positions - est_positions_aligned, axis=1)


def rpe(T_ref: np.ndarray, T_est: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair relative pose errors (translation, rotation in degrees) for pose pairs (i, i + delta).

    E_i = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q the reference and P the (aligned) estimate, as evo's RPE.
    """
    if delta < 1:
        raise ValueError(f"RPE delta must be >= 1, got {delta}")
    if len(T_ref) <= delta:
        return np.zeros(0), np.zeros(0)
    dq = _inv(T_ref[:-delta]) @ T_ref[delta:]
    dp = _inv(T_est[:-delta]) @ T_est[delta:]
    E = _inv(dq) @ dp
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E[:, :3, :3]))


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (N, 4, 4)."""
    out = np.repeat(np.eye(4)[None], len(T), axis=0)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -(Rt @ T[:, :3, 3, None])[..., 0]
    return out


def rmse(x: np.ndarray) -> float:
    """Root mean square of x (NaN for an empty array)."""
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")
