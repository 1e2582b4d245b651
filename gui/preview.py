"""Off-screen PNG previews of a Map (isometric, top, front, side) with pyvista/VTK, and a turntable.

Lines are coloured by axis from the one palette (`papl_mapper.palette`), points are faint, the
trajectory and keyframe frusta are optional. Each view is auto-framed (orthographic) to the map;
a title band and a legend naming every axis are drawn onto the image with PIL so the swatches carry
the exact palette colours. Huge maps are decimated (seeded) and the subtitle says so.

No X server is needed: a subprocess probe finds a working off-screen OpenGL window (EGL, then
OSMesa) before VTK is touched in this process, since a missing library makes VTK crash, not raise.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import BackendUnavailableError, InputError
from papl_mapper.extras import require
from papl_mapper.map import Map
from papl_mapper.palette import UNANCHORED_RGB, axis_colors, axis_names, line_colors
from papl_mapper.scale.estimate import units_note

log = logging.getLogger(__name__)

VIEWS = ("isometric", "top", "front", "side")
#: view name -> (direction from the focal point to the camera, camera up), world +Z up.
_VIEW_GEOMETRY: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "isometric": ((1.0, -1.0, 0.8), (0.0, 0.0, 1.0)),
    "top": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "front": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "side": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
}
TRAJECTORY_RGB: tuple[int, int, int] = (110, 40, 150)  # dark violet: not in the axis palette
THEMES: dict[str, dict[str, tuple[int, int, int]]] = {
    "white": {"background": (255, 255, 255), "text": (25, 25, 25), "panel": (245, 245, 245)},
    "dark": {"background": (24, 26, 32), "text": (235, 235, 235), "panel": (40, 43, 52)},
}
#: Off-screen VTK window classes to try: (VTK_DEFAULT_OPENGL_WINDOW value, name, Debian packages).
BACKENDS: tuple[tuple[str, str, str], ...] = (
    ("vtkEGLRenderWindow", "EGL", "libegl1 libgl1"),
    ("vtkOSOpenGLRenderWindow", "OSMesa", "libosmesa6"),
)
_PROBE_CODE = (
    "import vtkmodules.vtkRenderingOpenGL2, vtkmodules.vtkRenderingCore as rc\n"
    "w = rc.vtkRenderWindow(); w.SetOffScreenRendering(1); w.SetSize(8, 8); w.Render()\n"
    "print('PAPL_PROBE', w.GetClassName(), int(w.SupportsOpenGL()))\n"
)


@dataclass
class PreviewOptions:
    """How previews look. Every field has a default; load from TOML with `load_config`."""

    width: int = 1600
    """Image width in pixels."""
    height: int = 1200
    """Image height in pixels (a title band is part of it)."""
    views: tuple[str, ...] = VIEWS
    """Views to render, any of isometric, top, front, side."""
    theme: Literal["white", "dark"] = "white"
    """Background theme: white or dark."""
    line_width: float = 0.0
    """Line width in pixels; 0 picks one readable at the resolution (2.5 px at 1600x1200, at least 2)."""
    show_points: bool = True
    """Draw the map points, faint (blended toward the background)."""
    point_size: float = 0.0
    """Point size in pixels; 0 picks one from the resolution."""
    show_trajectory: bool = True
    """Draw the keyframe trajectory as a polyline."""
    show_frusta: bool = False
    """Draw a small camera frustum at every keyframe."""
    max_lines: int = 200_000
    """More lines than this are decimated (seeded random subset) for the preview."""
    max_points: int = 200_000
    """More points than this are decimated for the preview."""
    max_frusta: int = 40
    """At most this many keyframe frusta are drawn (every k-th keyframe)."""
    palette: str = "okabe-ito"
    """Axis palette name from papl_mapper.palette.PALETTES."""
    turntable: Literal["", "gif", "mp4"] = ""
    """Also write a turntable animation: '' (none), 'gif' or 'mp4'."""
    turntable_frames: int = 36
    """Frames in one turn of the turntable."""
    turntable_size: tuple[int, ...] = (800, 600)
    """Turntable frame size (width, height) in pixels."""
    turntable_fps: float = 12.0
    """Turntable frames per second."""
    seed: int = 0
    """Seed of the decimation subset."""
    title: str = ""
    """Title prefix; empty uses the map's source name if known."""


