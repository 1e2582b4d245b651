"""Plan and elevation views of a map for CAD: structure projected onto the floor plane or a wall plane.

Plan: looking down the vertical axis, with the map's first horizontal axis as north (page up);
vertical lines become marks (corners, door frames, columns), horizontal lines wall traces.
Elevation k: looking along horizontal axis k, vertical axis up; lines along the view direction become
marks. One layer per axis, stray geometry left out as in the DXF export (see `cad_split`), plus a
scale bar (and a north arrow on the plan) sized to the drawing. Writers in `drawing.py`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.errors import InputError

from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, cad_split


@dataclass
class ViewLayer:
    """One layer of a view: 2D segments and marks (points drawn as small circles), one colour."""

    name: str  # DXF layer / SVG group id, e.g. "HORIZONTAL_1"
    rgb: tuple[int, int, int]
    segments: np.ndarray  # (S, 2, 2) drawing coordinates
    marks: np.ndarray  # (K, 2) drawing coordinates
    polyline: bool = False  # segments chain into one polyline (the trajectory)


@dataclass
class View:
    """A 2D drawing of the map: drawing x = world . right, drawing y = world . page_up."""

    title: str
    right_w: np.ndarray  # (3,) unit world direction drawn to the right
    page_up_w: np.ndarray  # (3,) unit world direction drawn up the page
    layers: list[ViewLayer]
    units: str  # "m", or "arbitrary"
    scale_note: str
    north: bool = False  # draw a north arrow (page up is the first horizontal axis)
    north_label: str = ""
    notes: list[str] = field(default_factory=list)

    def to_2d(self, xyz: np.ndarray) -> np.ndarray:
        """(..., 2) drawing coordinates of world points (..., 3)."""
        return np.stack([xyz @ self.right_w, xyz @ self.page_up_w], axis=-1)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (2,) of every segment and mark ((0,0), (1,1) when empty)."""
        xy = [ly.segments.reshape(-1, 2) for ly in self.layers] + [ly.marks for ly in self.layers]
        xy = np.concatenate([a for a in xy if len(a)] or [np.array([[0.0, 0.0], [1.0, 1.0]])])
        lo, hi = xy.min(0), xy.max(0)
        hi = np.where(hi - lo > 0, hi, lo + 1.0)
        return lo, hi

    @property
    def extent(self) -> float:
        lo, hi = self.bounds()
        return float(max(hi - lo))

    def unit_label(self, value: float) -> str:
        """'2 m', or '2 units' for a map of arbitrary scale."""
        return f"{value:g} m" if self.units == "m" else f"{value:g} units"


def nice_length(extent: float) -> float:
    """A round scale-bar length (1, 2 or 5 times a power of ten) about a fifth of `extent`."""
    target = max(extent, 1e-12) / 5
    p = 10 ** math.floor(math.log10(target))
    return max(c * p for c in (1, 2, 5) if c * p <= target)


def _up_and_horizontals(scene: ExportScene) -> tuple[np.ndarray, list[dict]]:
    info = scene.axis_info
    vert = [a for a in info if a["vertical"]]
    if not vert:
        raise InputError("the map has no vertical axis: plans and elevations need one")
    up = np.asarray(vert[0]["direction"], np.float64)
    up = up if up[2] >= 0 else -up
    horizontal = [a for a in info if not a["vertical"]]
    if not horizontal:
        raise InputError("the map has no horizontal axis: plans and elevations need one")
    return up / np.linalg.norm(up), horizontal


def _flat(d: np.ndarray, up: np.ndarray) -> np.ndarray:
    d = np.asarray(d, np.float64) - (np.asarray(d) @ up) * up
    return d / np.linalg.norm(d)


def _build(scene, options, right, page_up, end_on_axis: int, title: str, **kw) -> View:
    """Layers: each axis group drawn as segments, or as marks (midpoints) for the axis seen end-on."""
    groups, _, _ = cad_split(scene, options)
    view = View(title, right, page_up, [], scene.units, scene.scale_note, **kw)
    for g in groups:
        if g.axis_index < 0 or not len(g.ids):
            continue  # unanchored lines are no structure to draw from
        xy = view.to_2d(g.segments_w)  # (S, 2, 2)
        if g.axis_index == end_on_axis:
            layer = ViewLayer(g.key.upper(), g.rgb, np.zeros((0, 2, 2)), xy.mean(axis=1))
        else:
            layer = ViewLayer(g.key.upper(), g.rgb, xy, np.zeros((0, 2)))
        view.layers.append(layer)
    if len(scene.trajectory_w) >= 2:
        t = view.to_2d(scene.trajectory_w)
        view.layers.append(
            ViewLayer("TRAJECTORY", TRAJECTORY_RGB, np.stack([t[:-1], t[1:]], axis=1), np.zeros((0, 2)), True)
        )
    return view


def _empty(scene: ExportScene, title: str) -> View:
    """The view of a map with nothing to draw: a valid drawing holding only its annotations."""
    return View(title, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), [], scene.units, scene.scale_note)


def plan_view(scene: ExportScene, options: ExportOptions) -> View:
    """The plan on the floor plane: north (page up) along the map's first horizontal axis."""
    if scene.is_empty:
        return _empty(scene, "plan (empty map)")
    up, horizontal = _up_and_horizontals(scene)
    north = _flat(horizontal[0]["direction"], up)
    east = np.cross(north, up)
    vertical = next(a["index"] for a in scene.axis_info if a["vertical"])
    label = f"N: {horizontal[0]['name']}"
    return _build(scene, options, east, north, vertical, "plan", north=True, north_label=label)


def elevation_view(scene: ExportScene, options: ExportOptions, horizontal_number: int = 1) -> View:
    """The elevation seen looking along horizontal axis `horizontal_number` (1-based, as in its name)."""
    if scene.is_empty:
        return _empty(scene, "elevation (empty map)")
    up, horizontal = _up_and_horizontals(scene)
    if not 1 <= horizontal_number <= len(horizontal):
        raise InputError(
            f"elevation-{horizontal_number}: the map has horizontal axes 1..{len(horizontal)}; "
            f"name the file elevation-K with K one of them"
        )
    a = horizontal[horizontal_number - 1]
    look = _flat(a["direction"], up)
    right = np.cross(look, up)
    return _build(scene, options, right, up, a["index"], f"elevation looking along {a['name']}")
