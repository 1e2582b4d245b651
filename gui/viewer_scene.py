"""The viewer's data path: a Map turned once into per-line tables, and the filters over them.

Everything here is numpy on the map's arrays, with no renderer imported, so the time it takes is
measured apart from drawing (benchmarks/viewer.py) and tests check it without a window. What the
window draws is `ViewerScene.selection(filters)`: which lines pass the toggles and filters, the
seeded subset drawn when more pass than the renderer holds, and the legend counts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from papl_mapper.geometry.lines import line_intrinsics
from papl_mapper.map import LineState, Map
from papl_mapper.palette import UNANCHORED_RGB, axis_colors, axis_names, line_colors

#: Line representation names as the picking panel shows them.
STATE_NAMES = {
    int(LineState.TEMPORARY_VP): "temporary VP",
    int(LineState.ORTHONORMAL): "orthonormal",
    int(LineState.ANCHORED): "anchored",
}


@dataclass
class Filters:
    """What the user chose to see: one switch per axis and for unanchored lines, and two thresholds."""

    axes_on: list[bool]
    """One switch per principal axis, in axis order."""
    unanchored_on: bool = True
    """Draw lines that belong to no axis."""
    min_observations: int = 0
    """Hide lines seen in fewer keyframes (the exporters' --min-obs)."""
    max_rms_px: float = float("inf")
    """Hide lines whose reprojection RMS over their observations exceeds this (pixels)."""


@dataclass
class Selection:
    """The lines one set of filters lets through: those passing, those drawn, and the legend."""

    passing: np.ndarray  # (k,) int64 line rows passing the filters
    drawn: np.ndarray  # (d,) int64 line rows drawn, a seeded subset of `passing` when decimated
    counts: list[int]  # lines passing per axis, then unanchored
    decimated: bool

    @property
    def note(self) -> str:
        """One line for the window when not every passing line is drawn."""
        if not self.decimated:
            return ""
        return f"decimated: {len(self.drawn):,} of {len(self.passing):,} lines drawn"


@dataclass
class ViewerScene:
    """Per-line facts of one map, computed once when the map opens."""

    endpoints_w: np.ndarray  # (M, 2, 3) float32 for the renderer
    axis: np.ndarray  # (M,) int64 axis index, -1 unanchored
    line_rgb: np.ndarray  # (M, 3) uint8 palette colours
    n_obs: np.ndarray  # (M,) int64 observations (keyframes) per line
    n_axes: int
    axis_labels: list[str]
    axis_rgb: list[tuple[int, int, int]]  # palette colour per axis, then unanchored
    rms_px: np.ndarray | None = None  # (M,) float64, filled by `compute_rms` (NaN: no observation)
    seed: int = 0
    _order: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def from_map(cls, m: Map, palette: str = "okabe-ito", seed: int = 0) -> ViewerScene:
        """Colours, axis labels and observation counts; the reprojection RMS is left to `compute_rms`."""
        n_axes = len(m.axes)
        axis = m.lines.axis_of_line()
        rgb = line_colors(axis, n_axes, m.axes.vertical_index, palette)
        n_obs = observation_counts(m.lines.ids, m.lines.obs_ids[:, 0])
        colours = [tuple(int(c) for c in row) for row in axis_colors(n_axes, m.axes.vertical_index, palette)]
        return cls(
            endpoints_w=m.lines.endpoints_w.astype(np.float32),
            axis=axis,
            line_rgb=rgb,
            n_obs=n_obs,
            n_axes=n_axes,
            axis_labels=[*axis_names(n_axes, m.axes.vertical_index), "unanchored"],
            axis_rgb=[*colours, UNANCHORED_RGB],
            seed=seed,
        )

    def __len__(self) -> int:
        return len(self.axis)

    def default_filters(self) -> Filters:
        return Filters(axes_on=[True] * self.n_axes)

    def compute_rms(self, m: Map) -> np.ndarray:
        """Reprojection RMS (pixels) of every line over its observations; stored and returned."""
        self.rms_px = line_rms_px(m)
        return self.rms_px

    def selection(self, f: Filters, max_drawn: int) -> Selection:
        """Rows passing `f`, and at most `max_drawn` of them to draw (a fixed random order, so the
        subset shown for a tighter filter is a subset of the one shown for a looser filter)."""
        if len(f.axes_on) != self.n_axes:
            raise ValueError(f"{len(f.axes_on)} axis switches for {self.n_axes} axes")
        on = np.array([*f.axes_on, f.unanchored_on], bool)
        group = np.where(self.axis < 0, self.n_axes, self.axis)
        keep = on[group]
        if f.min_observations > 0:
            keep &= self.n_obs >= f.min_observations
        if np.isfinite(f.max_rms_px) and self.rms_px is not None:
            keep &= ~(self.rms_px > f.max_rms_px)  # lines without observations have NaN: kept
        passing = np.flatnonzero(keep)
        counts = np.bincount(group[passing], minlength=self.n_axes + 1).tolist()
        if len(passing) <= max_drawn:
            return Selection(passing, passing, counts, False)
        if self._order is None:  # rank of each line in one seeded permutation
            perm = np.random.default_rng(self.seed).permutation(len(self))
            self._order = np.empty(len(self), np.int64)
            self._order[perm] = np.arange(len(self))
        rank = self._order[passing]
        cut = np.partition(rank, max_drawn - 1)[max_drawn - 1]
        return Selection(passing, passing[rank <= cut], counts, True)


def observation_counts(ids: np.ndarray, obs_ids: np.ndarray) -> np.ndarray:
    """(M,) how many observations name each id (a validated map refers to known ids only)."""
    if len(ids) == 0 or len(obs_ids) == 0:
        return np.zeros(len(ids), np.int64)
    return np.bincount(_rows(ids, obs_ids), minlength=len(ids)).astype(np.int64)


def line_rms_px(m: Map, chunk: int = 1_000_000) -> np.ndarray:
    """(M,) RMS pixel distance of each line's observed endpoints to its projection (NaN: unobserved).

    The same error as bundle adjustment's line term: observed endpoints against the image line of
    the 3D segment's carrier (K_L (X1 x X2) in the camera frame), valid behind the camera too.
    Observations are taken as given (the map stores them in the processed image's pixels).
    """
    lines, kf = m.lines, m.keyframes
    M = len(lines)
    if M == 0 or len(lines.obs_ids) == 0:
        return np.full(M, np.nan)
    row_of_line = _rows(lines.ids, lines.obs_ids[:, 0])
    row_of_kf = _rows(kf.ids, lines.obs_ids[:, 1])
    T_cw = np.linalg.inv(kf.T_wc)  # (N, 4, 4)
    KL = line_intrinsics(m.camera.K)
    sq = np.zeros(M)
    for s in range(0, len(row_of_line), chunk):
        li, ki = row_of_line[s : s + chunk], row_of_kf[s : s + chunk]
        R, t = T_cw[ki, :3, :3], T_cw[ki, :3, 3]
        X = lines.endpoints_w[li]  # (c, 2, 3)
        X1 = np.einsum("cij,cj->ci", R, X[:, 0]) + t
        X2 = np.einsum("cij,cj->ci", R, X[:, 1]) + t
        l = np.cross(X1, X2) @ KL.T  # (c, 3) image line in pixels
        norm = np.maximum(np.hypot(l[:, 0], l[:, 1]), 1e-12)
        xy = lines.obs_xy[s : s + chunk]
        d1 = (xy[:, 0] * l[:, 0] + xy[:, 1] * l[:, 1] + l[:, 2]) / norm
        d2 = (xy[:, 2] * l[:, 0] + xy[:, 3] * l[:, 1] + l[:, 2]) / norm
        sq += np.bincount(li, weights=d1 * d1 + d2 * d2, minlength=M)
    n = np.bincount(row_of_line, minlength=M)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.sqrt(sq / np.maximum(2 * n, 1)), np.nan)


def _rows(ids: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """Row of each referenced id in `ids` (the map's validation guarantees every id exists)."""
    order = np.argsort(ids, kind="stable")
    return order[np.searchsorted(ids, refs, sorter=order)]


def bounds(m: Map, q: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners framing the bulk of the map: the q..100-q percentile box of its line endpoints,
    keyframe centres and points, padded by a tenth (far strays of a monocular map stay out of it)."""
    parts = [m.lines.endpoints_w.reshape(-1, 3), m.keyframes.T_wc[:, :3, 3], m.points.xyz]
    xyz = np.concatenate([p for p in parts if len(p)] or [np.array([[-1.0, -1, -1], [1, 1, 1]])])
    if len(xyz) > 200_000:
        xyz = xyz[:: len(xyz) // 200_000]
    lo, hi = np.percentile(xyz, [q, 100 - q], axis=0) if len(xyz) >= 50 else (xyz.min(0), xyz.max(0))
    pad = np.maximum((hi - lo) * 0.1, 1e-3)
    return lo - pad, hi + pad