@dataclass
class Scene:
    """What one map looks like in the previews, prepared once for every view."""

    endpoints_w: np.ndarray  # (m, 2, 3) lines drawn (after decimation)
    line_rgb: np.ndarray  # (m, 3) uint8
    points_w: np.ndarray  # (p, 3) points drawn
    point_rgb: np.ndarray  # (p, 3) uint8, already faded toward the background
    centres_w: np.ndarray  # (k, 3) keyframe centres
    frusta_w: np.ndarray  # (k, 5, 3) apex + 4 image-corner points of each frustum
    legend: list[tuple[str, tuple[int, int, int]]]  # (label, rgb)
    notes: list[str]  # decimation and emptiness notes, shown in the subtitle and the report
    n_lines: int  # lines in the map
    n_points: int  # points in the map

    @property
    def empty(self) -> bool:
        return not (len(self.endpoints_w) or len(self.points_w) or len(self.centres_w))


@dataclass
class PreviewResult:
    """Files written by `render_views`, with the facts the report shows beside them."""

    paths: list[Path]
    views: list[str]
    notes: list[str]
    backend: str
    time_s: dict[str, float] = field(default_factory=dict)
    turntable: Path | None = None


# ---- backend --------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _probe(window_class: str, env_items: tuple[tuple[str, str], ...]) -> tuple[bool, str]:
    env = dict(env_items)
    env["VTK_DEFAULT_OPENGL_WINDOW"] = window_class
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE], env=env, capture_output=True, text=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, str(exc)
    out = proc.stdout.split()
    if proc.returncode == 0 and len(out) >= 3 and out[0] == "PAPL_PROBE" and out[2] == "1":
        return True, out[1]
    tail = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
    if proc.returncode < 0:
        tail = f"crashed with signal {-proc.returncode}: {tail}"
    return False, tail.replace("\x1b[0m", "").replace("\x1b[33m", "")[-300:]


RENDER_MODULES = ("pyvista", "matplotlib", "PIL")
"""What previews import (the 'render' extra); checked before any work so a missing one names the extra."""


def find_offscreen_backend(env: dict[str, str] | None = None) -> str:
    """Name the VTK off-screen window class that renders here (EGL, then OSMesa), probed in a subprocess.

    Raises BackendUnavailableError naming the system packages to install when none works. Waits for
    a search `start_offscreen_probe` began with the same environment instead of probing again.
    """
    return _backend_search(_env_key(env)).result()


def start_offscreen_probe(env: dict[str, str] | None = None) -> None:
    """Begin `find_offscreen_backend` in a thread (each probe is a child process) so that previews
    rendered later find it done; a failure is raised by `find_offscreen_backend`."""
    _backend_search(_env_key(env))


def _env_key(env: dict[str, str] | None) -> tuple[tuple[str, str], ...]:
    return tuple(sorted((os.environ if env is None else env).items()))


@functools.lru_cache(maxsize=8)
def _backend_search(env_items: tuple[tuple[str, str], ...]) -> Future[str]:
    """The search for one environment, started once: a Future of the window class."""
    future: Future[str] = Future()

    def search() -> None:
        try:
            future.set_result(_find_backend(dict(env_items)))
        except BaseException as exc:  # noqa: BLE001 - raised again by whoever waits for it
            future.set_exception(exc)

    threading.Thread(target=search, name="offscreen-probe", daemon=True).start()
    return future


