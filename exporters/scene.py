"""What an export writes: the map's parts selected, checked and grouped, ready for any format.

`prepare(map, options)` turns a Map into an `ExportScene`: line segments sorted into one group per
axis (plus unanchored) with their palette colours, points, the trajectory and camera frusta, each
checked for NaN or infinite values (refused naming the offending ids). Every format module reads
only this, so selection, colouring and checks are the same in every file.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.errors import ConfigError, MapFormatError
from papl_mapper.map import Map
from papl_mapper.palette import PALETTES, UNANCHORED_RGB, axis_colors, axis_names
from papl_mapper.scale.estimate import units_note

log = logging.getLogger(__name__)

PARTS = ("lines", "points", "trajectory", "frusta")
#: Trajectory and frusta colour (the previews' dark violet: not in any axis palette).
TRAJECTORY_RGB: tuple[int, int, int] = (110, 40, 150)


@dataclass
class ExportOptions:
    """Options every exporter understands (formats ignore the ones that do not apply to them)."""

    parts: tuple[str, ...] = ("lines", "points", "trajectory")
    """Which parts of the map to write: any of lines, points, trajectory, frusta."""
    min_observations: int = 0
    """Leave out lines with fewer 2D observations than this (one per keyframe; 0 keeps every line)."""
    min_axis_weight: float = 0.5
    """A line belongs to its best axis when anchored with at least this weight, else it is unanchored."""
    palette: str = "okabe-ito"
    """Axis palette (papl_mapper.palette.PALETTES); the vertical axis is always blue, unanchored grey."""
    ascii: bool = False
    """PLY only: write ASCII instead of binary little-endian."""
    tube_radius: float = 0.001
    """Tubes: radius as a fraction of the scene's bounding-box diagonal."""
    tube_sides: int = 6
    """Tubes: number of sides of each tube (3 or more)."""
    line_width: float = 0.0015
    """USD: curve width as a fraction of the scene's bounding-box diagonal."""
    point_size: float = 0.002
    """USD: point width as a fraction of the scene's bounding-box diagonal."""
    frustum_depth: float = 0.02
    """Frusta: depth of each camera frustum as a fraction of the scene's bounding-box diagonal."""
    image_name: str = "frame_{frame_index:06d}.png"
    """COLMAP: image file name pattern, formatted with the keyframe's id and frame_index."""
    cad_min_observations: int = 3
    """CAD exports (DXF, plan, elevation): lines seen in fewer keyframes than this are stray."""
    cad_stray_margin: float = 3.0
    """CAD exports: geometry beyond the structure's interquartile box by more than this many times its
    size (Tukey's far-out fences) is stray."""
    elevation_axis: int = 1
    """Elevation: the horizontal axis (1-based, as in 'horizontal 1') to look along; a file named
    elevation-K.dxf or .svg sets it to K."""
    keep_stray: bool = False
    """CAD exports: keep stray lines and points (on a STRAY layer that is off) instead of leaving them out."""

    def check(self) -> None:
        """Raise ConfigError naming the first option with an impossible value."""
        bad = [p for p in self.parts if p not in PARTS]
        if bad:
            raise ConfigError(f"export option parts: unknown part(s) {bad}; choose from {list(PARTS)}")
        if self.palette not in PALETTES:
            raise ConfigError(
                f"export option palette: unknown {self.palette!r}; choose one of {sorted(PALETTES)}"
            )
        if self.elevation_axis < 1:
            raise ConfigError(f"export option elevation_axis must be >= 1, got {self.elevation_axis}")
        if self.cad_min_observations < 0:
            raise ConfigError(
                f"export option cad_min_observations must be >= 0, got {self.cad_min_observations}"
            )
        if not (np.isfinite(self.cad_stray_margin) and self.cad_stray_margin >= 0):
            raise ConfigError(f"export option cad_stray_margin must be >= 0, got {self.cad_stray_margin}")
        if self.min_observations < 0:
            raise ConfigError(f"export option min_observations must be >= 0, got {self.min_observations}")
        if self.tube_sides < 3:
            raise ConfigError(f"export option tube_sides must be >= 3, got {self.tube_sides}")
        for name in ("tube_radius", "line_width", "point_size", "frustum_depth"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"export option {name} must be a positive fraction, got {v}")
        try:
            self.image_name.format(id=0, frame_index=0)
        except (KeyError, IndexError, ValueError) as exc:
            raise ConfigError(
                f"export option image_name {self.image_name!r}: use only {{id}} and {{frame_index}} ({exc})"
            ) from exc


