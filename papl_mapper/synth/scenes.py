"""Synthetic scenes built from textured planar quads, with ground-truth segments, axes and free space.

A scene is pure geometry: rectangles (quads) with a material and a texture frame, the 3D segments
that appear as intensity edges in renders (frames of doors and windows, junctions, pillar edges,
light fittings) labelled with their principal axis (-1 for non-structural), the principal axes
(axis 0 vertical +Z), a closed walking route and the convex regions of free space. World +Z is up,
units are metres. Every builder is seeded and deterministic.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.rows import unique_rows

#: Quads are rendered in tiles no longer than this many texels, each with its own mip level.
TILE_TEXELS = 512
#: Segments whose direction is within this angle of an axis are labelled with that axis.
AXIS_LABEL_TOL_DEG = 0.5


@dataclass(frozen=True)
class Material:
    """Surface appearance: BGR albedo in [0, 1], procedural texture contrast, emissive lights."""

    name: str
    color_bgr: tuple[float, float, float]
    contrast: float = 0.25  # amplitude of the seeded noise/blob texture (0 = plain)
    blob_scale_m: float = 0.15  # typical blob size of the texture in metres
    seed: int = 0
    emissive: bool = False  # lights: not shaded by the normal


@dataclass
class Scene:
    """Quads (Q, 4, 3) with materials and texture frames, GT segments (S, 2, 3) and axes (A, 3)."""

    name: str
    quad_corners: np.ndarray  # (Q, 4, 3) float64, p0, p0+u, p0+u+v, p0+v
    quad_material: np.ndarray  # (Q,) int64 into materials
    tex_origin: np.ndarray  # (Q, 3) texture frame origin on the quad's plane
    tex_u: np.ndarray  # (Q, 3) unit texture u direction (metres)
    tex_v: np.ndarray  # (Q, 3) unit texture v direction (metres)
    materials: list[Material]
    segments: np.ndarray  # (S, 2, 3) float64 ground-truth segments
    segment_axis: np.ndarray  # (S,) int64, axis id or -1 for non-structural
    axes: np.ndarray  # (A, 3) unit directions, axis 0 vertical
    axis_names: list[str]
    route: np.ndarray  # (R, 2) closed loop of XY waypoints in free space, walked from index 0
    free_space: list[np.ndarray]  # convex CCW polygons (k, 2) whose union is walkable
    eye_height: float = 1.6
    pitch_deg: float = -4.0  # mean camera pitch of the walker (positive looks up)
    background_bgr: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    texels_per_m: float = 256.0  # texture resolution (the renderer tiles quads by TILE_TEXELS)

    @property
    def normals(self) -> np.ndarray:
        """(Q, 3) unit quad normals (u x v)."""
        n = np.cross(
            self.quad_corners[:, 1] - self.quad_corners[:, 0],
            self.quad_corners[:, 3] - self.quad_corners[:, 0],
        )
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def corner_points(self) -> np.ndarray:
        """(P, 3) unique endpoints of the structural segments: the scene's GT corner points."""
        ends = self.segments[self.segment_axis >= 0].reshape(-1, 3)
        if not len(ends):
            return np.zeros((0, 3))
        return unique_rows(np.round(ends, 6))

    def sample_surface_points(self, n: int, seed: int = 0) -> np.ndarray:
        """(n, 3) points drawn uniformly (by area) on the quads: stand-ins for textured corners."""
        rng = np.random.default_rng(seed)
        u = self.quad_corners[:, 1] - self.quad_corners[:, 0]
        v = self.quad_corners[:, 3] - self.quad_corners[:, 0]
        area = np.linalg.norm(np.cross(u, v), axis=1)
        q = rng.choice(len(area), size=n, p=area / area.sum())
        a, b = rng.random((2, n, 1))
        return self.quad_corners[q, 0] + a * u[q] + b * v[q]

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance of each point (N, 3) to the nearest quad: how far a camera is from any surface."""
        p0 = self.quad_corners[:, 0]
        u = self.quad_corners[:, 1] - p0
        v = self.quad_corners[:, 3] - p0
        uu = (u * u).sum(1)
        vv = (v * v).sum(1)
        out = np.empty(len(points))
        for i in range(0, len(points), 256):
            d = points[i : i + 256, None, :] - p0[None]  # (n, Q, 3)
            a = np.clip((d * u).sum(-1) / uu, 0, 1)
            b = np.clip((d * v).sum(-1) / vv, 0, 1)
            closest = p0 + a[..., None] * u + b[..., None] * v
            out[i : i + 256] = np.linalg.norm(points[i : i + 256, None, :] - closest, axis=-1).min(axis=1)
        return out

    def in_free_space(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) whether each XY point lies at least `margin` inside one of the free-space polygons."""
        ok = np.zeros(len(xy), bool)
        for poly in self.free_space:
            a = poly
            b = np.roll(poly, -1, axis=0)
            e = b - a
            nrm = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1, keepdims=True)
            sd = ((xy[:, None, :] - a[None]) * nrm[None]).sum(-1).min(axis=1)  # inward distance (CCW)
            ok |= sd >= margin
        return ok


