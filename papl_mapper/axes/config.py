"""Thresholds of principal-axis management, with the paper's values where it states them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class AxesConfig:
    """Creation (mean shift), association (EM) and update (adopt/delete/merge) of principal axes.

    The paper gives the 10-degree discard angle and the 0.6 ratio; the others it leaves open and are
    our choices (its commented-out tau_diff schedule is 10/5/1 degrees by line count).
    """

    # ---- creation --------------------------------------------------------------------------------
    tau_n: int = 10
    """Fewest unclassified structural lines before new axes are searched for (paper tau_n)."""
    tau_d_deg: float = 10.0
    """Mean-shift window: only directions within this angle of the current mode contribute (tau_d)."""
    kernel_sigma_deg: float = 4.0
    """Width of the Gaussian kernel on angle, K = exp(-c a^2) with c = 1 / (2 sigma^2)."""
    mean_shift_max_iter: int = 50
    """Iteration cap of each mean-shift trajectory."""
    mean_shift_tol_deg: float = 1e-3
    """A trajectory has converged when its mode moves less than this."""
    max_seeds: int = 400
    """Most seeds (evenly subsampled line directions) started per call."""
    mode_merge_deg: float = 3.0
    """Converged modes closer than this are one mode."""
    min_support: int = 5
    """Fewest lines within tau_d of a mode for it to become an axis."""
    max_mean_angle_deg: float = 5.0
    """Largest mean angle between a candidate axis and its supporting lines."""
    discard_existing_deg: float = 10.0
    """A candidate within this angle of an existing axis is discarded (paper: 10 degrees)."""
    min_nonstructural_ratio: float = 0.6
    """Create axes only if non-structural / structural line count exceeds this (paper: 0.6)."""
    max_new_axes: int = 1
    """Most axes created per call, best (smallest mean angle) first; the paper creates the optimal one."""

    min_support_fraction: float = 0.01
    """A new axis needs at least this fraction of the map's structural lines behind it (a whole recording
    has many lines: a handful of misclassified ones must not found an axis). An Atlanta world's lines
    split over its horizontal directions, as unevenly as the walk faces them, so this stays low
    (benchmarks/results/notes.md)."""

    # ---- association -------------------------------------------------------------------------------
    association: Literal["soft", "hard"] = "soft"
    """EM soft line-axis weights, or each line anchored to its single best axis (an ablation)."""
    gate_deg: float = 15.0
    """Loose gate: a line whose mean vanishing-direction angle to an axis exceeds this gets weight 0."""
    sigma_deg: float = 2.0
    """Standard deviation of the zero-mean normal likelihood on the mean angle."""
    em_iterations: int = 10
    """EM iterations (E: weights, M: mixing proportions of the axes)."""
    direction_alpha: float = 1e-3
    """A line loses an axis when the back-projection planes of its segments reject it at this
    significance and the direction they fit lies beyond `gate_deg` from it (the paper's gate on the
    line's own direction, where its views decide it); with none left it is unanchored. 0: no check."""

    # ---- update ------------------------------------------------------------------------------------
    update: bool = True
    """Update, merge and delete axes after the first global BA and optimise again (axis management)."""
    tau_diff_deg: float = 1.0
    """Adopt the direction after BA when it moved more than this (paper tau_diff)."""
    jump_deg: float = 5.0
    """A move larger than this counts as a jump (a significant change)."""
    max_jumps: int = 3
    """An axis that jumped this many times is deleted (the vertical axis never is)."""
    merge_deg: float = 5.0
    """Axes closer than this are merged, keeping the older one (and always the vertical)."""