@dataclass
class SegmentGroup:
    """Segments of one kind drawn in one colour: an axis, the unanchored lines, or the frusta."""

    name: str  # human name, e.g. "vertical", "horizontal 1", "unanchored", "frusta"
    key: str  # identifier-safe name, e.g. "vertical", "horizontal_1"
    rgb: tuple[int, int, int]  # sRGB 0..255
    segments_w: np.ndarray  # (S, 2, 3) float64, world (+Z up)
    ids: np.ndarray  # (S,) int64: line ids (keyframe ids for frusta)
    axis_index: int = -1  # the map's axis index, -1 when not an axis
    direction_w: np.ndarray | None = None  # (3,) the axis direction, when an axis
    observations: np.ndarray | None = None  # (S,) keyframes that saw each line, when lines


@dataclass
class ExportScene:
    """The selected, checked parts of a map, grouped the way every exporter writes them."""

    line_groups: list[SegmentGroup]  # one per axis in axis order, then unanchored; empty groups kept
    frusta: SegmentGroup | None
    points_xyz: np.ndarray  # (P, 3) float64
    points_rgb: np.ndarray  # (P, 3) uint8
    points_ids: np.ndarray  # (P,) int64
    trajectory_w: np.ndarray  # (N, 3) float64 camera centres in time order (empty when not exported)
    keyframe_ids: np.ndarray  # (N,)
    units: str
    diagonal: float  # robust bounding-box diagonal of everything exported (1.0 when empty)
    axis_info: list[dict] = field(default_factory=list)  # name, direction, colour per axis
    scale_note: str = "arbitrary (monocular scale unknown)"  # how the units were found, one safe line
    vertical_index: int = -1  # the map's vertical axis, -1 when none

    @property
    def n_segments(self) -> int:
        return sum(len(g.ids) for g in self.line_groups)

    def segment_groups(self) -> list[SegmentGroup]:
        """Non-empty line groups, then the trajectory as segments, then frusta (for line-only formats)."""
        out = [g for g in self.line_groups if len(g.ids)]
        if len(self.trajectory_w) >= 2:
            seg = np.stack([self.trajectory_w[:-1], self.trajectory_w[1:]], axis=1)
            out.append(SegmentGroup("trajectory", "trajectory", TRAJECTORY_RGB, seg, self.keyframe_ids[1:]))
        if self.frusta is not None and len(self.frusta.ids):
            out.append(self.frusta)
        return out

    @property
    def is_empty(self) -> bool:
        return self.n_segments == 0 and len(self.points_xyz) == 0 and len(self.trajectory_w) == 0

    @property
    def meters_per_unit(self) -> float | None:
        """Metres per map unit when the units are known, None for arbitrary (monocular) scale."""
        return _METERS.get(self.units)

    def structure_box(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) Tukey fences of the anchored lines and the trajectory: the interquartile box grown by
        `margin` times its size on each axis (each at least 5% of the largest): what lies outside is
        stray for CAD drawings. Quartiles, unlike the extremes, ignore a few stray lines far away."""
        parts = [g.segments_w.reshape(-1, 3) for g in self.line_groups if g.axis_index >= 0]
        parts = [p for p in parts if len(p)] or [g.segments_w.reshape(-1, 3) for g in self.line_groups]
        xyz = np.concatenate([*parts, self.trajectory_w, np.zeros((0, 3))])
        if not len(xyz):
            xyz = self.points_xyz if len(self.points_xyz) else np.zeros((1, 3))
        q1, q3 = np.percentile(xyz, [25, 75], axis=0)
        iqr = np.maximum(q3 - q1, 0.05 * max(float((q3 - q1).max()), 1e-12))
        return q1 - margin * iqr, q3 + margin * iqr


_METERS = {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "cm": 0.01, "mm": 0.001}


def header_text(text: object, limit: int = 200) -> str:
    """`text` made safe for any file header: one line of printable ASCII (others become '?'), cut short."""
    s = "".join(c if " " <= c <= "~" else "?" for c in str(text))
    return s[:limit]


def scale_note(metadata: dict) -> str:
    """How the map's units were found, as one header-safe line ('arbitrary ...' when unscaled)."""
    return header_text(units_note(metadata).replace("±", "+-"))


