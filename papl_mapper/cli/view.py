"""`papl-map view RUN_DIR | MAP`: the interactive desktop viewer (3D map, walkthrough player, picking).

Needs a display and OpenGL; without them it says in one line what is missing and points to
`papl-map render` (PNG previews) and `papl-map report` (HTML), which need neither.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from papl_mapper.errors import BackendUnavailableError, InputError
from papl_mapper.map import Map

_ELSEWHERE = "use `papl-map render MAP --out DIR` (PNG previews) or `papl-map report RUN_DIR` (HTML) instead"
#: Run in a child process: a missing X server, Qt platform plugin or OpenGL aborts a process, not raises.
_PROBE = (
    "from PySide6.QtWidgets import QApplication\n"
    "app = QApplication(['probe'])\n"
    "import vtkmodules.vtkRenderingOpenGL2, vtkmodules.vtkRenderingCore as rc\n"
    "w = rc.vtkRenderWindow(); w.SetOffScreenRendering(1); w.SetSize(8, 8); w.Render()\n"
    "gl = [l.split(':', 1)[1].strip() for l in w.ReportCapabilities().splitlines()\n"
    "      if l.startswith('OpenGL renderer string')]\n"
    "print('PAPL_PROBE', w.GetClassName(), int(w.SupportsOpenGL()), *(gl or ['unknown']))\n"
)
#: OpenGL renderers that draw on the CPU: multisampling multiplies their frame time, so it is off.
SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view", help="open the interactive desktop viewer on a run or map", description=__doc__
    )
    p.add_argument("source", help="a run folder (map.papl beside the run's summary) or a .papl map file")
    p.add_argument("--keyframe", type=int, default=0, help="keyframe row to open the walkthrough at")
    p.add_argument("--max-lines", type=int, help="draw at most this many lines (default 1,000,000)")
    p.add_argument("--size", help="window WIDTHxHEIGHT in pixels, default 1600x1000")
    p.add_argument(
        "--recording", type=Path, help="the recording, if it moved (default: the map's source_path)"
    )
    p.add_argument("--no-detect", action="store_true", help="do not detect segments in the 2D panel")
    p.add_argument("--script", type=Path, help="JSON list of steps to run in the window (see viewer_control)")
    p.set_defaults(func=run)


def check_display(env: dict[str, str] | None = None) -> None:
    """Raise BackendUnavailableError (what is missing, what to use instead) unless a window can open."""
    env = dict(os.environ if env is None else env)
    if not env.get("DISPLAY") and not env.get("WAYLAND_DISPLAY"):
        raise BackendUnavailableError(
            f"no display (DISPLAY is not set): the viewer needs a screen; {_ELSEWHERE}"
        )
    try:
        import PySide6  # noqa: F401
        import pyvistaqt  # noqa: F401
    except ImportError as exc:
        raise BackendUnavailableError(
            f"the viewer needs Qt ({exc.name} is not installed): pip install 'papl-mapper[viewer]', "
            f"or {_ELSEWHERE}"
        ) from exc


def start_probe(env: dict[str, str] | None = None) -> subprocess.Popen:
    """Start the window probe in a child process (it runs while the map loads)."""
    env = dict(os.environ if env is None else env)
    env.setdefault("QT_LOGGING_RULES", "*.debug=false")
    return subprocess.Popen(
        [sys.executable, "-c", _PROBE], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def finish_probe(proc: subprocess.Popen, env: dict[str, str] | None = None) -> str:
    """Wait for the probe and return the OpenGL renderer's name; raise BackendUnavailableError naming
    the display and the fault when no window can open."""
    display = (env or os.environ).get("DISPLAY") or (env or os.environ).get("WAYLAND_DISPLAY")
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise BackendUnavailableError(f"opening a window on display {display} hangs; {_ELSEWHERE}") from None
    words = out.split()
    if proc.returncode == 0 and len(words) >= 3 and words[0] == "PAPL_PROBE" and words[2] == "1":
        return " ".join(words[3:])
    lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
    hint = next((ln for ln in lines if "could not connect" in ln or "Could not load" in ln), None)
    tail = hint or (lines[-1] if lines else f"exit code {proc.returncode}")
    if words[:1] == ["PAPL_PROBE"]:
        tail = f"{words[1]} has no usable OpenGL"
    if "could not connect" in tail:
        raise BackendUnavailableError(f"no X server answers on display {display}; {_ELSEWHERE}")
    raise BackendUnavailableError(
        f"cannot open an OpenGL window on display {display} ({tail[-200:]}); install the set-up's "
        f"system packages (scripts/setup.sh: Qt's xcb libraries, libgl1), or {_ELSEWHERE}"
    )


def _map_path(src: Path) -> Path:
    if src.is_dir():
        path = src / "map.papl"
        if not path.exists():
            raise InputError(f"{src}: no map.papl in this folder (give a run folder or a .papl file)")
        return path
    return src


def _size(text: str | None) -> tuple[int, int]:
    if not text:
        return 1600, 1000
    w, _, h = text.lower().partition("x")
    try:
        size = int(w), int(h)
    except ValueError:
        raise InputError(f"--size {text!r}: give WIDTHxHEIGHT, e.g. 1600x1000") from None
    if not (320 <= size[0] <= 8192 and 240 <= size[1] <= 8192):
        raise InputError(f"--size {text!r}: width 320..8192 and height 240..8192 pixels")
    return size


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    check_display()
    src = Path(args.source)
    width, height = _size(args.size)
    if args.max_lines is not None and args.max_lines < 1:
        raise InputError(f"--max-lines {args.max_lines}: give a positive number of lines")
    if args.script is not None:
        from papl_mapper.gui.viewer_control import load_script

        load_script(args.script)  # a bad script is refused before any window opens
    path = _map_path(src)
    if args.recording is not None and not args.recording.exists():
        raise InputError(f"--recording {args.recording}: no such file or folder")
    # three things at once: the probe (a child), the map load (a thread: reading and numpy release
    # the GIL) and the window's imports (here); importing is safe without a display, opening is not
    probe = start_probe()
    pool = ThreadPoolExecutor(1, thread_name_prefix="map-load")
    try:
        loading = pool.submit(Map.load, path)
        os.environ.setdefault("QT_LOGGING_RULES", "*.debug=false")
        from papl_mapper.gui.viewer_window import ViewerOptions, import_window_libraries, open_viewer

        import_window_libraries()
        m = loading.result()
        if len(m.keyframes) and not 0 <= args.keyframe < len(m.keyframes):
            raise InputError(f"--keyframe {args.keyframe}: the map has keyframes 0..{len(m.keyframes) - 1}")
    except BaseException:
        probe.kill()
        raise
    finally:
        pool.shutdown(wait=True)
    renderer = finish_probe(probe)

    software = any(name in renderer.lower() for name in SOFTWARE_GL)
    options = ViewerOptions(
        width=width,
        height=height,
        detect_segments=not args.no_detect,
        multi_samples=1 if software else 8,
        renderer=renderer,
        recording=str(args.recording or ""),
    )
    if args.max_lines is not None:
        options.max_lines = args.max_lines
    return open_viewer(m, src, options, args.script, keyframe=args.keyframe, started=t0)
