"""Soft line-axis association by EM (paper "Data Association").

Per line, the input is the set of vanishing directions it was observed with (rotated to the world
frame); its evidence for axis j is the mean angle between those directions and the axis. Lines
beyond a loose gate get weight 0; inside it the likelihood is a zero-mean normal on that angle.
EM alternates the weights w_kj (E) and the axes' mixing proportions (M). The vanishing directions
are per frame; `direction_checked` then takes from each line the axes its segments' back-projection
planes reject, the paper's gate on the line's own direction where its views decide that direction.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtri  # chi-square quantiles without scipy.stats' much longer import

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


def direction_checked(
    normals_w: np.ndarray,
    length_px: np.ndarray,
    obs_line: np.ndarray,
    weights: np.ndarray,
    axes: np.ndarray,
    config: AxesConfig,
    sigma_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The line-axis `weights` (N, A) without the axes each line's segments reject, renormalised, and
    the (N,) lines left with none. A line's back-projection planes (unit world normals (K,3) of the
    observations of line `obs_line`) reject an axis when it lies outside them beyond their noise
    (chi-square over the line's views at `config.direction_alpha`) and the direction that fits them
    best lies beyond `config.gate_deg` from it.

    A plane tilts by about sqrt(2) sigma_px / length about the segment (endpoint noise `sigma_px`, the
    BA's), so weighted by the length a normal's distance from the axis is in pixels. The test is on the
    axis alone, not against the free fit: where the views barely move across the line, its planes
    nearly coincide and their noise lies along one direction, which the free fit then absorbs."""
    weights = np.array(weights, np.float64)
    unfit = np.zeros(len(weights), bool)
    if config.direction_alpha <= 0 or len(obs_line) == 0 or len(axes) == 0:
        return weights, unfit
    wn = normals_w * length_px[:, None]
    scatter = np.zeros((len(weights), 3, 3))
    np.add.at(scatter, obs_line, wn[:, :, None] * wn[:, None, :])
    views = np.bincount(obs_line, minlength=len(weights))
    rows = np.flatnonzero((views >= 3) & (weights.sum(axis=1) > 0))
    if len(rows) == 0:
        return weights, unfit
    a = unit_rows(axes, "axes")
    miss = np.einsum("ai,nij,aj->na", a, scatter[rows], a) / (2.0 * sigma_px**2)  # (n, A)
    free = np.linalg.eigh(scatter[rows])[1][:, :, 0]  # the direction fitting the planes best
    angle = np.degrees(np.arccos(np.clip(np.abs(free @ a.T), 0.0, 1.0)))
    limit = chdtri(views[rows], config.direction_alpha)[:, None]
    kept = weights[rows] * ~((miss > limit) & (angle > config.gate_deg))
    total = kept.sum(axis=1, keepdims=True)
    weights[rows] = np.divide(kept, total, out=np.zeros_like(kept), where=total > 0)
    unfit[rows] = total[:, 0] == 0
    return weights, unfit
