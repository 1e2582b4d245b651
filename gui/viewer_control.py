"""The viewer's scripted-control hook: a JSON list of steps run in the open window, one after another.

Each step is an object with "do" naming it. Keys and clicks go through Qt as a user's would (`key`;
`click` at pixel x, y or at world point xyz; `click_line` by id); `call` invokes one of the window's
actions by name; `orbit` turns the camera about the vertical and times each frame; `screenshot`
grabs the window from the screen (what a user sees), `render` only the 3D view, `state` writes
`ViewerWindow.state()` as JSON; `wait` lets the event loop run; `quit` closes the window. Tests
use it under Xvfb, and `papl-map view --script FILE` exposes it to users for reproducible shots.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.errors import InputError

from .viewer_pick import clearest_spot, to_pixels

log = logging.getLogger(__name__)

#: Window actions a script may `call`, with their keyword arguments.
CALLABLE = {
    "set_keyframe": ("row",),
    "set_filters": ("min_observations", "max_rms_px", "unanchored_on"),
    "toggle_group": ("i",),
    "view_top": (),
    "view_front": (),
    "view_side": (),
    "view_isometric": (),
    "fit": (),
    "toggle_follow": (),
    "toggle_play": (),
    "pick_row": ("row",),
    "clear_pick": (),
    "save_png": ("path",),
    "save_viewpoint": ("path",),
    "restore_viewpoint": ("path",),
}
STEPS = ("key", "click", "click_line", "call", "orbit", "screenshot", "render", "state", "wait", "quit")


def load_script(path: Path) -> list[dict[str, Any]]:
    """Read and check a script; raise InputError naming the file and the first bad step."""
    try:
        steps = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the script ({exc.strerror or exc})") from exc
    except ValueError as exc:
        raise InputError(f"{path}: not JSON ({exc})") from exc
    if not isinstance(steps, list):
        raise InputError(f"{path}: a script is a JSON list of steps")
    for i, s in enumerate(steps):
        if not isinstance(s, dict) or s.get("do") not in STEPS:
            raise InputError(f"{path}: step {i} must be an object with 'do' one of {list(STEPS)}")
        if s["do"] == "call":
            method = s.get("method")
            if method not in CALLABLE:
                raise InputError(f"{path}: step {i} calls {method!r}; callable: {sorted(CALLABLE)}")
            bad = set(s.get("kwargs", {})) - set(CALLABLE[method])
            if bad:
                raise InputError(f"{path}: step {i}: {method} takes no {sorted(bad)}")
    return steps


def run_script(win: Any, path: Path) -> None:
    """Queue the script's steps on the window's event loop (the first runs once the window is up)."""
    from PySide6 import QtCore

    steps = load_script(path)
    state = {"i": 0}

    def step() -> None:
        if not win.ready:  # the first frame, the reprojection errors and the 2D panel come first
            QtCore.QTimer.singleShot(50, step)
            return
        if state["i"] >= len(steps):
            return
        s = steps[state["i"]]
        state["i"] += 1
        try:
            delay = _run_step(win, s)
        except Exception as exc:  # a failing step ends the run with its message, as a CLI error would
            log.error("script %s, step %d (%s): %s", path, state["i"] - 1, s.get("do"), exc)
            win.exit_code = 1
            win.close()
            return
        if s["do"] != "quit":
            QtCore.QTimer.singleShot(delay, step)

    QtCore.QTimer.singleShot(0, step)


def _run_step(win: Any, s: dict[str, Any]) -> int:
    """Do one step; returns the milliseconds to let the event loop run before the next."""
    from PySide6 import QtCore, QtWidgets
    from PySide6.QtTest import QTest

    do = s["do"]
    app = QtWidgets.QApplication.instance()
    if "path" in s and do in ("screenshot", "render", "state"):
        Path(s["path"]).parent.mkdir(parents=True, exist_ok=True)
    if do == "key":
        seq = _key(s["keys"])
        QTest.keyClick(win.plotter.interactor, seq[0], seq[1])  # as typed with the pointer on the 3D view
    elif do in ("click", "click_line"):
        if do == "click" and "xyz" in s:  # a world point: where it is on screen now
            px, _ = to_pixels(win.world_to_ndc(), np.asarray([s["xyz"]], np.float64), win.view_size())
            x, y = (float(v) for v in px[0])
        elif do == "click":
            x, y = float(s["x"]), float(s["y"])
        else:
            x, y = line_on_screen(win, int(s["id"]))
        mods = QtCore.Qt.KeyboardModifier.ShiftModifier if s.get("shift") else QtCore.Qt.KeyboardModifier(0)
        QTest.mouseClick(
            win.plotter.interactor, QtCore.Qt.MouseButton.LeftButton, mods, QtCore.QPoint(round(x), round(y))
        )
    elif do == "call":
        getattr(win, s["method"])(**s.get("kwargs", {}))
    elif do == "orbit":
        win.orbit(int(s.get("frames", 12)), float(s.get("degrees", 10.0)))
    elif do == "screenshot":
        app.processEvents()
        win.plotter.render()
        screen = win.screen()
        pix = screen.grabWindow(win.winId())
        if not pix.save(str(s["path"]), "PNG"):
            raise OSError(f"{s['path']}: the screenshot could not be written")
    elif do == "render":
        from PIL import Image

        Image.fromarray(win.render_3d()).save(s["path"])
    elif do == "state":
        Path(s["path"]).write_text(json.dumps(win.state(), indent=1, default=_json))
    elif do == "wait":
        return int(s.get("ms", 100))
    elif do == "quit":
        win.close()
    return int(s.get("after_ms", 50))


def line_on_screen(win: Any, line_id: int) -> tuple[float, float]:
    """Widget pixel where drawn line `line_id` stands clearest of the others (raises when not in view)."""
    rows = np.flatnonzero(win.map.lines.ids == line_id)
    drawn = win.selection.drawn
    where = np.flatnonzero(drawn == rows[0]) if len(rows) else []
    if not len(where):
        raise ValueError(f"line {line_id} is not drawn")
    spot = clearest_spot(win.world_to_ndc(), win.view_size(), win.scene.endpoints_w[drawn], int(where[0]))
    if spot is None:
        raise ValueError(f"line {line_id} is off screen")
    return spot


def _key(text: str) -> tuple[Any, Any]:
    """'Ctrl+S' -> (Qt.Key_S, Ctrl modifier)."""
    from PySide6 import QtGui

    seq = QtGui.QKeySequence(text)
    combo = seq[0]
    return combo.key(), combo.keyboardModifiers()


def _json(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)