def _find_backend(env: dict[str, str]) -> str:
    forced = env.get("VTK_DEFAULT_OPENGL_WINDOW")
    candidates = list(BACKENDS)
    if env.get("DISPLAY"):
        candidates.append(("vtkXOpenGLRenderWindow", "X11", "a reachable X server at DISPLAY"))
    if forced and forced not in [c[0] for c in BACKENDS]:
        candidates.insert(0, (forced, forced, "the libraries it needs"))
    # each probe sets the window class itself: a class set earlier (by `_plotter`) is no new environment
    probe_env = tuple(sorted((k, v) for k, v in env.items() if k != "VTK_DEFAULT_OPENGL_WINDOW"))
    failures = []
    for window_class, name, _packages in candidates:
        ok, detail = _probe(window_class, probe_env)
        if ok:  # `detail` is the class VTK really made (it may fall back by itself, e.g. EGL -> OSMesa)
            log.debug("off-screen rendering: asked for %s, got %s", name, detail)
            return detail
        failures.append(f"{name}: {detail}")
    raise BackendUnavailableError(
        "no off-screen OpenGL backend works on this machine ("
        + "; ".join(failures)
        + "). Install the system packages for EGL (libegl1 libgl1) or OSMesa (libosmesa6), e.g. "
        "`apt-get install -y libegl1 libgl1 libosmesa6`"
    )


def _plotter(size: tuple[int, int], background: tuple[int, int, int]) -> Any:
    """An off-screen pyvista Plotter on the probed backend."""
    os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = find_offscreen_backend()
    import pyvista as pv

    pl = pv.Plotter(off_screen=True, window_size=list(size), lighting=None)
    pl.set_background([c / 255 for c in background])
    return pl


# ---- scene ----------------------------------------------------------------------------------


def _fade(rgb: np.ndarray, background: tuple[int, int, int], keep: float) -> np.ndarray:
    return (keep * rgb.astype(np.float64) + (1 - keep) * np.asarray(background, np.float64)).astype(np.uint8)


def prepare_scene(m: Map, options: PreviewOptions) -> Scene:
    """Colours, decimation and legend for a map (shared by every view and the report)."""
    rng = np.random.default_rng(options.seed)
    theme = THEMES[options.theme]
    notes: list[str] = []
    n_axes = len(m.axes)
    axis = m.lines.axis_of_line()
    rgb = line_colors(axis, n_axes, m.axes.vertical_index, options.palette)
    ends = m.lines.endpoints_w
    if len(ends) > options.max_lines:
        keep = np.sort(rng.choice(len(ends), options.max_lines, replace=False))
        ends, rgb = ends[keep], rgb[keep]
        notes.append(f"decimated for preview: {len(keep):,} of {len(m.lines):,} lines shown")
    pts = m.points.xyz if options.show_points else np.zeros((0, 3))
    prgb = m.points.color if options.show_points else np.zeros((0, 3), np.uint8)
    if len(pts) > options.max_points:
        keep = np.sort(rng.choice(len(pts), options.max_points, replace=False))
        pts, prgb = pts[keep], prgb[keep]
        notes.append(f"decimated for preview: {len(keep):,} of {len(m.points):,} points shown")
    prgb = _fade(prgb, theme["background"], 0.45)
    centres = m.keyframes.T_wc[:, :3, 3] if options.show_trajectory else np.zeros((0, 3))
    frusta = np.zeros((0, 5, 3))
    if options.show_frusta and len(m.keyframes):
        step = max(1, math.ceil(len(m.keyframes) / options.max_frusta))
        frusta = _frusta(m, _robust_diagonal(m) * 0.02)[::step]
        if step > 1:
            notes.append(f"every {step}th keyframe frustum drawn")
    legend = [
        (f"{name}  ({int((axis == a).sum()):,})", tuple(int(c) for c in col))
        for a, (name, col) in enumerate(
            zip(
                axis_names(n_axes, m.axes.vertical_index),
                axis_colors(n_axes, m.axes.vertical_index, options.palette),
                strict=True,
            )
        )
    ]
    legend.append((f"unanchored  ({int((axis < 0).sum()):,})", UNANCHORED_RGB))
    if len(centres) or len(frusta):
        legend.append(("trajectory", TRAJECTORY_RGB))
    if len(m.lines) == 0 and len(m.points) == 0 and len(m.keyframes) == 0:
        notes.append("empty map: no lines, points or keyframes")
    elif len(m.lines) == 0:
        notes.append("no lines in this map")
    return Scene(ends, rgb, pts, prgb, centres, frusta, legend, notes, len(m.lines), len(m.points))