class SceneBuilder:
    """Collects quads, materials and GT segments of one scene."""

    def __init__(
        self, name: str, axes: np.ndarray, axis_names: list[str], seed: int, texels_per_m: float = 256.0
    ):
        self.name = name
        self.axes = np.asarray(axes, float)
        self.axis_names = axis_names
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.texels_per_m = texels_per_m
        self.materials: list[Material] = []
        self._quads: list[tuple] = []
        self._segments: list[np.ndarray] = []
        self._seg_axis: list[int] = []

    def material(
        self, name: str, color_bgr, contrast: float = 0.25, blob: float = 0.15, emissive=False
    ) -> int:
        seed = int(self.rng.integers(0, 2**31))
        self.materials.append(
            Material(name, tuple(float(c) for c in color_bgr), contrast, blob, seed, emissive)
        )
        return len(self.materials) - 1

    def quad(self, p0, u, v, mat: int, segments: str = "", tex_origin=None) -> None:
        """Add rectangle p0, p0+u, p0+u+v, p0+v; `segments` picks GT edges: b(ottom p0->p0+u), r, t, l."""
        p0, u, v = (np.asarray(x, float) for x in (p0, u, v))
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        tu, tv = u / lu, v / lv
        origin = p0 if tex_origin is None else np.asarray(tex_origin, float)
        self._quads.append((p0, u, v, mat, origin, tu, tv))
        edges = {"b": (p0, p0 + u), "r": (p0 + u, p0 + u + v), "t": (p0 + v, p0 + u + v), "l": (p0, p0 + v)}
        for key in segments:
            self.segment(*edges[key])

    def segment(self, a, b, axis: int | None = None) -> None:
        a, b = np.asarray(a, float), np.asarray(b, float)
        if axis is None:
            d = (b - a) / np.linalg.norm(b - a)
            c = np.abs(self.axes @ d)
            best = int(np.argmax(c))
            axis = best if c[best] >= math.cos(math.radians(AXIS_LABEL_TOL_DEG)) else -1
        self._segments.append(np.stack([a, b]))
        self._seg_axis.append(axis)

    def build(self, route, free_space, eye_height=1.6, background=(0.0, 0.0, 0.0), pitch_deg=-4.0) -> Scene:
        q = self._quads
        corners = np.array([[p, p + u, p + u + v, p + v] for p, u, v, *_ in q])
        return Scene(
            texels_per_m=self.texels_per_m,
            name=self.name,
            quad_corners=corners,
            quad_material=np.array([x[3] for x in q], np.int64),
            tex_origin=np.array([x[4] for x in q]),
            tex_u=np.array([x[5] for x in q]),
            tex_v=np.array([x[6] for x in q]),
            materials=self.materials,
            segments=np.array(self._segments).reshape(-1, 2, 3),
            segment_axis=np.array(self._seg_axis, np.int64),
            axes=self.axes / np.linalg.norm(self.axes, axis=1, keepdims=True),
            axis_names=self.axis_names,
            route=np.asarray(route, float),
            free_space=[np.asarray(p, float) for p in free_space],
            eye_height=eye_height,
            pitch_deg=pitch_deg,
            background_bgr=background,
            seed=self.seed,
        )


# ---- shared pieces -----------------------------------------------------------------------------

Z = np.array([0.0, 0.0, 1.0])


def _hdir(yaw_deg: float) -> np.ndarray:
    a = math.radians(yaw_deg)
    return np.array([math.cos(a), math.sin(a), 0.0])


