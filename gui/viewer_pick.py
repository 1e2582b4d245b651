"""Picking in the viewer: which drawn line or point lies under a click, and what to say about a line.

The window hands over its camera as one 4x4 world-to-normalised-device matrix and the viewport
size; everything else is numpy on the drawn segments, so a pick costs the same whatever the
renderer and is tested without a window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from papl_mapper.map import Map

from .viewer_scene import STATE_NAMES, ViewerScene


@dataclass
class LineFacts:
    """What the picking panel says about one line."""

    id: int
    row: int
    axis: str
    length: float
    n_obs: int
    rms_px: float  # NaN when the line has no observation or the RMS is not computed yet
    representation: str
    keyframe_ids: list[int]

    def text(self, units: str) -> str:
        rms = "n/a" if not np.isfinite(self.rms_px) else f"{self.rms_px:.2f} px"
        return (
            f"line {self.id}: {self.axis}, length {self.length:.3f} {units}, {self.n_obs} observations, "
            f"reprojection RMS {rms}, {self.representation}; seen by {len(self.keyframe_ids)} keyframes"
        )


def to_pixels(
    world_to_ndc: np.ndarray, xyz: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Project (n, 3) world points to (n, 2) pixel coordinates (x right, y down) and NDC depth (n,)."""
    w, h = size
    hom = np.concatenate([xyz.astype(np.float64), np.ones((len(xyz), 1))], axis=1) @ world_to_ndc.T
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = hom[:, :3] / hom[:, 3:4]
    px = np.stack([(ndc[:, 0] + 1) * 0.5 * w, (1 - ndc[:, 1]) * 0.5 * h], axis=1)
    behind = hom[:, 3] <= 0
    px[behind] = np.nan
    return px, ndc[:, 2]


def segment_distances(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel distance of point c (2,) to each 2D segment a-b (k, 2), and the parameter t of the foot."""
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    t = np.clip(np.sum((c - a) * ab, axis=1) / L2, 0, 1)
    d = np.linalg.norm(a + t[:, None] * ab - c, axis=1)
    return np.where(np.isfinite(d), d, np.inf), t


def clearest_spot(
    world_to_ndc: np.ndarray, size: tuple[int, int], endpoints_w: np.ndarray, k: int, samples: int = 21
) -> tuple[float, float] | None:
    """The pixel on segment `k` of (n, 2, 3) farthest from every other segment on screen (where a user
    would click to pick it), or None when no part of it is in the view."""
    px, _ = to_pixels(world_to_ndc, endpoints_w.reshape(-1, 3), size)
    a, b = px[0::2], px[1::2]
    others = np.ones(len(a), bool)
    others[k] = False
    best, spot = -1.0, None
    w, h = size
    for s in np.linspace(0.05, 0.95, samples):
        c = a[k] + s * (b[k] - a[k])
        if not (np.isfinite(c).all() and 2 <= c[0] < w - 2 and 2 <= c[1] < h - 2):
            continue
        d = segment_distances(a[others], b[others], c)[0].min(initial=np.inf)
        if d > best:
            best, spot = d, (float(c[0]), float(c[1]))
    return spot


def pick_segment(
    world_to_ndc: np.ndarray,
    size: tuple[int, int],
    endpoints_w: np.ndarray,
    click_px: tuple[float, float],
    radius_px: float = 8.0,
) -> int | None:
    """Index into `endpoints_w` (k, 2, 3) of the segment nearest the click within `radius_px`, or None.

    Among segments equally near (within a pixel), the one nearest the viewer wins."""
    if len(endpoints_w) == 0:
        return None
    k = len(endpoints_w)
    px, depth = to_pixels(world_to_ndc, endpoints_w.reshape(-1, 3), size)
    a, b = px[: k * 2 : 2], px[1 : k * 2 : 2]
    c = np.asarray(click_px, np.float64)
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    t = np.clip(np.sum((c - a) * ab, axis=1) / L2, 0, 1)
    d = np.linalg.norm(a + t[:, None] * ab - c, axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    best = float(d.min())
    if best > radius_px:
        return None
    near = np.flatnonzero(d <= best + 1.0)
    z = depth[::2][near] * (1 - t[near]) + depth[1::2][near] * t[near]
    return int(near[np.argmin(z)])


def pick_point(
    world_to_ndc: np.ndarray,
    size: tuple[int, int],
    xyz: np.ndarray,
    click_px: tuple[float, float],
    radius_px: float = 10.0,
) -> int | None:
    """Row of `xyz` (n, 3) nearest the click on screen within `radius_px` (nearest the viewer on ties)."""
    if len(xyz) == 0:
        return None
    px, depth = to_pixels(world_to_ndc, xyz, size)
    d = np.linalg.norm(px - np.asarray(click_px, np.float64), axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    best = float(d.min())
    if best > radius_px:
        return None
    near = np.flatnonzero(d <= best + 1.0)
    return int(near[np.argmin(depth[near])])


def line_facts(m: Map, scene: ViewerScene, row: int) -> LineFacts:
    """Id, axis, length, observations, reprojection RMS, representation, keyframes seeing line `row`."""
    lid = int(m.lines.ids[row])
    seen = m.lines.obs_ids[m.lines.obs_ids[:, 0] == lid, 1]
    a = int(scene.axis[row])
    rms = float(scene.rms_px[row]) if scene.rms_px is not None else float("nan")
    return LineFacts(
        id=lid,
        row=row,
        axis=scene.axis_labels[a] if a >= 0 else "unanchored",
        length=float(np.linalg.norm(m.lines.endpoints_w[row, 1] - m.lines.endpoints_w[row, 0])),
        n_obs=int(scene.n_obs[row]),
        rms_px=rms,
        representation=STATE_NAMES.get(int(m.lines.state[row]), f"state {int(m.lines.state[row])}"),
        keyframe_ids=sorted(set(seen.tolist())),
    )