def _robust_diagonal(m: Map) -> float:
    xyz = [m.lines.endpoints_w.reshape(-1, 3), m.keyframes.T_wc[:, :3, 3], m.points.xyz]
    xyz = np.concatenate([x for x in xyz if len(x)] or [np.zeros((1, 3))])
    lo, hi = np.percentile(xyz, [1, 99], axis=0)
    return float(np.linalg.norm(hi - lo)) or 1.0


def _frusta(m: Map, depth: float) -> np.ndarray:
    """(K, 5, 3) apex and the four image corners at `depth` in front of each keyframe."""
    from papl_mapper.exporters.scene import frustum_corners  # the exports' and the viewer's frustum

    return np.concatenate([m.keyframes.T_wc[:, None, :3, 3], frustum_corners(m, depth)], axis=1)


def _robust(x: np.ndarray, q: float) -> np.ndarray:
    """Rows of `x` (n, 3) except far strays: beyond the q..100-q percentile range widened by half its span."""
    if len(x) < 50:
        return x
    lo, hi = np.percentile(x, [q, 100 - q], axis=0)
    span = hi - lo
    return x[((x >= lo - 0.5 * span) & (x <= hi + 0.5 * span)).all(axis=1)]


def _framing_points(scene: Scene) -> np.ndarray:
    """(n, 3) the points every view must show: lines, trajectory and points, less far strays."""
    parts = []
    if len(scene.endpoints_w):
        parts.append(_robust(scene.endpoints_w.reshape(-1, 3), 0.5))
    if len(scene.centres_w):
        parts.append(scene.centres_w)
    if len(scene.frusta_w):
        parts.append(scene.frusta_w.reshape(-1, 3))
    if len(scene.points_w):
        parts.append(_robust(scene.points_w, 1.0))
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def _camera_for(
    view_dir: np.ndarray,
    up: np.ndarray,
    pts: np.ndarray,
    size: tuple[int, int],
    reserve_right_px: int = 0,
    margin: float = 1.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Orthographic camera (position, focal point, up, parallel scale) framing `pts` from `view_dir`
    into an image of `size` (w, h) whose right `reserve_right_px` pixels are kept free for the legend."""
    d = view_dir / np.linalg.norm(view_dir)
    right = np.cross(-d, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, -d)
    if len(pts) == 0:
        pts = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    w, h = size
    usable = max(w - reserve_right_px, w // 3)
    x, y, z = pts @ right, pts @ true_up, pts @ d
    cx, cy = 0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max())
    half_h = max(0.5 * (y.max() - y.min()), 0.5 * (x.max() - x.min()) * h / usable) * margin
    half_h = half_h if half_h > 1e-9 else 1.0
    shift = 0.5 * (w - usable) * (2 * half_h / h)  # world units: data centred in the free part
    focal = right * (cx + shift) + true_up * cy + d * 0.5 * (z.min() + z.max())
    dist = max(float(z.max() - z.min()), 2 * half_h) * 2 + 1.0
    return focal + d * dist, focal, true_up, float(half_h)


def _build_plotter(scene: Scene, options: PreviewOptions, size: tuple[int, int]) -> Any:
    import pyvista as pv

    theme = THEMES[options.theme]
    pl = _plotter(size, theme["background"])
    scale = min(size[0] / 1600, size[1] / 1200)
    lw = options.line_width or max(2.0, round(2.5 * scale * 2) / 2)
    ps = options.point_size or max(1.0, round(2.0 * scale))
    if len(scene.points_w):
        cloud = pv.PolyData(np.ascontiguousarray(scene.points_w, dtype=np.float64))
        cloud.point_data["rgb"] = scene.point_rgb
        pl.add_mesh(cloud, scalars="rgb", rgb=True, point_size=ps, lighting=False, style="points")
    if len(scene.endpoints_w):
        m = len(scene.endpoints_w)
        cells = np.column_stack([np.full(m, 2), np.arange(0, 2 * m, 2), np.arange(1, 2 * m, 2)]).ravel()
        seg = pv.PolyData(
            np.ascontiguousarray(scene.endpoints_w.reshape(-1, 3), dtype=np.float64), lines=cells
        )
        seg.cell_data["rgb"] = scene.line_rgb
        pl.add_mesh(seg, scalars="rgb", rgb=True, line_width=lw, lighting=False)
    traj_rgb = [c / 255 for c in TRAJECTORY_RGB]
    if len(scene.centres_w) >= 2:
        actor = pl.add_mesh(
            pv.lines_from_points(scene.centres_w), color=traj_rgb, line_width=1.5 * lw, lighting=False
        )
        _to_overlay(pl, actor)  # the path stays visible inside a dense map
    if len(scene.frusta_w):
        k = len(scene.frusta_w)
        base = np.arange(k)[:, None] * 5
        edges = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]])
        cells = (base[:, None, :] + edges[None]).reshape(-1, 2)
        fr = pv.PolyData(
            scene.frusta_w.reshape(-1, 3), lines=np.column_stack([np.full(len(cells), 2), cells]).ravel()
        )
        pl.add_mesh(fr, color=traj_rgb, line_width=max(1.0, lw / 2), lighting=False)
    return pl


def _to_overlay(pl: Any, actor: Any) -> None:
    """Move `actor` to a second renderer layer drawn over the map with the same camera."""
    from vtkmodules.vtkRenderingCore import vtkRenderer

    top = getattr(pl, "_papl_overlay", None)
    if top is None:
        top = vtkRenderer()
        top.SetLayer(1)
        top.InteractiveOff()
        top.SetActiveCamera(pl.renderer.GetActiveCamera())
        pl.ren_win.SetNumberOfLayers(2)
        pl.ren_win.AddRenderer(top)
        pl._papl_overlay = top
    pl.renderer.RemoveActor(actor)
    top.AddActor(actor)


# ---- overlay (title band and legend) --------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _font(size: int) -> Any:
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)


def _band_height(height: int) -> int:
    return max(24, round(0.075 * height))


def _legend_font_size(height: int) -> int:
    return max(10, round(0.02 * height))


def legend_box(size: tuple[int, int], labels: list[str]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the legend panel in an image of `size`: top-right, below the title band,
    as wide as its longest label."""
    w, h = size
    fs = _legend_font_size(h)
    pad, row = round(0.6 * fs), round(1.5 * fs)
    text_w = max((_font(fs).getlength(lbl) for lbl in labels), default=0.0)
    box_w = round(3 * pad + fs + text_w)
    x1 = w - pad
    y0 = _band_height(h) + pad
    return x1 - box_w, y0, x1, y0 + 2 * pad + row * len(labels)


def _compose(
    render: np.ndarray, scene: Scene, options: PreviewOptions, title: str, subtitle: str
) -> np.ndarray:
    """Paste the render under a title band and draw the legend; returns (H, W, 3) uint8."""
    from PIL import Image, ImageDraw

    theme = THEMES[options.theme]
    h, w = options.height, render.shape[1]
    band = h - render.shape[0]
    canvas = Image.new("RGB", (w, h), theme["panel"])
    canvas.paste(Image.fromarray(render), (0, band))
    draw = ImageDraw.Draw(canvas)
    fs = _legend_font_size(h)
    draw.text((round(0.6 * fs), round(0.12 * band)), title, fill=theme["text"], font=_font(round(1.3 * fs)))
    draw.text(
        (round(0.6 * fs), round(0.58 * band)),
        subtitle,
        fill=theme["text"],
        font=_font(max(9, round(0.9 * fs))),
    )
    x0, y0, x1, y1 = legend_box((w, h), [lbl for lbl, _ in scene.legend])
    draw.rectangle((x0, y0, x1, y1), fill=theme["panel"], outline=theme["text"], width=1)
    pad, row = round(0.6 * fs), round(1.5 * fs)
    for i, (label, rgb) in enumerate(scene.legend):
        y = y0 + pad + i * row
        draw.rectangle((x0 + pad, y + 2, x0 + pad + fs, y + fs + 2), fill=tuple(rgb))
        draw.text((x0 + 2 * pad + fs, y), label, fill=theme["text"], font=_font(fs))
    if scene.empty:
        msg = scene.notes[0] if scene.notes else "nothing to show"
        f = _font(round(1.5 * fs))
        tw = draw.textlength(msg, font=f)
        draw.text(((w - tw) / 2, band + (h - band) / 2), msg, fill=theme["text"], font=f)
    return np.asarray(canvas)


def _save_png(img: np.ndarray, path: Path) -> None:
    from PIL import Image

    with atomic_path(path, suffix=".png") as tmp:
        Image.fromarray(img).save(tmp, optimize=False, compress_level=4)


# ---- public ---------------------------------------------------------------------------------


def render_views(
    m: Map,
    out_dir: str | os.PathLike,
    options: PreviewOptions | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> PreviewResult:
    """Render the chosen views (and optionally a turntable) of `m` into `out_dir` as `<view>.png`."""
    options = options or PreviewOptions()
    _check_options(options)
    for module in RENDER_MODULES:
        require(module, "rendering previews")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = prepare_scene(m, options)
    backend = find_offscreen_backend()
    band = _band_height(options.height)
    size = (options.width, options.height - band)
    t0 = time.perf_counter()
    pl = _build_plotter(scene, options, size)
    times = {"setup_s": time.perf_counter() - t0}
    frame_pts = _framing_points(scene)
    x0, _, x1, _ = legend_box((options.width, options.height), [lbl for lbl, _ in scene.legend])
    reserve = options.width - x0 + round(0.6 * _legend_font_size(options.height))
    name = options.title or str(m.metadata.get("source", m.metadata.get("name", "map")))
    counts = f"{scene.n_lines:,} lines, {scene.n_points:,} points, {len(m.keyframes):,} keyframes"
    units = units_note(m.metadata).replace("±", "+-")
    subtitle = "; ".join([counts, f"units: {units}", *scene.notes])
    paths, total = [], len(options.views) + (options.turntable_frames if options.turntable else 0)
    try:
        for i, view in enumerate(options.views):
            t1 = time.perf_counter()
            d, up = (np.asarray(v) for v in _VIEW_GEOMETRY[view])
            _set_camera(pl, *_camera_for(d, up, frame_pts, size, reserve))
            img = np.asarray(pl.screenshot(return_img=True))[..., :3]
            path = out_dir / f"{view}.png"
            _save_png(_compose(img, scene, options, f"{name}: {view} view", subtitle), path)
            paths.append(path)
            times[f"{view}_s"] = time.perf_counter() - t1
            if progress:
                progress(i + 1, total, view)
        turntable = None
        if options.turntable:
            t1 = time.perf_counter()
            turntable = _turntable(pl, scene, options, out_dir, frame_pts, name, subtitle, progress, total)
            times["turntable_s"] = time.perf_counter() - t1
    finally:
        pl.close()
    return PreviewResult(paths, list(options.views), scene.notes, backend, times, turntable)


def _check_options(o: PreviewOptions) -> None:
    bad = [v for v in o.views if v not in _VIEW_GEOMETRY]
    if bad:
        raise InputError(f"unknown preview view(s) {bad}; choose from {list(VIEWS)}")
    if o.theme not in THEMES:
        raise InputError(f"unknown theme {o.theme!r}; choose from {list(THEMES)}")
    if not (64 <= o.width <= 8192 and 64 <= o.height <= 8192):
        raise InputError(f"preview size {o.width}x{o.height} must lie within 64..8192 pixels")
    if o.turntable not in ("", "gif", "mp4"):
        raise InputError(f"turntable {o.turntable!r}: choose '', 'gif' or 'mp4'")
    if len(o.turntable_size) != 2 or min(o.turntable_size) < 64:
        raise InputError(f"turntable_size {o.turntable_size}: give (width, height), each >= 64")


def _set_camera(pl: Any, position: np.ndarray, focal: np.ndarray, up: np.ndarray, scale: float) -> None:
    pl.camera_position = [tuple(position), tuple(focal), tuple(up)]  # also marks the camera as set
    cam = pl.camera
    cam.parallel_projection = True
    cam.parallel_scale = scale
    dist = float(np.linalg.norm(np.asarray(position) - np.asarray(focal)))
    cam.clipping_range = (0.02 * dist, 3.0 * dist)  # cameras stand >= 2 depth spans off the data
    pl.render()


def _turntable(
    pl: Any,
    scene: Scene,
    options: PreviewOptions,
    out_dir: Path,
    frame_pts: np.ndarray,
    name: str,
    subtitle: str,
    progress: Callable[[int, int, str], None] | None,
    total: int,
) -> Path:
    """One turn about the vertical axis at a fixed zoom; GIF via Pillow or MP4 via OpenCV."""
    w, h = (int(v) for v in options.turntable_size)
    band = _band_height(h)
    size = (w, h - band)
    pl.window_size = list(size)
    centre = 0.5 * (frame_pts.min(axis=0) + frame_pts.max(axis=0)) if len(frame_pts) else np.zeros(3)
    radius = float(np.linalg.norm(frame_pts - centre, axis=1).max()) if len(frame_pts) else 1.0
    radius = radius or 1.0
    small = dataclasses.replace(options, width=w, height=h)
    frames = []
    base = np.asarray(_VIEW_GEOMETRY["isometric"][0])
    for k in range(options.turntable_frames):
        a = 2 * math.pi * k / options.turntable_frames
        rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        d = rot @ base
        d /= np.linalg.norm(d)
        scale = radius * 1.05 * max(1.0, size[1] / size[0])
        _set_camera(pl, centre + d * (4 * radius + 1), centre, np.array([0.0, 0.0, 1.0]), scale)
        img = np.asarray(pl.screenshot(return_img=True))[..., :3]
        frames.append(_compose(img, scene, small, f"{name}: turntable", subtitle))
        if progress:
            progress(len(options.views) + k + 1, total, f"turntable {k + 1}")
    path = out_dir / f"turntable.{options.turntable}"
    with atomic_path(path, suffix=path.suffix) as tmp_path:
        tmp = str(tmp_path)
        if options.turntable == "gif":
            from PIL import Image

            images = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
            duration = round(1000 / options.turntable_fps)
            images[0].save(
                tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0
            )
        else:
            import cv2

            vw = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), options.turntable_fps, (w, h))
            if not vw.isOpened():
                raise BackendUnavailableError(
                    f"{path}: OpenCV cannot write MP4 (mp4v) here; use turntable='gif' instead"
                )
            for f in frames:
                vw.write(np.ascontiguousarray(f[..., ::-1]))
            vw.release()
    return path