def _wall(
    b: SceneBuilder,
    start,
    end,
    height: float,
    mat: int,
    openings=(),
    junctions: str = "bt",
    skirting: int | None = None,
    opening_segments: bool = True,
) -> None:
    """A vertical wall from `start` to `end` (XY at z=0, seen from its left), with doorway openings.

    `openings` are (offset along the wall, width, top) holes from the floor. GT segments: floor and
    ceiling junctions ('b', 't' in `junctions`), opening jambs and lintels, skirting top edges.
    """
    s = np.array([start[0], start[1], 0.0])
    e = np.array([end[0], end[1], 0.0])
    d = e - s
    length = float(np.linalg.norm(d))
    dh = d / length
    hv = Z * height
    cuts = [0.0]
    for off, w, top in sorted(openings):
        cuts += [off, off + w]
        # the lintel overlaps its neighbours by 2 cm (same plane and texture) so no seam can open
        b.quad(s + dh * (off - 0.02) + Z * top, dh * (w + 0.04), Z * (height - top), mat, tex_origin=s)
        if opening_segments:
            b.segment(s + dh * off + Z * top, s + dh * (off + w) + Z * top)
            b.segment(s + dh * off, s + dh * off + Z * top)
            b.segment(s + dh * (off + w), s + dh * (off + w) + Z * top)
    cuts.append(length)
    for a0, a1 in zip(cuts[0::2], cuts[1::2], strict=True):
        if a1 - a0 < 1e-6:
            continue
        b.quad(s + dh * a0, dh * (a1 - a0), hv, mat, tex_origin=s)
        if skirting is not None:
            n_in = np.array([-dh[1], dh[0], 0.0]) * 0.01  # 1 cm proud of the wall, on its left side
            b.quad(s + dh * a0 + n_in, dh * (a1 - a0), Z * 0.1, skirting, segments="bt")
        elif "b" in junctions:
            b.segment(s + dh * a0, s + dh * a1)
    if "t" in junctions:
        b.segment(s + hv, e + hv)


def _panel(
    b: SceneBuilder, wall_start, wall_end, offset, width, bottom, height, mat, proud=0.01, tilt_deg=0.0
):
    """A rectangle on a wall's left face (door, window, poster); tilted in the wall plane if asked."""
    s = np.array([wall_start[0], wall_start[1], 0.0])
    d = np.array([wall_end[0], wall_end[1], 0.0]) - s
    dh = d / np.linalg.norm(d)
    n_in = np.array([-dh[1], dh[0], 0.0])
    centre = s + dh * (offset + width / 2) + Z * (bottom + height / 2) + n_in * proud
    t = math.radians(tilt_deg)
    u = (math.cos(t) * dh + math.sin(t) * Z) * width
    v = (-math.sin(t) * dh + math.cos(t) * Z) * height
    b.quad(centre - u / 2 - v / 2, u, v, mat, segments="brtl")


# ---- corridor ----------------------------------------------------------------------------------


