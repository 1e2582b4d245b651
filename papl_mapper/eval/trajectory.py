"""Trajectory metrics: timestamp association, ATE and RPE (files: `papl_mapper.trajectory_io`; the
Sim(3) alignment: `papl_mapper.geometry.similarity`).

The association and the alignment follow evo (`evo_ape tum gt est -as`): the shorter trajectory's
stamps are matched to the nearest stamp of the longer one within `max_diff`, and the estimate is
aligned to the reference by Umeyama's closed form with scale, so ATE RMSE agrees with evo.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.se3 import invert
from papl_mapper.trajectory_io import Trajectory


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
    dq = invert(T_ref[:-delta]) @ T_ref[delta:]
    dp = invert(T_est[:-delta]) @ T_est[delta:]
    E = invert(dq) @ dp
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E[:, :3, :3]))


def rmse(x: np.ndarray) -> float:
    """Root mean square of x (NaN for an empty array)."""
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")
