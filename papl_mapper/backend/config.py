"""Typed configuration of the bundle adjustment (global and local)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np


@dataclass
class BAConfig:
    """Bundle adjustment settings; defaults suit pixel observations of a 640x480 camera."""

    max_iterations: int = 30
    """Levenberg-Marquardt iterations at most."""
    relative_error_tol: float = 1e-5
    """Stop when the cost decreases by less than this fraction in one iteration."""
    absolute_error_tol: float = 1e-9
    """Stop when the cost decreases by less than this in one iteration."""
    lambda_initial: float = 1e-4
    """Initial Levenberg-Marquardt damping."""
    halve_rejected_steps: bool = True
    """A Levenberg-Marquardt step that raises the cost is tried again at half its length (one cost
    evaluation) before the damping grows and the system is solved again (a whole elimination): most
    rejected steps overshoot along a few unanchored lines' curved parameters (benchmarks/results/notes.md)."""
    multifrontal_from_keyframes: int = 500
    """Damped systems with at least this many keyframes are solved by multifrontal elimination, smaller
    ones sequentially (both exact, the same step): sequential is faster on many small landmark cliques;
    once a long recording's loop closures fill in the camera part, multifrontal's dense fronts are
    several times faster (benchmarks/results/notes.md)..."""
    multifrontal_max_front_mib: float = 400.0
    """...while the camera part as one dense front, (6 x keyframes)^2 doubles, stays within this many MiB
    (1,206 keyframes): the fronts' memory grows faster than that, and past it a long recording's job
    outgrows its memory (a 5-minute 720p walk, 2,687 keyframes: past 4.9 GB)."""
    point_sigma_px: float = 1.0
    """Standard deviation of point observations, pixels."""
    line_sigma_px: float = 1.0
    """Standard deviation of the endpoint-to-line distances, pixels."""
    huber_k: float = 1.345
    """Huber threshold in standard deviations (applied per observation, to its whitened 2-vector)."""
    huber_k_start: float | None = None
    """Graduated robust loss: if set, Levenberg-Marquardt first converges with this wider Huber threshold and
    then continues with `huber_k` (each stage up to max_iterations). From starts with residuals of tens of
    pixels a tight Huber weights every observation down alike, and anchored lines settled in false minima
    (Open-Structure livingroom2: anchored line RMS 9.0 px with huber_k only, 1.3 px with 20 then 1.345,
    see benchmarks/line_representations.py). Keep it below the gross errors expected: 20-40 px outliers under
    a 20 sigma first stage pulled a synthetic map into another basin (ATE 0.028 against 0.002 with 5 sigma
    or huber_k alone; tests/test_backend_robust.py). None: one stage."""
    min_line_parallax_deg: float = 0.0
    """A line whose observing camera centres span less than this angle about it has no observable depth (as
    points need a triangulation angle): before BA such lines (judged on their start geometry) are left out
    and kept unchanged; after BA a line that became so (e.g. driven hundreds of scene sizes away) keeps its
    input geometry; both counted in BAResult.dropped. Same rule for every line representation; 0 = off."""
    min_orthonormal_parallax_deg: float = 1.0
    """The same rule for orthonormal lines, at least this angle whatever min_line_parallax_deg says: with
    a free direction and no observable depth such a line has near-null directions whose Gauss-Newton steps
    (radians of U and W) fail the whole Levenberg-Marquardt step until the damping grows; a line anchored
    to an axis keeps its direction and still holds the cameras' rotation, so it is not held to this."""
    axis_prior_sigma_deg: float = 2.0
    """The paper's axis error e_a: how far (1 sigma) an axis may move from its value before BA."""
    min_axis_weight: float = 0.1
    """Soft associations w_kj below this are left out of the graph."""
    min_lines_per_axis: int = 2
    """An axis anchoring fewer lines is held fixed (its direction is not observable enough)."""
    min_views: int = 2
    """Points and lines seen from fewer distinct keyframes are left out (kept unchanged)."""
    min_segment_px: float = 2.0
    """Line observations shorter than this are dropped (zero-length segments have no direction)."""
    min_ray_angle_deg: float = 1.0
    """Line observations whose 3D line is within this angle of the viewing ray are dropped."""
    structural_lines: Literal["anchored", "fixed_direction"] = "anchored"
    """How ANCHORED lines are optimised: the paper's 3-parameter form (shared axis + inverse depth), or the
    2-parameter baseline of Xu et al. 2022 (direction held at its axis, 2-dof position; for comparisons)."""
    anchor_bearing: Literal["observation", "estimate"] = "observation"
    """The ray an anchored line is held on: through the observed segment midpoint in the reference keyframe
    (the paper; unbiased, but that one observation's noise is never averaged out), or through the point of
    the current line estimate nearest that midpoint (as good as the estimate, e.g. a multi-view
    triangulation; a poor estimate's error stays)."""
    anchor_offset: bool = False
    """Give anchored lines a second parameter: the anchor's sideways shift across the line in the reference
    image (pixels), besides the paper's inverse depth. The paper's form (False: n + 2 parameters per axis)
    holds each line on one ray through a single observation, so it can only slide in depth and keeps that
    observation's noise; with the offset (2n + 2, the minimal count for lines parallel to a known direction)
    the line fits all its views (benchmarks/line_representations.py). False here keeps a bare BAConfig in
    the paper's form; `papl-map run` turns it on (pipelines/config.py), `--preset paper-anchors` off."""
    tvp_offset: bool = False
    """With anchor_offset, also give temporary-VP lines the offset (then 4 parameters, a general line); off
    keeps the paper's 3-parameter first stage (measured on the demo: the offset there cost ATE)."""
    optimize_poses: bool = True
    """False holds every keyframe pose at its value (e.g. the fixed-pose experiment)."""
    optimize_axes: bool = True
    """False holds the principal axes at their values."""
    scale_prior_sigma: float = 1e-2
    """Monocular gauge: relative sigma of the prior holding the distance between the two gauge keyframes.
    The data carry no scale, so the optimum meets the prior exactly whatever its sigma; a stiff sigma
    (1e-4) made Levenberg-Marquardt stall on pose-noise starts (measured), 1e-2 does not."""


def min_parallax_deg(config: BAConfig, orthonormal: np.ndarray | bool) -> np.ndarray | float:
    """The parallax a line needs to enter (and to leave) BA: min_line_parallax_deg, raised to
    min_orthonormal_parallax_deg for orthonormal lines."""
    return np.where(
        orthonormal,
        max(config.min_line_parallax_deg, config.min_orthonormal_parallax_deg),
        config.min_line_parallax_deg,
    )