def corridor(seed: int = 0) -> Scene:
    """Indoor Manhattan ring corridor around a block, rooms behind open doorways, windows, lights."""
    b = SceneBuilder("corridor", [Z, [1, 0, 0], [0, 1, 0]], ["vertical", "x", "y"], seed)
    rng = b.rng
    H = 2.7
    wall = b.material("wall", (0.78, 0.80, 0.82), 0.14, 0.12)
    wall2 = b.material("wall-inner", (0.55, 0.68, 0.78), 0.14, 0.10)
    room = b.material("room-wall", (0.45, 0.62, 0.70), 0.25, 0.15)
    floor = b.material("floor", (0.30, 0.38, 0.45), 0.35, 0.08)
    ceil = b.material("ceiling", (0.88, 0.88, 0.88), 0.10, 0.25)
    skirt = b.material("skirting", (0.20, 0.22, 0.25), 0.08, 0.3)
    door = b.material("door", (0.25, 0.40, 0.55), 0.15, 0.3)
    window = b.material("window", (0.95, 0.90, 0.80), 0.05, 0.5, emissive=True)
    light = b.material("light", (0.97, 0.99, 1.0), 0.02, 0.5, emissive=True)
    poster = b.material("poster", (0.30, 0.35, 0.75), 0.45, 0.06)
    # block [-4, 4] x [-2, 2], corridor ring 2 m wide, outer walls at x = +-6, y = +-4
    for x0, x1, y0, y1 in ((-6, 6, 2, 4), (-6, 6, -4, -2), (4, 6, -2.02, 2.02), (-6, -4, -2.02, 2.02)):
        b.quad([x0, y0, 0], [x1 - x0, 0, 0], [0, y1 - y0, 0], floor, tex_origin=[-6, -4, 0])
        b.quad([x0, y0, H], [0, y1 - y0, 0], [x1 - x0, 0, 0], ceil, tex_origin=[-6, -4, H])
    # inner block walls, seen from the corridor (left side when walking counter-clockwise around it)
    block = [(4, 2), (4, -2), (-4, -2), (-4, 2)]  # clockwise: the corridor is on each wall's left
    for i in range(4):
        s, e = block[i], block[(i + 1) % 4]
        _wall(b, s, e, H, wall2, skirting=skirt)
        length = float(np.hypot(e[0] - s[0], e[1] - s[1]))
        _panel(b, s, e, length * 0.2, 0.9, 0.0, 2.05, door, proud=0.03)
        _panel(b, s, e, length * 0.55, 0.7, 1.1, 0.5, poster, tilt_deg=float(rng.uniform(15, 35)))
    for x, y in block:  # convex vertical corners of the block
        b.segment([x, y, 0.1], [x, y, H])
    # outer walls (counter-clockwise: the corridor is on their left)
    outer = [(-6, -4), (6, -4), (6, 4), (-6, 4)]
    doorway = {1: (3.0, 1.0, 2.1), 2: (2.5, 1.0, 2.1)}  # wall index -> (offset, width, top)
    for i in range(4):
        s, e = outer[i], outer[(i + 1) % 4]
        ops = [doorway[i]] if i in doorway else []
        _wall(b, s, e, H, wall, openings=ops, skirting=skirt)
        length = float(np.hypot(e[0] - s[0], e[1] - s[1]))
        for off in (0.15, 0.7) if i == 0 else (0.45, 0.75) if i == 2 else (0.65,):
            _panel(b, s, e, length * off, 1.2, 1.0, 1.0, window)
    for x, y in outer:  # concave corners
        b.segment([x, y, 0.1], [x, y, H])
    # rooms behind the doorways: 3 x 3 m boxes, walls seen from inside
    for wall_i, (off, w, _top) in doorway.items():
        s, e = np.array(outer[wall_i], float), np.array(outer[(wall_i + 1) % 4], float)
        dh = (e - s) / np.linalg.norm(e - s)
        out = np.array([dh[1], -dh[0]])  # away from the corridor
        c0 = s + dh * (off + w / 2 - 1.5)
        r = [c0, c0 + out * 3, c0 + out * 3 + dh * 3, c0 + dh * 3]  # room footprint
        for k in range(3):
            _wall(b, r[k], r[k + 1], H, room, junctions="bt")
        for k in range(4):
            b.segment([*r[k], 0], [*r[k], H])
        p0 = np.array([*r[0], 0.0])
        b.quad(p0, np.r_[out * 3, 0], np.r_[dh * 3, 0], floor, tex_origin=[-6, -4, 0])
        b.quad(p0 + Z * H, np.r_[dh * 3, 0], np.r_[out * 3, 0], ceil)
        # the room's side of the doorway wall, 1 cm behind the corridor's side
        back = out * 0.01
        _wall(
            b,
            r[3] + back,
            r[0] + back,
            H,
            room,
            openings=[(1.5 - w / 2, w, 2.1)],
            junctions="",
            opening_segments=False,
        )
    # ceiling lights along the corridor centre line, 1 cm below the ceiling
    for cx in np.arange(-4.5, 4.6, 3.0):
        for cy in (3.0, -3.0):
            b.quad([cx - 0.6, cy - 0.15, H - 0.01], [1.2, 0, 0], [0, 0.3, 0], light, segments="brtl")
    for cy in (-0.6, 1.2):
        for cx in (5.0, -5.0):
            b.quad([cx - 0.15, cy - 0.6, H - 0.01], [0.3, 0, 0], [0, 1.2, 0], light, segments="brtl")
    route = [(0, -3), (5, -3), (5, 3), (-5, 3), (-5, -3)]
    free = [
        np.array([[-5.7, -3.7], [5.7, -3.7], [5.7, -2.3], [-5.7, -2.3]]),
        np.array([[-5.7, 2.3], [5.7, 2.3], [5.7, 3.7], [-5.7, 3.7]]),
        np.array([[4.3, -3.7], [5.7, -3.7], [5.7, 3.7], [4.3, 3.7]]),
        np.array([[-5.7, -3.7], [-4.3, -3.7], [-4.3, 3.7], [-5.7, 3.7]]),
    ]
    return b.build(route, free, eye_height=1.6, background=(0.1, 0.1, 0.1))


