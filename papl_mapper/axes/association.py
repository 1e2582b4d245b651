"""Soft line-axis association by EM (paper "Data Association").

Per line, the input is the set of vanishing directions it was observed with (rotated to the world
frame); its evidence for axis j is the mean angle between those directions and the axis. Lines
beyond a loose gate get weight 0; inside it the likelihood is a zero-mean normal on that angle.
EM alternates the weights w_kj (E) and the axes' mixing proportions (M).
"""

from __future__ import annotations

import numpy as np

from papl_mapper.axes.config import AxesConfig
from papl_mapper.axes.directions import unit_rows
from papl_mapper.errors import GeometryError


def pack_observations(obs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """List of per-line (k_i, 3) arrays -> packed (M, 3) directions and (M,) line index."""
    if not obs:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    arrays = [np.asarray(o, np.float64).reshape(-1, 3) for o in obs]
    index = np.concatenate([np.full(len(o), i, np.int64) for i, o in enumerate(arrays)])
    return np.concatenate(arrays), index


def mean_angles_deg(
    obs_dirs_w: np.ndarray, line_index: np.ndarray, n_lines: int, axes: np.ndarray
) -> np.ndarray:
    """(N, A) mean unsigned angle between each line's observed directions and each axis (inf if none)."""
    obs = unit_rows(obs_dirs_w, "observed vanishing directions")  # (M, 3)
    axes = unit_rows(axes, "axes") if len(axes) else np.zeros((0, 3))
    line_index = np.asarray(line_index, np.int64)
    if len(line_index) != len(obs):
        raise GeometryError(f"line index has {len(line_index)} entries for {len(obs)} observations")
    if len(line_index) and (line_index.min() < 0 or line_index.max() >= n_lines):
        raise GeometryError(f"line index outside 0..{n_lines - 1}")
    ang = np.degrees(np.arccos(np.clip(np.abs(obs @ axes.T), 0.0, 1.0)))  # (M, A)
    sums = np.zeros((n_lines, len(axes)))
    np.add.at(sums, line_index, ang)
    counts = np.bincount(line_index, minlength=n_lines).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = sums / counts[:, None]
    out[counts == 0] = np.inf
    return out


def associate(
    line_obs_dirs_w: list[np.ndarray] | tuple[np.ndarray, np.ndarray],
    axes: np.ndarray,
    config: AxesConfig | None = None,
    n_lines: int | None = None,
    *,
    line_dirs_w: np.ndarray | None = None,
) -> np.ndarray:
    """Soft weights (N, A): w_kj >= 0, rows sum to 1, or to 0 for a line outside every gate.

    `line_obs_dirs_w` is either a list (one (k,3) array per line) or a packed pair
    (directions (M,3), line index (M,)) with `n_lines` lines. The gate is on the angle between the
    line's estimated 3D direction `line_dirs_w` (N,3) and the axis when given (as in the paper),
    else on the mean vanishing-direction angle; a line with no observation gets weight 0.
    """
    config = config or AxesConfig()
    if isinstance(line_obs_dirs_w, tuple):
        obs, index = line_obs_dirs_w
        n = int(n_lines if n_lines is not None else (int(np.max(index)) + 1 if len(index) else 0))
    else:
        obs, index = pack_observations(line_obs_dirs_w)
        n = len(line_obs_dirs_w)
    axes = np.asarray(axes, np.float64).reshape(-1, 3)
    if n == 0 or len(axes) == 0:
        return np.zeros((n, len(axes)))
    ang = mean_angles_deg(obs, index, n, axes)  # (N, A)
    gated = ang <= config.gate_deg
    if line_dirs_w is not None:
        dirs = unit_rows(line_dirs_w, "line directions")
        if len(dirs) != n:
            raise GeometryError(f"line_dirs_w has {len(dirs)} rows for {n} lines")
        gate_ang = np.degrees(np.arccos(np.clip(np.abs(dirs @ unit_rows(axes, "axes").T), 0.0, 1.0)))
        gated = (gate_ang <= config.gate_deg) & np.isfinite(ang)
    lik = np.where(gated, np.exp(-0.5 * (np.where(gated, ang, 0.0) / config.sigma_deg) ** 2), 0.0)
    prior = np.full(len(axes), 1.0 / len(axes))
    w = np.zeros_like(lik)
    for _ in range(max(1, config.em_iterations)):
        num = lik * prior[None, :]
        den = num.sum(axis=1, keepdims=True)
        w = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
        has = den[:, 0] > 0
        if not has.any():
            break
        new_prior = w[has].sum(axis=0) + 1e-9
        new_prior /= new_prior.sum()
        if np.allclose(new_prior, prior, atol=1e-10):
            prior = new_prior
            break
        prior = new_prior
    num = lik * prior[None, :]
    den = num.sum(axis=1, keepdims=True)
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)
