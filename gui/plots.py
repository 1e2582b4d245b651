"""Report plots with matplotlib (Agg, no display): trajectory top view, line-direction stereonet,
per-frame counts and ATE over time. Each returns PNG bytes, ready to embed in the HTML report.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np

from papl_mapper.extras import require
from papl_mapper.palette import UNANCHORED_RGB, axis_colors, axis_names

_DPI = 100


def _figure(width_in: float = 6.4, height_in: float = 4.8):
    matplotlib = require("matplotlib", "the report's plots")
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    return buf.getvalue()


def _rgb01(rgb) -> tuple[float, float, float]:
    return tuple(float(c) / 255 for c in rgb)


def trajectory_top(
    centres_w: np.ndarray,
    endpoints_w: np.ndarray | None = None,
    line_rgb: np.ndarray | None = None,
    gt_centres_w: np.ndarray | None = None,
    units: str = "arbitrary",
    label: str = "estimate",
) -> bytes:
    """Top view (x, y) of the camera path over the map's lines; the ground truth too when given."""
    from matplotlib.collections import LineCollection

    fig = _figure()
    ax = fig.add_subplot()
    if endpoints_w is not None and len(endpoints_w):
        colors = np.asarray(line_rgb, np.float64) / 255 if line_rgb is not None else "0.7"
        ax.add_collection(LineCollection(endpoints_w[:, :, :2], colors=colors, linewidths=0.6, alpha=0.35))
    if gt_centres_w is not None and len(gt_centres_w):
        ax.plot(gt_centres_w[:, 0], gt_centres_w[:, 1], "--", color="0.2", lw=1.2, label="ground truth")
    if len(centres_w):
        ax.plot(centres_w[:, 0], centres_w[:, 1], "-", color="#6e2896", lw=1.6, label=label)
        ax.plot(*centres_w[0, :2], "o", color="#6e2896", ms=6, label="start")
        ax.plot(*centres_w[-1, :2], "s", color="#6e2896", ms=6, label="end")
        ax.legend(loc="best", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no trajectory", ha="center", va="center", transform=ax.transAxes)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel(f"x [{units}]")
    ax.set_ylabel(f"y [{units}]")
    ax.set_title("trajectory, top view (lines faint, coloured by axis)")
    ax.grid(True, lw=0.3)
    return _png(fig)


def stereonet_xy(directions: np.ndarray) -> np.ndarray:
    """(n, 2) lower-hemisphere equal-area (Schmidt) projection of undirected unit directions (n, 3).

    Vertical directions map to the centre, horizontal ones to the unit circle.
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    d = np.where(d[:, 2:3] > 0, -d, d)  # lower hemisphere
    r = np.sqrt(np.clip(1.0 + d[:, 2], 0.0, 1.0))  # 0 at straight down, 1 on the horizon
    h = np.linalg.norm(d[:, :2], axis=1)
    scale = np.where(h > 1e-12, r / np.maximum(h, 1e-12), 0.0)
    return d[:, :2] * scale[:, None]


def direction_stereonet(
    endpoints_w: np.ndarray,
    axis_of_line: np.ndarray,
    axes_w: np.ndarray,
    vertical_index: int,
    palette: str = "okabe-ito",
    max_lines: int = 20_000,
    seed: int = 0,
) -> bytes:
    """Equal-area stereonet of line directions coloured by axis, with each principal axis marked."""
    fig = _figure(5.6, 5.6)
    ax = fig.add_subplot()
    t = np.linspace(0, 2 * np.pi, 361)
    ax.plot(np.cos(t), np.sin(t), color="0.3", lw=1)
    for r in (np.sqrt(1 - np.cos(np.radians(a))) for a in (30, 60)):
        ax.plot(r * np.cos(t), r * np.sin(t), color="0.8", lw=0.5)
    ax.plot([-1, 1], [0, 0], color="0.85", lw=0.5)
    ax.plot([0, 0], [-1, 1], color="0.85", lw=0.5)
    n_axes = len(axes_w)
    if len(endpoints_w):
        idx = np.arange(len(endpoints_w))
        if len(idx) > max_lines:
            idx = np.sort(np.random.default_rng(seed).choice(len(idx), max_lines, replace=False))
        d = endpoints_w[idx, 1] - endpoints_w[idx, 0]
        keep = np.linalg.norm(d, axis=1) > 0
        xy = stereonet_xy(d[keep])
        lab = axis_of_line[idx][keep]
        table = np.vstack([axis_colors(n_axes, vertical_index, palette), [UNANCHORED_RGB]]) / 255
        col = table[np.where(lab < 0, n_axes, lab)]
        ax.scatter(xy[:, 0], xy[:, 1], s=4, c=col, alpha=0.5, linewidths=0)
    names = axis_names(n_axes, vertical_index)
    for a, (name, rgb) in enumerate(zip(names, axis_colors(n_axes, vertical_index, palette), strict=True)):
        p = stereonet_xy(axes_w[a][None])[0]
        ax.plot(*p, marker="*", ms=16, color=_rgb01(rgb), mec="black", mew=0.8, ls="none", label=name)
    if n_axes:
        ax.legend(loc="lower left", fontsize=7, bbox_to_anchor=(-0.02, -0.02))
    ax.text(0, 1.09, "+y", ha="center", va="bottom", fontsize=8, color="0.4")
    ax.text(1.09, 0, "+x", ha="left", va="center", fontsize=8, color="0.4")
    ax.set_xlim(-1.12, 1.12)
    ax.set_ylim(-1.12, 1.12)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("line directions (lower hemisphere, equal area); stars = axes")
    return _png(fig)


def per_frame_counts(
    frame: Sequence[float], series: dict[str, Sequence[float]], xlabel: str = "frame"
) -> bytes:
    """Counts per frame (points, lines, ...) as step plots."""
    fig = _figure(6.4, 3.6)
    ax = fig.add_subplot()
    x = np.asarray(frame, np.float64)
    for name, values in series.items():
        ax.step(x, np.asarray(values, np.float64), where="mid", label=name, lw=1.2)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    ax.set_title(f"tracked features per {xlabel}")
    ax.grid(True, lw=0.3)
    if series:
        ax.legend(fontsize=8)
    return _png(fig)


def ate_over_time(timestamps: np.ndarray, errors: np.ndarray, units: str = "arbitrary") -> bytes:
    """Absolute trajectory error of each matched pose over time (after Sim(3) alignment)."""
    fig = _figure(6.4, 3.6)
    ax = fig.add_subplot()
    t = np.asarray(timestamps, np.float64)
    e = np.asarray(errors, np.float64)
    if len(t):
        ax.plot(t - t[0], e, lw=1.2, color="#0072b2")
        ax.axhline(float(np.sqrt(np.mean(e**2))), color="#d55e00", ls="--", lw=1, label="RMSE")
        ax.legend(fontsize=8)
    ax.set_xlabel("time since first pose [s]")
    ax.set_ylabel(f"ATE [{units}]")
    ax.set_title("absolute trajectory error over time")
    ax.grid(True, lw=0.3)
    return _png(fig)