# ---- atlanta -----------------------------------------------------------------------------------


def atlanta(seed: int = 0) -> Scene:
    """Outdoor plaza ringed by six buildings whose facades face 0, 35 and 70 degrees (and +90)."""
    yaws = (0.0, 35.0, 70.0)
    dirs = [Z] + [_hdir(y) for y in yaws] + [_hdir(y + 90) for y in yaws]
    names = ["vertical"] + [f"h{int(y)}" for y in yaws] + [f"h{int(y + 90)}" for y in yaws]
    b = SceneBuilder("atlanta", dirs, names, seed, texels_per_m=128.0)
    rng = b.rng
    ground = b.material("ground", (0.42, 0.44, 0.45), 0.25, 0.10)
    facades = [
        b.material(f"facade{i}", c, 0.25, 0.2)
        for i, c in enumerate(
            [(0.55, 0.65, 0.80), (0.70, 0.72, 0.70), (0.45, 0.55, 0.70), (0.75, 0.70, 0.60)]
        )
    ]
    glass = b.material("glass", (0.35, 0.28, 0.22), 0.10, 0.4)
    door = b.material("door", (0.15, 0.25, 0.35), 0.12, 0.3)
    sign = b.material("sign", (0.20, 0.55, 0.85), 0.45, 0.05)
    b.quad([-30, -30, 0], [60, 0, 0], [0, 60, 0], ground)
    for k in range(6):
        phi = math.radians(60 * k + 10)
        centre = 17.0 * np.array([math.cos(phi), math.sin(phi)])
        yaw = yaws[k % 3]
        w, d = rng.uniform(7, 9.5), rng.uniform(6, 9)
        h = float(rng.uniform(8, 14))
        ex, ey = _hdir(yaw)[:2], _hdir(yaw + 90)[:2]
        fp = [centre + sx * w / 2 * ex + sy * d / 2 * ey for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        mat = facades[k % len(facades)]
        for i in range(4):  # CCW footprint: the outside of the building is on each wall's right
            s, e = fp[(i + 1) % 4], fp[i]  # reversed so the street is on the wall's left
            _wall(b, s, e, h, mat, junctions="bt")
            length = float(np.linalg.norm(e - s))
            n_win = int(length // 2.2)
            floors = int((h - 1.0) // 3.0)
            for fl in range(floors):
                for j in range(n_win):
                    off = (length - n_win * 2.2) / 2 + 2.2 * j + 0.5
                    if fl == 0 and j == n_win // 2:
                        _panel(b, s, e, off - 0.1, 1.4, 0.0, 2.3, door, proud=0.03)
                        continue
                    _panel(b, s, e, off, 1.2, 1.0 + 3.0 * fl, 1.5, glass, proud=0.03)
            if i == k % 4:
                _panel(
                    b,
                    s,
                    e,
                    length * 0.1,
                    1.2,
                    2.6,
                    0.8,
                    sign,
                    proud=0.05,
                    tilt_deg=float(rng.uniform(20, 30)),
                )
        for p in fp:
            b.segment([p[0], p[1], 0.0], [p[0], p[1], h])
    n = 16
    route = [
        (5.0 * math.cos(2 * math.pi * i / n - math.pi / 2), 5.0 * math.sin(2 * math.pi * i / n - math.pi / 2))
        for i in range(n)
    ]
    free = [
        np.array(
            [(8.0 * math.cos(2 * math.pi * i / 24), 8.0 * math.sin(2 * math.pi * i / 24)) for i in range(24)]
        )
    ]
    return b.build(route, free, eye_height=1.6, background=(0.92, 0.80, 0.62), pitch_deg=7.0)


# ---- garage ------------------------------------------------------------------------------------


def garage(seed: int = 0) -> Scene:
    """Low-texture parking garage: plain walls, square pillars, painted bay lines, few corners."""
    b = SceneBuilder("garage", [Z, [1, 0, 0], [0, 1, 0]], ["vertical", "x", "y"], seed, texels_per_m=170.0)
    H = 2.5
    wall = b.material("wall", (0.62, 0.63, 0.62), 0.04, 0.4)
    floor = b.material("floor", (0.40, 0.41, 0.41), 0.06, 0.3)
    ceil = b.material("ceiling", (0.70, 0.70, 0.70), 0.03, 0.5)
    pillar = b.material("pillar", (0.72, 0.74, 0.75), 0.03, 0.5)
    paint = b.material("paint", (0.85, 0.90, 0.92), 0.03, 0.5)
    stripe = b.material("stripe", (0.10, 0.75, 0.90), 0.03, 0.5)
    X, Y = 12.0, 8.0
    b.quad([-X, -Y, 0], [2 * X, 0, 0], [0, 2 * Y, 0], floor)
    b.quad([-X, -Y, H], [0, 2 * Y, 0], [2 * X, 0, 0], ceil)
    outer = [(-X, -Y), (X, -Y), (X, Y), (-X, Y)]
    for i in range(4):
        _wall(b, outer[i], outer[(i + 1) % 4], H, wall)
        b.segment([*outer[i], 0], [*outer[i], H])
    for px in (-6.0, -2.0, 2.0, 6.0):
        for py in (-2.5, 2.5):
            c = [
                (px - 0.25, py - 0.25),
                (px + 0.25, py - 0.25),
                (px + 0.25, py + 0.25),
                (px - 0.25, py + 0.25),
            ]
            for i in range(4):
                _wall(b, c[(i + 1) % 4], c[i], H, pillar)
                b.segment([*c[i], 0], [*c[i], H])
    # painted bay lines along the long walls, 2 cm proud of the floor... 5 mm
    for x in np.arange(-10.0, 10.1, 2.5):
        for y0, y1 in ((-Y, -Y + 4.5), (Y - 4.5, Y)):
            b.quad([x - 0.06, y0, 0.005], [0.12, 0, 0], [0, y1 - y0, 0], paint, segments="lr")
    # a hatched no-parking area: oblique stripes (non-structural)
    for k in range(4):
        x0 = 8.0 + 0.6 * k
        p0 = np.array([x0, -1.5, 0.005])
        u = np.array([0.9, 0.9, 0.0])
        v = np.array([-0.12, 0.12, 0.0])
        b.quad(p0, u, v, stripe, segments="bt")
    route = [(0, -5.5), (9.3, -5.5), (9.3, 5.5), (-9.3, 5.5), (-9.3, -5.5)]
    free = [
        np.array([[-11.7, -7.7], [11.7, -7.7], [11.7, -3.0], [-11.7, -3.0]]),
        np.array([[-11.7, 3.0], [11.7, 3.0], [11.7, 7.7], [-11.7, 7.7]]),
        np.array([[6.5, -7.7], [11.7, -7.7], [11.7, 7.7], [6.5, 7.7]]),
        np.array([[-11.7, -7.7], [-6.5, -7.7], [-6.5, 7.7], [-11.7, 7.7]]),
    ]
    return b.build(route, free, eye_height=1.5, background=(0.05, 0.05, 0.05))


SCENES: dict[str, Callable[[int], Scene]] = {"corridor": corridor, "atlanta": atlanta, "garage": garage}

#: Low-texture scenes: materials of large surfaces made blank (walls, ceilings, pillars, facades)...
BLANK_MATERIALS = ("wall", "room-wall", "ceiling", "pillar", "facade")
#: ...and those made faint (floors, ground): this fraction of their texture contrast is kept.
FAINT_MATERIALS = ("floor", "ground")
FAINT_CONTRAST = 0.2


def low_texture(scene: Scene) -> Scene:
    """The same scene (geometry, GT segments, axes, route) with blank walls and ceilings and faint floors.

    Materials whose names start with one of BLANK_MATERIALS get no texture at all (a plain colour,
    still shaded by orientation, so junctions and corners stay visible as intensity edges); those
    starting with FAINT_MATERIALS keep FAINT_CONTRAST of their contrast. Doors, windows, posters,
    skirting, lights and paint are unchanged: they are the few places with texture left.
    """
    mats = []
    for m in scene.materials:
        if m.emissive:
            mats.append(m)
        elif m.name.startswith(BLANK_MATERIALS):
            mats.append(dataclasses.replace(m, contrast=0.0))
        elif m.name.startswith(FAINT_MATERIALS):
            mats.append(dataclasses.replace(m, contrast=m.contrast * FAINT_CONTRAST))
        else:
            mats.append(m)
    return dataclasses.replace(scene, materials=mats)


def make_scene(name: str, seed: int = 0) -> Scene:
    """Build a named scene; InputError listing the known names when `name` is unknown."""
    try:
        builder = SCENES[name]
    except KeyError:
        raise InputError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}") from None
    return builder(seed)
