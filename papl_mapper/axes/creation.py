"""Axis creation: mean shift over the directions of unclassified structural lines (paper eq. meanshift).

Directions are lines (sign-invariant): each neighbour is sign-aligned to the current mode before
averaging. The kernel is Gaussian on the angle and only neighbours within tau_d contribute.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.axes.config import AxesConfig
from papl_mapper.axes.directions import canonical_sign, unit_rows
from papl_mapper.geometry.lines import line_angle_deg

log = logging.getLogger(__name__)


@dataclass
class Candidate:
    """A converged mean-shift mode: direction, supporting line indices, mean angle to them."""

    direction: np.ndarray  # (3,) unit
    support: np.ndarray  # (K,) int64 indices into the input lines
    mean_angle_deg: float
    accepted: bool = False
    reason: str = ""


@dataclass
class CreationResult:
    """New axes (A_new, 3) and every candidate with why it was accepted or rejected (for logs)."""

    new_axes: np.ndarray  # (A_new, 3)
    candidates: list[Candidate] = field(default_factory=list)
    reason: str = ""


def mean_shift_modes(dirs: np.ndarray, config: AxesConfig) -> np.ndarray:
    """Run mean shift from (subsampled) seeds; return the distinct converged modes (M, 3)."""
    dirs = unit_rows(dirs, "line directions")  # (N, 3)
    n = len(dirs)
    if n == 0:
        return np.zeros((0, 3))
    step = max(1, int(np.ceil(n / config.max_seeds)))
    modes = dirs[::step].copy()  # (S, 3)
    cos_win = np.cos(np.radians(config.tau_d_deg))
    c = 1.0 / (2.0 * np.radians(config.kernel_sigma_deg) ** 2)
    active = np.ones(len(modes), bool)
    for _ in range(config.mean_shift_max_iter):
        if not active.any():
            break
        m = modes[active]
        dots = m @ dirs.T  # (S', N)
        ang = np.arccos(np.clip(np.abs(dots), 0.0, 1.0))
        w = np.exp(-c * ang**2) * (np.abs(dots) >= cos_win)
        w = w * np.where(dots < 0.0, -1.0, 1.0)  # sign-align neighbours to the mode
        new = w @ dirs  # (S', 3)
        norm = np.linalg.norm(new, axis=1)
        ok = norm > 1e-12
        new[ok] /= norm[ok, None]
        new[~ok] = m[~ok]
        moved = np.degrees(np.arccos(np.clip(np.abs(np.sum(new * m, axis=1)), 0.0, 1.0)))
        modes[active] = new
        idx = np.flatnonzero(active)
        active[idx[moved < config.mean_shift_tol_deg]] = False
    # merge converged modes that coincide
    modes = canonical_sign(modes)
    out: list[np.ndarray] = []
    for m in modes:
        if not out or line_angle_deg(m, np.array(out)).min() >= config.mode_merge_deg:
            out.append(m)
    return np.array(out).reshape(-1, 3)


def create_axes(
    line_dirs_w: np.ndarray,
    existing_axes: np.ndarray,
    n_nonstructural: int,
    config: AxesConfig | None = None,
    *,
    n_structural: int = 0,
) -> CreationResult:
    """Find new principal axes among unclassified structural lines (N,3), given existing axes (A,3).

    `n_nonstructural` / `n_structural` are the local map's counts of lines not anchored / anchored
    to an axis; axes are created only when their ratio exceeds config.min_nonstructural_ratio
    (always when nothing is anchored yet).
    """
    config = config or AxesConfig()
    line_dirs_w = np.asarray(line_dirs_w, np.float64).reshape(-1, 3)
    existing = np.asarray(existing_axes, np.float64).reshape(-1, 3)
    empty = np.zeros((0, 3))
    if len(line_dirs_w) < config.tau_n:
        return CreationResult(empty, [], f"{len(line_dirs_w)} unclassified lines < tau_n={config.tau_n}")
    if n_structural > 0 and n_nonstructural / n_structural <= config.min_nonstructural_ratio:
        return CreationResult(
            empty,
            [],
            f"non-structural/structural ratio {n_nonstructural}/{n_structural} "
            f"<= {config.min_nonstructural_ratio}",
        )
    dirs = unit_rows(line_dirs_w, "unclassified line directions")
    modes = mean_shift_modes(dirs, config)
    ang = line_angle_deg(modes[:, None], dirs[None])  # (M, N)
    candidates: list[Candidate] = []
    for m, a in zip(modes, ang, strict=True):
        support = np.flatnonzero(a <= config.tau_d_deg)
        mean_angle = float(a[support].mean()) if len(support) else 90.0
        cand = Candidate(m, support.astype(np.int64), mean_angle)
        if len(support) < config.min_support:
            cand.reason = f"support {len(support)} < {config.min_support}"
        elif mean_angle > config.max_mean_angle_deg:
            cand.reason = f"mean angle {mean_angle:.2f} > {config.max_mean_angle_deg} deg"
        elif len(existing) and line_angle_deg(m, existing).min() < config.discard_existing_deg:
            cand.reason = f"within {config.discard_existing_deg} deg of an existing axis"
        candidates.append(cand)
    ok = [c for c in candidates if not c.reason]
    ok.sort(key=lambda c: (c.mean_angle_deg, -len(c.support)))
    chosen: list[np.ndarray] = []
    for cand in ok:
        if len(chosen) >= config.max_new_axes:
            cand.reason = f"max_new_axes={config.max_new_axes} reached"
            continue
        if chosen and line_angle_deg(cand.direction, np.array(chosen)).min() < config.discard_existing_deg:
            cand.reason = f"within {config.discard_existing_deg} deg of a better new axis"
            continue
        cand.accepted = True
        cand.reason = "accepted"
        chosen.append(cand.direction)
    new = np.array(chosen).reshape(-1, 3)
    log.debug("axis creation: %d modes, %d new axes", len(modes), len(new))
    return CreationResult(new, candidates, f"{len(new)} new axes from {len(modes)} modes")
