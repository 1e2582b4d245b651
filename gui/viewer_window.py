"""The desktop viewer's window: a pyvista/VTK 3D view in Qt, a control column and the 2D panel.

Qt (PySide6) and VTK are imported by `open_viewer` only, so the rest of papl_mapper.gui stays
importable without them. Every action a mouse can take is a method of `ViewerWindow` bound to a
keyboard shortcut as well, and `papl_mapper.gui.viewer_control` drives the same methods from a
script; the state a test checks comes from `ViewerWindow.state()`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.extras import require
from papl_mapper.map import Map
from papl_mapper.palette import hex_color

from .preview import _VIEW_GEOMETRY, THEMES, TRAJECTORY_RGB, PreviewOptions, Scene, _compose, _save_png
from .viewer_actors import frusta_segments, points_polydata, segments_polydata, trajectory_polydata
from .viewer_pick import LineFacts, line_facts, pick_point, pick_segment, to_pixels
from .viewer_scene import Filters, Selection, ViewerScene, bounds, line_rms_px
from .viewer_walk import Panel, detector_for, keyframe_panel, open_frames

log = logging.getLogger(__name__)

HIGHLIGHT_RGB = (230, 0, 120)  # picked line, the keyframes seeing it, the measurement: not in the palette
CURRENT_RGB = (20, 20, 20)  # the walkthrough's current keyframe frustum


@dataclass
class ViewerOptions:
    """How the viewer opens. Every field has a default; `papl-map view` sets them from flags."""

    max_lines: int = 1_000_000
    """More lines than this pass the filters: a seeded subset is drawn and the window says so."""
    max_points: int = 1_000_000
    """More points than this: a seeded subset is drawn."""
    width: int = 1600
    """Window width in pixels."""
    height: int = 1000
    """Window height in pixels."""
    line_width: float = 2.0
    """Line width in pixels."""
    point_size: float = 3.0
    """Point size in pixels."""
    palette: str = "okabe-ito"
    """Axis palette (papl_mapper.palette.PALETTES)."""
    play_fps: float = 4.0
    """Keyframes per second while the walkthrough plays."""
    detect_segments: bool = True
    """Detect segments in the 2D panel's frame (the run's own detector settings)."""
    multi_samples: int = 8
    """Antialiasing samples per pixel; 1 turns it off (the CLI does on a software renderer)."""
    recording: str = ""
    """The recording, when it is no longer where the map says (empty: the map's source_path)."""
    renderer: str = ""
    """The OpenGL renderer's name as the display probe found it (shown in the status line)."""


SHORTCUTS: tuple[tuple[str, str, str], ...] = (
    # (key sequence, method name, what it does) -- the README's table is made from this
    ("1", "toggle_axis_1", "toggle axis 1 (2..9 likewise)"),
    ("U", "toggle_unanchored", "toggle unanchored lines"),
    ("P", "toggle_points", "toggle points"),
    ("+", "grow_points", "bigger points"),
    ("-", "shrink_points", "smaller points"),
    ("J", "toggle_trajectory", "toggle the trajectory"),
    ("K", "toggle_frusta", "toggle keyframe frusta"),
    ("T", "view_top", "top view"),
    ("F", "view_front", "front view"),
    ("S", "view_side", "side view"),
    ("I", "view_isometric", "isometric view"),
    ("R", "fit", "fit the map in the view"),
    ("Space", "toggle_play", "play / pause the walkthrough"),
    ("Right", "next_keyframe", "next keyframe"),
    ("Left", "previous_keyframe", "previous keyframe"),
    ("C", "toggle_follow", "3D camera follows the walk"),
    ("]", "more_min_obs", "minimum observations + 1"),
    ("[", "less_min_obs", "minimum observations - 1"),
    ("Esc", "clear_pick", "clear the picked line and the measurement"),
    ("Ctrl+S", "save_png", "save the view as a PNG in the previews' style"),
    ("Ctrl+Shift+S", "save_viewpoint", "save the viewpoint"),
    ("Ctrl+O", "restore_viewpoint", "restore the saved viewpoint"),
    ("Ctrl+Q", "close", "quit"),
)


def import_window_libraries() -> None:
    """Import Qt, pyvista and pyvistaqt without touching the display (the CLI overlaps this with its
    probe of the display in a child process)."""
    for module in ("PySide6.QtWidgets", "pyvista", "pyvistaqt"):  # Qt first: pyvistaqt needs it
        require(module, "papl-map view")


def frustum_depth(m: Map, diag: float) -> float:
    """Depth of the drawn keyframe frusta: a few of the walk's typical steps between keyframes
    (so they stay small against the map), at most a fiftieth of the map's diagonal."""
    c = m.keyframes.T_wc[:, :3, 3]
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    steps = steps[steps > 0]
    typical = 4 * float(np.median(steps)) if len(steps) else diag
    return min(typical, 0.02 * diag) or 0.02 * diag


def open_viewer(
    m: Map,
    source: Path,
    options: ViewerOptions,
    script: Path | None = None,
    keyframe: int = 0,
    started: float | None = None,
) -> int:
    """Open the window on `m` (read from `source`, a run folder or map file) and run until it closes.

    `started` (a perf_counter time) is when the command began: the window reports its first frame
    relative to it."""
    from PySide6 import QtWidgets

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["papl-map view"])
    win = build_window(m, source, options, keyframe, started)
    win.show()
    if script is not None:
        from .viewer_control import run_script

        run_script(win, script)
    app.exec()
    return win.exit_code


