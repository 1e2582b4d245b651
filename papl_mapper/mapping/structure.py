"""Principal axes of a whole map: the vertical, horizontal axes by mean shift, soft line weights by EM.

A batch tool sees every line at once, so axis creation runs over all structural lines until no
new axis is accepted (the paper creates one per local map); association then gives every line
its weights w_kj from the world vanishing directions it was observed with.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from papl_mapper.axes import AxesConfig, AxisState, associate, create_axes
from papl_mapper.map import Axes
from papl_mapper.mapping.assemble import refine_direction

log = logging.getLogger(__name__)


@dataclass
class Structure:
    """Axes (vertical first), per-line weights (M,A) and the axis book-keeping for later updates."""

    axes: Axes
    weights: np.ndarray
    state: AxisState


def hard_weights(weights: np.ndarray) -> np.ndarray:
    """One-hot rows: each associated line goes to its single best axis (the hard-association ablation)."""
    out = np.zeros_like(weights)
    has = weights.sum(axis=1) > 0
    out[np.flatnonzero(has), weights[has].argmax(axis=1)] = 1.0
    return out


def line_weights(
    obs_dirs_w: np.ndarray,
    obs_line: np.ndarray,
    n_lines: int,
    axes: np.ndarray,
    config: AxesConfig,
    hard: bool,
) -> np.ndarray:
    """EM weights (n_lines, A) from packed world vanishing directions (K,3) of line observations."""
    ok = np.isfinite(obs_dirs_w).all(axis=1)
    w = associate((obs_dirs_w[ok], obs_line[ok]), axes, config, n_lines=n_lines)
    return hard_weights(w) if hard else w


def find_structure(
    line_dirs_w: np.ndarray,
    structural: np.ndarray,
    obs_dirs_w: np.ndarray,
    obs_line: np.ndarray,
    vertical_w: np.ndarray,
    config: AxesConfig | None = None,
    hard: bool = False,
    max_axes: int = 8,
    obs_normals_w: np.ndarray | None = None,
    obs_weight: np.ndarray | None = None,
    min_support_fraction: float = 0.0,
    max_tilt_deg: float = 3.0,
) -> Structure:
    """Axes and weights for lines with directions (M,3), `structural` (M,) marking VP-classified ones.

    `obs_dirs_w` (K,3) / `obs_line` (K,) are the world vanishing directions of the lines'
    observations (NaN rows for non-structural observations). With the observations' world
    back-projection plane normals (K,3) and weights (segment lengths), each horizontal axis is
    refined over every observation classified near it, across all frames at once.
    Atlanta world: a new axis must be within `max_tilt_deg` of horizontal and supported by at
    least `min_support_fraction` of the structural lines (a whole recording has many lines, so a
    handful of misclassified ones must not found an axis).
    """
    cfg = dataclasses.replace(config or AxesConfig())
    n = len(line_dirs_w)
    cfg.min_support = max(cfg.min_support, int(np.ceil(min_support_fraction * structural.sum())))
    axes = np.asarray(vertical_w, np.float64).reshape(1, 3) / np.linalg.norm(vertical_w)
    weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    while len(axes) < max_axes:
        free = structural & (weights.sum(axis=1) == 0)
        res = create_axes(
            line_dirs_w[free],
            axes,
            int(free.sum()),
            cfg,
            # no ratio test: it guards a real-time local map against creating axes too eagerly;
            # over a whole recording the support and mean-angle tests of the candidates suffice
            n_structural=0,
        )
        tilt = np.degrees(np.arcsin(np.clip(np.abs(res.new_axes @ axes[0]), 0.0, 1.0)))
        new = res.new_axes[tilt <= max_tilt_deg]
        if len(new) == 0:
            log.debug("axis creation stops: %s", res.reason or "no horizontal candidate accepted")
            break
        axes = np.vstack([axes, new])
        weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    if obs_normals_w is not None and len(axes) > 1:
        w = np.ones(len(obs_normals_w)) if obs_weight is None else obs_weight
        ok = np.isfinite(obs_dirs_w).all(axis=1)
        for a in range(1, len(axes)):
            near = ok.copy()
            near[ok] = np.abs(obs_dirs_w[ok] @ axes[a]) > np.cos(np.radians(cfg.gate_deg / 3))
            if near.sum() >= 3:
                axes[a] = refine_direction(obs_normals_w[near], w[near], axes[a])
        weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    angles = [
        np.degrees(np.arccos(np.clip(abs(a @ axes[0]), 0, 1))) for a in axes[1:]
    ]  # horizontal axes should be near 90 deg from the vertical
    log.info(
        "%d axes (vertical + %d horizontal, %s deg from vertical); %d of %d lines associated",
        len(axes),
        len(axes) - 1,
        ", ".join(f"{a:.1f}" for a in angles) or "-",
        int((weights.sum(axis=1) > 0).sum()),
        n,
    )
    return Structure(Axes(axes, vertical_index=0), weights, AxisState.new(len(axes), vertical_index=0))