def stray_mask(xyz: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(N,) True where any of the points (N, ..., 3) lies outside the box."""
    lo, hi = box
    if len(xyz) == 0:
        return np.zeros(0, bool)
    out = (xyz < lo) | (xyz > hi)
    return out.reshape(len(xyz), -1).any(axis=1)


def cad_split(
    scene: ExportScene, options: ExportOptions
) -> tuple[list[SegmentGroup], SegmentGroup, np.ndarray]:
    """Line groups without their stray lines, the stray lines as one group, and the points kept.

    Stray: seen in fewer than `cad_min_observations` keyframes, or reaching outside the structure box.
    """
    box = scene.structure_box(options.cad_stray_margin)
    kept, stray_seg, stray_ids = [], [], []
    for g in scene.line_groups:
        bad = stray_mask(g.segments_w, box)
        if g.observations is not None:
            bad |= g.observations < options.cad_min_observations
        kept.append(
            SegmentGroup(
                g.name, g.key, g.rgb, g.segments_w[~bad], g.ids[~bad], g.axis_index, g.direction_w,
                None if g.observations is None else g.observations[~bad],
            )
        )  # fmt: skip
        stray_seg.append(g.segments_w[bad])
        stray_ids.append(g.ids[bad])
    stray = SegmentGroup(
        "stray",
        "stray",
        UNANCHORED_RGB,
        np.concatenate(stray_seg).reshape(-1, 2, 3),
        np.concatenate(stray_ids),
    )
    return kept, stray, ~stray_mask(scene.points_xyz, box)


def prepare(m: Map, options: ExportOptions) -> ExportScene:
    """Select the parts asked for, check them for non-finite values, group lines by axis."""
    options.check()
    parts = set(options.parts)
    lines = m.lines
    n_axes = len(m.axes)
    vertical = m.axes.vertical_index if m.axes.vertical_index >= 0 else None
    groups: list[SegmentGroup] = []
    keep = np.zeros(len(lines), bool)
    n_obs = observation_counts(lines.ids, lines.obs_ids[:, 0]) if len(lines) else np.zeros(0, np.int64)
    if "lines" in parts and len(lines):
        keep[:] = True
        if options.min_observations > 0:
            keep &= n_obs >= options.min_observations
        check_finite(lines.endpoints_w[keep], lines.ids[keep], "lines.endpoints_w")
    axis = lines.axis_of_line(options.min_axis_weight) if len(lines) else np.zeros(0, np.int64)
    check_finite(m.axes.directions, np.arange(n_axes), "axes.directions")
    colors = axis_colors(n_axes, vertical, options.palette)
    names = axis_names(n_axes, vertical)
    # one stable sort by group key (axes 0..A-1, unanchored = A) instead of a mask per group
    key = np.where(axis < 0, n_axes, axis)[keep]
    idx = np.flatnonzero(keep)[np.argsort(key, kind="stable")]
    bounds = np.searchsorted(np.sort(key), np.arange(n_axes + 2))
    for a in range(n_axes + 1):
        sel = idx[bounds[a] : bounds[a + 1]]
        if a < n_axes:
            g = SegmentGroup(
                names[a], names[a].replace(" ", "_"), tuple(int(c) for c in colors[a]),
                lines.endpoints_w[sel], lines.ids[sel], a, m.axes.directions[a].copy(), n_obs[sel],
            )  # fmt: skip
        else:
            g = SegmentGroup(
                "unanchored", "unanchored", UNANCHORED_RGB, lines.endpoints_w[sel], lines.ids[sel],
                observations=n_obs[sel],
            )  # fmt: skip
        groups.append(g)
    if "points" in parts and len(m.points):
        pts, prgb, pids = m.points.xyz, m.points.color, m.points.ids
        check_finite(pts, pids, "points.xyz")
    else:
        pts, prgb, pids = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64)
    kf = m.keyframes
    want_kf = bool({"trajectory", "frusta"} & parts) and len(kf) > 0
    if want_kf:
        check_finite(kf.T_wc, kf.ids, "keyframes.T_wc")
        order = np.argsort(kf.timestamp, kind="stable")
        centres = kf.T_wc[order, :3, 3]
    traj = centres if want_kf and "trajectory" in parts else np.zeros((0, 3))
    traj_ids = kf.ids[order] if want_kf and "trajectory" in parts else np.zeros(0, np.int64)
    diagonal = _robust_diagonal(
        [g.segments_w.reshape(-1, 3) for g in groups] + [pts] + ([centres] if want_kf else [])
    )
    frusta = None
    if "frusta" in parts and len(kf):
        seg = frustum_segments(m, options.frustum_depth * diagonal)
        frusta = SegmentGroup("frusta", "frusta", TRAJECTORY_RGB, seg, np.repeat(kf.ids, 8))
    info = [
        {"index": a, "name": names[a], "direction": [float(v) for v in m.axes.directions[a]],
         "color_srgb": [int(c) for c in colors[a]], "vertical": a == vertical}
        for a in range(n_axes)
    ]  # fmt: skip
    scene = ExportScene(
        groups,
        frusta,
        pts,
        prgb,
        pids,
        traj,
        traj_ids,
        header_text(m.metadata.get("units", "arbitrary"), 40),
        diagonal,
        info,
        scale_note(m.metadata),
        int(vertical) if vertical is not None else -1,
    )
    if scene.is_empty:
        log.warning(
            "the map has nothing to export for parts %s: writing a valid empty file", list(options.parts)
        )
    return scene


def observation_counts(ids: np.ndarray, obs_ids: np.ndarray) -> np.ndarray:
    """(M,) how many observations name each id (observations of unknown ids are ignored)."""
    if len(ids) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(ids)
    pos = np.searchsorted(ids, obs_ids, sorter=order)
    pos = np.clip(pos, 0, len(ids) - 1)
    hit = ids[order[pos]] == obs_ids
    return np.bincount(order[pos[hit]], minlength=len(ids)).astype(np.int64)


def frustum_corners(m: Map, depth: float) -> np.ndarray:
    """(N, 4, 3) world points `depth` in front of every keyframe on the rays through the image's outer
    corners, clockwise from the top left. The image spans -0.5 .. width - 0.5 (pixel centres at integer
    coordinates, DESIGN.md), so the frustum holds every pixel whole, not only the corner pixels' centres.
    The one frustum of the exports, the viewer and the previews."""
    c = m.camera
    u = np.array([-0.5, c.width - 0.5, c.width - 0.5, -0.5])
    v = np.array([-0.5, -0.5, c.height - 0.5, c.height - 0.5])
    rays_c = np.stack([(u - c.cx) / c.fx, (v - c.cy) / c.fy, np.ones(4)], axis=1) * depth  # (4, 3)
    T = m.keyframes.T_wc  # (N, 4, 4)
    return np.einsum("nij,kj->nki", T[:, :3, :3], rays_c) + T[:, None, :3, 3]  # (N, 4, 3)


def frustum_segments(m: Map, depth: float) -> np.ndarray:
    """(8N, 2, 3) frustum edges of every keyframe: 4 rays from the centre to the image corners, 4 rims."""
    corners = frustum_corners(m, depth)
    T = m.keyframes.T_wc  # (N, 4, 4)
    centre = np.broadcast_to(T[:, None, :3, 3], corners.shape)
    rays = np.stack([centre, corners], axis=2)  # (N, 4, 2, 3)
    rims = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)  # (N, 4, 2, 3)
    return np.concatenate([rays, rims], axis=1).reshape(-1, 2, 3)


def _robust_diagonal(arrays: list[np.ndarray]) -> float:
    """Diagonal of the 1st..99th percentile box of all positions (stray points do not blow it up)."""
    arrays = [a for a in arrays if len(a)]
    if not arrays:
        return 1.0
    xyz = np.concatenate(arrays)
    if len(xyz) > 200_000:  # a strided sample is plenty for percentiles and keeps this O(1) in memory
        xyz = xyz[:: len(xyz) // 100_000]
    lo, hi = np.percentile(xyz, [1, 99], axis=0) if len(xyz) >= 100 else (xyz.min(0), xyz.max(0))
    d = float(np.linalg.norm(hi - lo))
    return d if d > 0 and np.isfinite(d) else 1.0


def check_finite(arr: np.ndarray, ids: np.ndarray, what: str) -> None:
    if arr.size == 0:
        return
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    if bad.any():
        shown = ids[bad][:10].tolist()
        more = f" and {int(bad.sum()) - len(shown)} more" if bad.sum() > len(shown) else ""
        raise MapFormatError(
            f"{what} holds NaN or infinite values for ids {shown}{more}; fix or drop them before exporting"
        )