def build_window(
    m: Map, source: Path, options: ViewerOptions, keyframe: int = 0, started: float | None = None
) -> Any:
    """The ViewerWindow (a QMainWindow) for `m`; the Qt classes are defined here, when Qt is imported."""
    return _window_class()(m, source, options, keyframe, started)


def _window_class() -> type:
    from PySide6 import QtCore, QtGui, QtWidgets
    from pyvistaqt import QtInteractor

    class ClickFilter(QtCore.QObject):
        """Left clicks (press and release in place) on the 3D view become picks; drags stay orbits."""

        def __init__(self, window: Any):
            super().__init__(window)
            self.window, self.press = window, None

        def eventFilter(self, obj: Any, ev: Any) -> bool:  # noqa: N802 (Qt's name)
            t = ev.type()
            if t == QtCore.QEvent.Type.KeyPress:
                return self.window.handle_key(ev)  # before VTK's own keys (w, s, e, q, 3 ...)
            if t == QtCore.QEvent.Type.MouseButtonPress and ev.button() == QtCore.Qt.MouseButton.LeftButton:
                self.press = ev.position()
            elif t == QtCore.QEvent.Type.MouseButtonRelease and self.press is not None:
                p, start = ev.position(), self.press
                self.press = None
                moved = abs(p.x() - start.x()) + abs(p.y() - start.y())
                if ev.button() == QtCore.Qt.MouseButton.LeftButton and moved < 5:
                    shift = bool(ev.modifiers() & QtCore.Qt.KeyboardModifier.ShiftModifier)
                    self.window.click(p.x(), p.y(), measure=shift)
            return False

    class ViewerWindow(QtWidgets.QMainWindow):
        def __init__(
            self, m: Map, source: Path, options: ViewerOptions, keyframe: int, started: float | None
        ):
            super().__init__()
            t0 = time.perf_counter()
            self.started = t0 if started is None else started
            self.map, self.source, self.options = m, source, options
            self.run_dir = source if source.is_dir() else None
            self.exit_code = 0
            self.scene = ViewerScene.from_map(m, options.palette)
            self.filters: Filters = self.scene.default_filters()
            self.selection: Selection | None = None
            self.units = str(m.metadata.get("units", "arbitrary"))
            self.show_points, self.show_trajectory, self.show_frusta = True, True, False
            self.point_size = options.point_size
            self.follow, self.playing = False, False
            self.kf_row = int(keyframe)
            self.picked: LineFacts | None = None
            self.measure: list[np.ndarray] = []
            self.measured: float | None = None
            self.panel: Panel | None = None
            self.frames, self.why_no_frames = None, ""
            self.detector = None
            self.timings: dict[str, float] = {"scene_s": time.perf_counter() - t0}
            self._ready = False  # no frame is drawn while the window is being built
            self.ready = False  # True once the first frame, the 2D panel and the RMS are up
            lo, hi = bounds(m)
            self.lo, self.hi = lo, hi
            self.diag = float(np.linalg.norm(hi - lo)) or 1.0
            self.frustum_depth = frustum_depth(m, self.diag)
            self.setWindowTitle(f"papl-map view: {source}")
            self.resize(options.width, options.height)
            self._build_ui(QtCore, QtGui, QtWidgets, QtInteractor)
            self._draw_static()
            self.refresh_lines()
            self.view_isometric()
            self.timings["window_s"] = time.perf_counter() - t0
            self._ready = True  # from here on every change renders; the first paint is the first frame
            self.plotter.ren_win.AddObserver("EndEvent", self._frame_done)
            self._play_timer = QtCore.QTimer(self)
            self._play_timer.timeout.connect(self._play_step)
            QtCore.QTimer.singleShot(0, self._after_first_frame)

        # ---- building -----------------------------------------------------------------------

        def _build_ui(self, QtCore: Any, QtGui: Any, QtWidgets: Any, QtInteractor: Any) -> None:  # noqa: N803
            self.QtGui, self.QtCore = QtGui, QtCore
            central = QtWidgets.QWidget(self)
            row = QtWidgets.QHBoxLayout(central)
            row.setContentsMargins(4, 4, 4, 4)
            self.plotter = QtInteractor(central, auto_update=False, multi_samples=self.options.multi_samples)
            self.plotter.set_background([c / 255 for c in THEMES["white"]["background"]])
            self.plotter.enable_trackball_style()
            row.addWidget(self.plotter.interactor, stretch=3)
            self._clicks = ClickFilter(self)
            self.plotter.interactor.installEventFilter(self._clicks)
            side = QtWidgets.QWidget(central)
            side.setFixedWidth(max(420, self.options.width // 3))
            col = QtWidgets.QVBoxLayout(side)
            col.setContentsMargins(4, 0, 4, 0)
            row.addWidget(side)
            self.setCentralWidget(central)

            legend = QtWidgets.QGroupBox("Lines by axis (click to toggle)")
            lg = QtWidgets.QVBoxLayout(legend)
            self.axis_boxes = []
            for i, (label, rgb) in enumerate(zip(self.scene.axis_labels, self.scene.axis_rgb, strict=True)):
                box = QtWidgets.QCheckBox(label)
                box.setChecked(True)
                box.setIcon(self._swatch(rgb))
                box.toggled.connect(lambda on, i=i: self._set_group(i, on))
                lg.addWidget(box)
                self.axis_boxes.append(box)
            col.addWidget(legend)

            filt = QtWidgets.QGroupBox("Filters")
            fl = QtWidgets.QFormLayout(filt)
            self.min_obs_box = QtWidgets.QSpinBox()
            self.min_obs_box.setRange(0, max(1, int(self.scene.n_obs.max(initial=0))))
            self.min_obs_box.valueChanged.connect(lambda v: self.set_filters(min_observations=int(v)))
            fl.addRow("minimum observations", self.min_obs_box)
            self.rms_box = QtWidgets.QDoubleSpinBox()
            self.rms_box.setRange(0.0, 1000.0)
            self.rms_box.setDecimals(1)
            self.rms_box.setSpecialValueText("off")
            self.rms_box.setValue(0.0)
            self.rms_box.setEnabled(False)
            self.rms_box.setToolTip("hide lines whose reprojection RMS exceeds this; 0 = off")
            self.rms_box.valueChanged.connect(
                lambda v: self.set_filters(max_rms_px=float(v) if v > 0 else math.inf)
            )
            fl.addRow("max reprojection RMS (px)", self.rms_box)
            self.points_box = QtWidgets.QCheckBox("points")
            self.points_box.setChecked(True)
            self.points_box.toggled.connect(lambda on: self._set_flag("show_points", on))
            self.size_box = QtWidgets.QDoubleSpinBox()
            self.size_box.setRange(1.0, 20.0)
            self.size_box.setValue(self.point_size)
            self.size_box.valueChanged.connect(self._set_point_size)
            fl.addRow(self.points_box, self.size_box)
            self.traj_box = QtWidgets.QCheckBox("trajectory")
            self.traj_box.setChecked(True)
            self.traj_box.toggled.connect(lambda on: self._set_flag("show_trajectory", on))
            self.frusta_box = QtWidgets.QCheckBox("keyframe frusta")
            self.frusta_box.toggled.connect(lambda on: self._set_flag("show_frusta", on))
            fl.addRow(self.traj_box, self.frusta_box)
            views = QtWidgets.QHBoxLayout()
            for name in ("top", "front", "side", "isometric", "fit"):
                b = QtWidgets.QPushButton(name)
                b.clicked.connect(getattr(self, "fit" if name == "fit" else f"view_{name}"))
                views.addWidget(b)
            fl.addRow(views)
            col.addWidget(filt)

            walk = QtWidgets.QGroupBox("Walkthrough")
            wl = QtWidgets.QVBoxLayout(walk)
            bar = QtWidgets.QHBoxLayout()
            self.play_button = QtWidgets.QPushButton("play")
            self.play_button.clicked.connect(self.toggle_play)
            self.follow_box = QtWidgets.QCheckBox("camera follows")
            self.follow_box.toggled.connect(self._set_follow)
            self.slider = QtWidgets.QSlider(QtCore.Qt.Orientation.Horizontal)
            self.slider.setRange(0, max(0, len(self.map.keyframes) - 1))
            self.slider.setValue(self.kf_row)
            self.slider.valueChanged.connect(self.set_keyframe)
            bar.addWidget(self.play_button)
            bar.addWidget(self.slider, stretch=1)
            bar.addWidget(self.follow_box)
            wl.addLayout(bar)
            self.image_label = QtWidgets.QLabel()
            self.image_label.setMinimumHeight(200)
            self.image_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            self.caption = QtWidgets.QLabel()
            self.caption.setWordWrap(True)
            wl.addWidget(self.image_label, stretch=1)
            wl.addWidget(self.caption)
            col.addWidget(walk, stretch=1)

            self.pick_label = QtWidgets.QLabel(
                "click a line to see its facts; shift+click two points to measure"
            )
            self.pick_label.setWordWrap(True)
            col.addWidget(self.pick_label)
            self.status = QtWidgets.QLabel()
            self.status.setWordWrap(True)
            col.addWidget(self.status)
            seq = QtGui.QKeySequence
            self.keys = {seq(keys).toString(): getattr(self, method) for keys, method, _ in SHORTCUTS}
            for k in range(2, min(self.scene.n_axes, 9) + 1):
                self.keys[str(k)] = lambda k=k: self.toggle_group(k - 1)

        def handle_key(self, ev: Any) -> bool:
            """Run the action bound to a key press; False (not handled) for other keys."""
            name = self.QtGui.QKeySequence(ev.keyCombination()).toString()
            fn = self.keys.get(name) or self.keys.get(
                name.removeprefix("Shift+")
            )  # "+" is Shift+= on US keys
            if fn is None:
                return False
            fn()
            return True

        def keyPressEvent(self, ev: Any) -> None:  # noqa: N802 (Qt's name): keys no child widget took
            if not self.handle_key(ev):
                super().keyPressEvent(ev)

        def _swatch(self, rgb: tuple[int, int, int]) -> Any:
            pix = self.QtGui.QPixmap(14, 14)
            pix.fill(self.QtGui.QColor(hex_color(rgb)))
            return self.QtGui.QIcon(pix)

        def _draw_static(self) -> None:
            """Points, trajectory and frusta: drawn once, shown or hidden by the toggles."""
            m, pl = self.map, self.plotter
            self.points_actor = self.traj_actor = self.frusta_actor = None
            xyz, rgb = m.points.xyz, m.points.color
            if len(xyz) > self.options.max_points:
                keep = np.sort(
                    np.random.default_rng(0).choice(len(xyz), self.options.max_points, replace=False)
                )
                xyz, rgb = xyz[keep], rgb[keep]
            self.points_drawn = xyz
            if len(xyz):
                bg = np.asarray(THEMES["white"]["background"], np.float64)
                faded = (0.55 * rgb + 0.45 * bg).astype(np.uint8)
                self.points_actor = self._overlay(
                    points_polydata(xyz, faded),
                    scalars="rgb",
                    rgb=True,
                    point_size=self.point_size,
                    style="points",
                    name="points",
                )
            traj = trajectory_polydata(m)
            tcol = [c / 255 for c in TRAJECTORY_RGB]
            if traj is not None:
                self.traj_actor = pl.add_mesh(
                    traj, color=tcol, line_width=3, lighting=False, name="trajectory", render=False
                )

        # ---- lines and filters --------------------------------------------------------------

        def _frame_done(self, *_: Any) -> None:
            if "first_frame_s" not in self.timings:
                self.timings["first_frame_s"] = time.perf_counter() - self.started
                self.timings["first_frame_unix"] = time.time()

        def _overlay(self, mesh: Any, name: str, **style: Any) -> Any:
            """Add (or replace) the named unlit actor without moving the camera or rendering."""
            return self.plotter.add_mesh(
                mesh, name=name, lighting=False, reset_camera=False, render=False, **style
            )

        def _render(self) -> None:
            if self._ready:
                self.plotter.render()

        def refresh_lines(self) -> None:
            """Redraw the lines passing the filters (decimated beyond max_lines) and update the legend."""
            t0 = time.perf_counter()
            sel = self.scene.selection(self.filters, self.options.max_lines)
            self.selection = sel
            t1 = time.perf_counter()
            self.plotter.remove_actor("lines", render=False)
            if len(sel.drawn):
                poly = segments_polydata(self.scene.endpoints_w[sel.drawn], self.scene.line_rgb[sel.drawn])
                self._overlay(
                    poly,
                    scalars="rgb",
                    rgb=True,
                    line_width=self.options.line_width,
                    name="lines",
                )
            self.timings["select_s"] = t1 - t0
            self.timings["lines_polydata_s"] = time.perf_counter() - t1
            for box, label, n in zip(self.axis_boxes, self.scene.axis_labels, sel.counts, strict=True):
                box.setText(f"{label}  ({n:,})")
            self._update_status()
            self._render()

        def set_filters(self, **changes: Any) -> None:
            """Change filter fields (min_observations, max_rms_px, unanchored_on) and redraw at once."""
            for k, v in changes.items():
                setattr(self.filters, k, v)
            if "min_observations" in changes and self.min_obs_box.value() != int(changes["min_observations"]):
                self.min_obs_box.blockSignals(True)
                self.min_obs_box.setValue(int(changes["min_observations"]))
                self.min_obs_box.blockSignals(False)
            self.refresh_lines()

        def _set_group(self, i: int, on: bool) -> None:
            if i < self.scene.n_axes:
                self.filters.axes_on[i] = on
            else:
                self.filters.unanchored_on = on
            self.refresh_lines()

        def toggle_group(self, i: int) -> None:
            """Toggle axis `i` (0-based), or unanchored lines for i == number of axes."""
            if 0 <= i < len(self.axis_boxes):
                self.axis_boxes[i].toggle()

        def toggle_axis_1(self) -> None:
            self.toggle_group(0)

        def toggle_unanchored(self) -> None:
            self.toggle_group(self.scene.n_axes)

        def more_min_obs(self) -> None:
            self.min_obs_box.setValue(self.min_obs_box.value() + 1)

        def less_min_obs(self) -> None:
            self.min_obs_box.setValue(max(0, self.min_obs_box.value() - 1))

        def _after_first_frame(self) -> None:
            """Once the first frame is up: the reprojection RMS (for its filter) and the 2D panel."""
            if "first_frame_s" not in self.timings:  # no paint yet: draw the first frame now
                self.plotter.ren_win.Render()
            # the RMS of a million lines takes seconds: a worker thread (numpy releases the GIL)
            # computes it while the window answers; its filter is enabled when it is done
            self._rms_started = time.perf_counter()
            self._rms_pool = ThreadPoolExecutor(1, thread_name_prefix="line-rms")
            self._rms_job = self._rms_pool.submit(line_rms_px, self.map)
            self.QtCore.QTimer.singleShot(50, self._rms_done)
            given = Path(self.options.recording) if self.options.recording else None
            self.frames, self.why_no_frames = open_frames(self.map, self.run_dir, given)
            if self.frames is not None and self.options.detect_segments:
                self.detector = detector_for(self.run_dir)
            if len(self.map.keyframes):
                self.set_keyframe(self.slider.value(), force=True)
            else:
                self.caption.setText("this map has no keyframes: nothing to play")
            self._update_status()

        def _rms_done(self) -> None:
            """Poll the RMS worker; when it is done, enable its filter and mark the window ready."""
            if not self._rms_job.done():
                self.QtCore.QTimer.singleShot(50, self._rms_done)
                return
            self.scene.rms_px = self._rms_job.result()
            self._rms_pool.shutdown()
            self.timings["rms_s"] = time.perf_counter() - self._rms_started
            self.rms_box.setEnabled(bool(np.isfinite(self.scene.rms_px).any()))
            self._update_status()
            self.ready = True

        # ---- toggles --------------------------------------------------------------------------

        def _frusta_actor(self) -> Any:
            """Keyframe frusta (at most 200, every k-th), made the first time they are shown."""
            m = self.map
            if self.frusta_actor is None and len(m.keyframes):
                rows = np.arange(0, len(m.keyframes), max(1, math.ceil(len(m.keyframes) / 200)))
                self.frusta_actor = self._overlay(
                    segments_polydata(frusta_segments(m, self.frustum_depth, rows)),
                    color=[c / 255 for c in TRAJECTORY_RGB],
                    line_width=1,
                    name="frusta",
                )
            return self.frusta_actor

        def _set_flag(self, name: str, on: bool) -> None:
            setattr(self, name, on)
            actor = {"show_points": self.points_actor, "show_trajectory": self.traj_actor}.get(name)
            if name == "show_frusta":
                actor = self._frusta_actor()
            if actor is not None:
                actor.SetVisibility(bool(on))
            self._render()

        def toggle_points(self) -> None:
            self.points_box.toggle()

        def toggle_trajectory(self) -> None:
            self.traj_box.toggle()

        def toggle_frusta(self) -> None:
            self.frusta_box.toggle()

        def _set_point_size(self, v: float) -> None:
            self.point_size = float(v)
            if self.points_actor is not None:
                self.points_actor.GetProperty().SetPointSize(self.point_size)
                self._render()

        def grow_points(self) -> None:
            self.size_box.setValue(self.size_box.value() + 1)

        def shrink_points(self) -> None:
            self.size_box.setValue(self.size_box.value() - 1)

        # ---- camera ---------------------------------------------------------------------------

        def _view(self, name: str) -> None:
            d, up = (np.asarray(v, np.float64) for v in _VIEW_GEOMETRY[name])
            d /= np.linalg.norm(d)
            centre = 0.5 * (self.lo + self.hi)
            cam = self.plotter.camera
            cam.SetParallelProjection(False)
            cam.SetViewAngle(30.0)
            dist = 0.5 * self.diag / math.tan(math.radians(15.0)) * 1.05
            self.plotter.camera_position = [tuple(centre + d * dist), tuple(centre), tuple(up)]
            self.plotter.renderer.ResetCameraClippingRange()
            self._render()

        def view_top(self) -> None:
            self._view("top")

        def view_front(self) -> None:
            self._view("front")

        def view_side(self) -> None:
            self._view("side")

        def view_isometric(self) -> None:
            self._view("isometric")

        def fit(self) -> None:
            """Keep the viewing direction, frame the whole map."""
            cam = self.plotter.camera
            d = np.asarray(cam.GetPosition()) - np.asarray(cam.GetFocalPoint())
            d = d / (np.linalg.norm(d) or 1.0)
            centre = 0.5 * (self.lo + self.hi)
            dist = 0.5 * self.diag / math.tan(math.radians(0.5 * cam.GetViewAngle())) * 1.05
            self.plotter.camera_position = [tuple(centre + d * dist), tuple(centre), tuple(cam.GetViewUp())]
            self.plotter.renderer.ResetCameraClippingRange()
            self._render()

        def orbit(self, frames: int, degrees: float) -> list[float]:
            """Turn the camera `frames` times by `degrees` about the vertical through its focal point,
            rendering each; the seconds per frame go into the timings as orbit_frame_s."""
            times = []
            for _ in range(frames):
                self.plotter.camera.Azimuth(degrees)  # about the view-up, which is +Z in the preset views
                self.plotter.renderer.ResetCameraClippingRange()
                t0 = time.perf_counter()
                self.plotter.ren_win.Render()
                times.append(time.perf_counter() - t0)
            self.timings["orbit_frame_s"] = times
            return times

        def viewpoint(self) -> dict[str, Any]:
            cam = self.plotter.camera
            return {
                "position": list(cam.GetPosition()),
                "focal_point": list(cam.GetFocalPoint()),
                "view_up": list(cam.GetViewUp()),
                "view_angle": float(cam.GetViewAngle()),
            }

        def set_viewpoint(self, vp: dict[str, Any]) -> None:
            cam = self.plotter.camera
            self.plotter.camera_position = [
                tuple(vp["position"]),
                tuple(vp["focal_point"]),
                tuple(vp["view_up"]),
            ]
            cam.SetViewAngle(float(vp.get("view_angle", 30.0)))
            self.plotter.renderer.ResetCameraClippingRange()
            self._render()

        def _default_path(self, suffix: str) -> Path:
            base = self.source if self.source.is_dir() else self.source.parent
            stem = "view" if self.source.is_dir() else self.source.stem
            return base / f"{stem}{suffix}"

        def save_viewpoint(self, path: Path | None = None) -> Path:
            path = Path(path) if path else self._default_path(".viewpoint.json")
            with atomic_path(path, suffix=".json") as tmp:
                Path(tmp).write_text(json.dumps(self.viewpoint(), indent=1))
            self.status_note = f"viewpoint saved to {path}"
            self._update_status()
            return path

        def restore_viewpoint(self, path: Path | None = None) -> None:
            path = Path(path) if path else self._default_path(".viewpoint.json")
            try:
                self.set_viewpoint(json.loads(path.read_text()))
                self.status_note = f"viewpoint restored from {path}"
            except (OSError, ValueError, KeyError, TypeError) as exc:
                self.status_note = f"{path}: no viewpoint restored ({exc})"
            self._update_status()

        # ---- walkthrough ----------------------------------------------------------------------

        def set_keyframe(self, row: int, force: bool = False) -> None:
            """Show keyframe `row`: its frustum in 3D, the camera on it when following, the 2D panel."""
            n = len(self.map.keyframes)
            if n == 0:
                return
            row = int(np.clip(row, 0, n - 1))
            if row == self.kf_row and not force:
                return
            self.kf_row = row
            if self.slider.value() != row:
                self.slider.blockSignals(True)
                self.slider.setValue(row)
                self.slider.blockSignals(False)
            seg = frusta_segments(self.map, 1.5 * self.frustum_depth, [row])
            self._overlay(
                segments_polydata(seg),
                color=[c / 255 for c in CURRENT_RGB],
                line_width=3,
                name="current",
            )
            current = self.plotter.actors.get("current")
            if current is not None:  # following, the view is the keyframe's: its frustum would frame it
                current.SetVisibility(not self.follow)
            if self.follow:
                self._follow_camera()
            t0 = time.perf_counter()
            rgb = self.scene.line_rgb
            self.panel = keyframe_panel(
                self.map, row, self.frames, self.why_no_frames, self.scene.endpoints_w, rgb, self.detector
            )
            self.timings["panel_s"] = time.perf_counter() - t0
            self._show_panel()
            self._render()

        def _follow_camera(self) -> None:
            T = self.map.keyframes.T_wc[self.kf_row]
            c, R = T[:3, 3], T[:3, :3]
            cam = self.plotter.camera
            # the keyframe's own view (as in the 2D panel), a touch wider so its surroundings show
            self.plotter.camera_position = [tuple(c), tuple(c + R[:, 2]), tuple(-R[:, 1])]
            h = self.map.camera.height
            cam.SetViewAngle(math.degrees(2 * math.atan(0.5 * h / self.map.camera.fy)) * 1.15)
            self.plotter.renderer.ResetCameraClippingRange()

        def _show_panel(self) -> None:
            p = self.panel
            assert p is not None
            img = np.ascontiguousarray(p.image)
            h, w = img.shape[:2]
            qimg = self.QtGui.QImage(img.data, w, h, 3 * w, self.QtGui.QImage.Format.Format_RGB888).copy()
            pix = self.QtGui.QPixmap.fromImage(qimg)
            target = self.image_label.width() or 400
            self.image_label.setPixmap(
                pix.scaledToWidth(target, self.QtCore.Qt.TransformationMode.SmoothTransformation)
            )
            self.caption.setText(p.caption)

        def next_keyframe(self) -> None:
            self.set_keyframe(self.kf_row + 1)

        def previous_keyframe(self) -> None:
            self.set_keyframe(self.kf_row - 1)

        def _set_follow(self, on: bool) -> None:
            self.follow = bool(on)
            current = self.plotter.actors.get("current")
            if current is not None:
                current.SetVisibility(not self.follow)
            if on and len(self.map.keyframes):
                self._follow_camera()
            self._render()

        def toggle_follow(self) -> None:
            self.follow_box.toggle()

        def toggle_play(self) -> None:
            self.playing = not self.playing
            self.play_button.setText("pause" if self.playing else "play")
            if self.playing:
                self._play_timer.start(max(1, round(1000 / self.options.play_fps)))
            else:
                self._play_timer.stop()

        def _play_step(self) -> None:
            if self.kf_row >= len(self.map.keyframes) - 1:
                self.toggle_play()
                return
            self.next_keyframe()

        # ---- picking and measuring ------------------------------------------------------------

        def world_to_ndc(self) -> np.ndarray:
            w, h = self.plotter.interactor.width(), self.plotter.interactor.height()
            mat = self.plotter.camera.GetCompositeProjectionTransformMatrix(w / max(h, 1), -1, 1)
            return np.array([[mat.GetElement(i, j) for j in range(4)] for i in range(4)])

        def view_size(self) -> tuple[int, int]:
            return self.plotter.interactor.width(), self.plotter.interactor.height()

        def click(self, x: float, y: float, measure: bool = False) -> None:
            """A click at widget pixel (x, y): pick the line under it, or with `measure` a point."""
            M, size = self.world_to_ndc(), self.view_size()
            if measure:
                cands = [self.scene.endpoints_w[self.selection.drawn].reshape(-1, 3).astype(np.float64)]
                if self.show_points and len(self.points_drawn):
                    cands.append(self.points_drawn)
                xyz = np.concatenate(cands) if cands else np.zeros((0, 3))
                k = pick_point(M, size, xyz, (x, y))
                if k is None:
                    self.pick_label.setText("no point or endpoint under the click")
                    return
                self.measure = (self.measure + [xyz[k]])[-2:]
                self._draw_measure()
                return
            drawn = self.selection.drawn if self.selection is not None else np.zeros(0, np.int64)
            k = pick_segment(M, size, self.scene.endpoints_w[drawn], (x, y))
            if k is None:
                self.clear_pick()
                self.pick_label.setText("no line under the click")
                return
            self.pick_row(int(drawn[k]))

        def pick_row(self, row: int) -> None:
            """Select line `row`: show its facts, draw it highlighted with the keyframes that see it."""
            facts = line_facts(self.map, self.scene, row)
            self.picked = facts
            self.pick_label.setText(facts.text(self.units))
            col = [c / 255 for c in HIGHLIGHT_RGB]
            self._overlay(
                segments_polydata(self.scene.endpoints_w[[row]]),
                color=col,
                line_width=3 * self.options.line_width,
                name="picked",
            )
            rows = np.flatnonzero(np.isin(self.map.keyframes.ids, facts.keyframe_ids))
            self.plotter.remove_actor("seeing", render=False)
            if len(rows):
                self._overlay(
                    segments_polydata(frusta_segments(self.map, 1.2 * self.frustum_depth, rows)),
                    color=col,
                    line_width=2,
                    name="seeing",
                )
            self._render()

        def _draw_measure(self) -> None:
            col = [c / 255 for c in HIGHLIGHT_RGB]
            pts = np.array(self.measure)
            import pyvista as pv

            self.plotter.add_mesh(
                pv.PolyData(pts),
                color=col,
                point_size=12,
                render_points_as_spheres=True,
                name="measure_pts",
                reset_camera=False,
                render=False,
            )
            if len(pts) == 2:
                self._overlay(
                    segments_polydata(pts[None]),
                    color=col,
                    line_width=3,
                    name="measure_line",
                )
                dist = float(np.linalg.norm(pts[1] - pts[0]))
                self.measured = dist
                self.pick_label.setText(f"distance {dist:.3f} {self.units}")
            else:
                self.plotter.remove_actor("measure_line", render=False)
                self.pick_label.setText("measure: shift+click a second point")
            self._render()

        def clear_pick(self) -> None:
            self.picked, self.measure, self.measured = None, [], None
            for name in ("picked", "seeing", "measure_pts", "measure_line"):
                self.plotter.remove_actor(name, render=False)
            self.pick_label.setText("")
            self._render()

        # ---- output ---------------------------------------------------------------------------

        def render_3d(self) -> np.ndarray:
            """(H, W, 3) uint8 of the 3D view as it is now."""
            return np.asarray(self.plotter.screenshot(return_img=True))[..., :3]

        def save_png(self, path: Path | None = None) -> Path:
            """The 3D view under the previews' title band with their legend (counts as filtered)."""
            path = Path(path) if path else self._default_path(".view.png")
            img = self.render_3d()
            sel = self.selection
            opts = PreviewOptions(width=img.shape[1], height=img.shape[0] + round(0.075 * img.shape[0]))
            legend = [
                (f"{label}  ({n:,})", rgb)
                for label, rgb, n, box in zip(
                    self.scene.axis_labels, self.scene.axis_rgb, sel.counts, self.axis_boxes, strict=True
                )
                if box.isChecked()
            ]
            legend.append(("trajectory", TRAJECTORY_RGB))
            notes = [sel.note] if sel.note else []
            drawn = self.scene.endpoints_w[sel.drawn]
            scene = Scene(
                drawn,
                self.scene.line_rgb[sel.drawn],
                self.points_drawn,
                np.zeros((0, 3), np.uint8),
                self.map.keyframes.T_wc[:, :3, 3],
                np.zeros((0, 5, 3)),
                legend,
                notes,
                len(self.scene),
                len(self.map.points),
            )
            band = opts.height - img.shape[0]
            opts.height = img.shape[0] + band
            name = self.source.name if self.source.is_dir() else self.source.stem
            counts = f"{len(sel.passing):,} of {len(self.scene):,} lines pass the filters"
            sub = "; ".join([counts, f"units: {self.units}", *notes])
            _save_png(_compose(img, scene, opts, f"{name}: viewer", sub), path)
            self.status_note = f"saved {path}"
            self._update_status()
            return path

        def _update_status(self) -> None:
            notes = []
            if len(self.scene) == 0:
                notes.append("no lines in this map")
            if self.selection is not None and self.selection.note:
                notes.append(self.selection.note)
            if self.scene.rms_px is None:
                notes.append("computing reprojection errors...")
            if self.options.renderer:
                aa = "antialiasing off" if self.options.multi_samples <= 1 else "antialiased"
                notes.append(f"OpenGL: {self.options.renderer} ({aa})")
            note = getattr(self, "status_note", "")
            if note:
                notes.append(note)
            self.status.setText("\n".join(notes))

        def state(self) -> dict[str, Any]:
            """What the window shows now, for tests and scripts."""
            sel = self.selection
            return {
                "lines": len(self.scene),
                "passing": int(len(sel.passing)) if sel else 0,
                "drawn": int(len(sel.drawn)) if sel else 0,
                "counts": list(sel.counts) if sel else [],
                "labels": self.scene.axis_labels,
                "colors": [list(c) for c in self.scene.axis_rgb],
                "filters": {
                    "axes_on": list(self.filters.axes_on),
                    "unanchored_on": self.filters.unanchored_on,
                    "min_observations": self.filters.min_observations,
                    "max_rms_px": None if math.isinf(self.filters.max_rms_px) else self.filters.max_rms_px,
                },
                "show_points": self.show_points,
                "show_trajectory": self.show_trajectory,
                "show_frusta": self.show_frusta,
                "point_size": self.point_size,
                "keyframe_row": self.kf_row,
                "follow": self.follow,
                "playing": self.playing,
                "viewpoint": self.viewpoint(),
                "panel": None
                if self.panel is None
                else {
                    "has_frame": self.panel.has_frame,
                    "caption": self.panel.caption,
                    "detected": self.panel.n_detected,
                    "reprojected": self.panel.n_reprojected,
                },
                "picked": None if self.picked is None else self.picked.__dict__,
                "measured": self.measured if len(self.measure) == 2 else None,
                "screen_length_px": self.screen_lengths(),
                "view_rect": self._rect(self.plotter.interactor),
                "panel_rect": self._rect(self.image_label),
                "status": self.status.text(),
                "pick_text": self.pick_label.text(),
                "timings_s": dict(self.timings),
            }

        def screen_lengths(self) -> list[float]:
            """Pixel length on screen of the drawn lines per axis, then unanchored (clipped to the view)."""
            sel = self.selection
            out = np.zeros(self.scene.n_axes + 1)
            if sel is None or not len(sel.drawn):
                return out.tolist()
            w, h = self.view_size()
            px, _ = to_pixels(self.world_to_ndc(), self.scene.endpoints_w[sel.drawn].reshape(-1, 3), (w, h))
            a, b = px[0::2], px[1::2]
            inside = np.isfinite(a).all(1) & np.isfinite(b).all(1)
            a, b = np.clip(a[inside], [0, 0], [w, h]), np.clip(b[inside], [0, 0], [w, h])
            group = self.scene.axis[sel.drawn][inside]
            group = np.where(group < 0, self.scene.n_axes, group)
            out += np.bincount(group, weights=np.linalg.norm(b - a, axis=1), minlength=len(out))
            return out.tolist()

        def _rect(self, widget: Any) -> list[int]:
            """(x, y, w, h) of a child widget in window pixels (where it is in a screenshot)."""
            p = widget.mapTo(self, self.QtCore.QPoint(0, 0))
            return [p.x(), p.y(), widget.width(), widget.height()]

        def closeEvent(self, ev: Any) -> None:  # noqa: N802 (Qt's name)
            if self.frames is not None:
                self.frames.close()
            self.plotter.close()
            super().closeEvent(ev)

    return ViewerWindow
