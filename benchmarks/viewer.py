"""Benchmark: the desktop viewer at 100,000 and 1,000,000 segments, and the renderer it was chosen over.

Three measurements, each in a fresh process on a building map (benchmarks/render.py's, with three
line observations per segment):
- data path (no rendering): Map.load, ViewerScene.from_map, a filter change, the PolyData of every
  drawn segment, the reprojection RMS of every line;
- `papl-map view` itself (pyvista/VTK in a Qt window, on the X display): time from launching the
  process to the first frame, frame times while orbiting, peak RSS of the process;
- Open3D 0.20's GUI (Filament on Vulkan) on the same segments: first frame and orbit frames through
  `render_to_image`, peak RSS; a run that does not finish within --o3d-timeout is recorded as such.
Needs a display: run under Xvfb (`xvfb-run -s "-screen 0 1920x1080x24" ...`) or starts one itself.
Prints a table and writes benchmarks/results/viewer.json.
Usage: .venv/bin/python benchmarks/viewer.py [--sizes 100000,1000000] [--frames 6] [--o3d-timeout 240]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import git_commit, machine_info
from render import building_map

ROOT = Path(__file__).resolve().parents[1]
GOAL_FIRST_FRAME_S = 3.0


def observed_map(n_segments: int, n_obs: int = 3, seed: int = 0):
    """The render benchmark's building with `n_obs` observations per segment (random keyframes)."""
    import dataclasses

    m = building_map(n_segments, seed)
    rng = np.random.default_rng(seed)
    ids = np.repeat(m.lines.ids, n_obs)
    kf = rng.integers(0, len(m.keyframes), len(ids))
    xy = rng.uniform(0, 700, (len(ids), 4))
    return dataclasses.replace(
        m, lines=dataclasses.replace(m.lines, obs_ids=np.stack([ids, kf], 1), obs_xy=xy)
    )


# ---- children ---------------------------------------------------------------------------------------


def _child_data(map_path: str) -> dict:
    import resource

    from papl_mapper.gui.viewer_actors import segments_polydata
    from papl_mapper.gui.viewer_scene import ViewerScene
    from papl_mapper.map import Map

    segments_polydata(np.zeros((1, 2, 3)))  # pyvista's import is not the data path
    out = {}
    t = time.perf_counter()
    m = Map.load(map_path)
    out["load_s"] = time.perf_counter() - t
    t = time.perf_counter()
    scene = ViewerScene.from_map(m)
    out["scene_s"] = time.perf_counter() - t
    f = scene.default_filters()
    t = time.perf_counter()
    sel = scene.selection(f, 10**7)
    out["select_all_s"] = time.perf_counter() - t
    f.axes_on[0] = False
    f.min_observations = 2
    t = time.perf_counter()
    scene.selection(f, 10**7)
    out["select_filtered_s"] = time.perf_counter() - t
    t = time.perf_counter()
    segments_polydata(scene.endpoints_w[sel.drawn], scene.line_rgb[sel.drawn])
    out["polydata_s"] = time.perf_counter() - t
    t = time.perf_counter()
    scene.compute_rms(m)
    out["rms_s"] = time.perf_counter() - t
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


_O3D_CHILD = r"""
import json, resource, sys, threading, time
import numpy as np
t0 = time.time()
import open3d as o3d
import open3d.visualization.gui as gui
import open3d.visualization.rendering as rendering
from papl_mapper.gui.viewer_scene import ViewerScene, bounds
from papl_mapper.map import Map
map_path, frames, out_path = sys.argv[1], int(sys.argv[2]), sys.argv[3]
m = Map.load(map_path)
scene = ViewerScene.from_map(m)
sel = scene.selection(scene.default_filters(), 10**7)
app = gui.Application.instance
app.initialize()
w = app.create_window("open3d", 1200, 1000)
sw = gui.SceneWidget()
sw.scene = rendering.Open3DScene(w.renderer)
w.add_child(sw)
w.set_on_layout(lambda ctx: setattr(sw, "frame", w.content_rect))
e = scene.endpoints_w[sel.drawn].reshape(-1, 3).astype(np.float64)
k = len(sel.drawn)
ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(e),
                          o3d.utility.Vector2iVector(np.arange(2 * k, dtype=np.int32).reshape(-1, 2)))
ls.colors = o3d.utility.Vector3dVector(scene.line_rgb[sel.drawn] / 255.0)
mat = rendering.MaterialRecord(); mat.shader = "unlitLine"; mat.line_width = 2.0
sw.scene.add_geometry("lines", ls, mat)
lo, hi = bounds(m)
centre = 0.5 * (lo + hi); r = float(np.linalg.norm(hi - lo))
res = {}
def worker():
    ev = threading.Event()
    def shot():
        sw.look_at(centre, centre + np.array([r, -r, 0.8 * r]), np.array([0, 0, 1.0]))
        sw.scene.scene.render_to_image(lambda im: ev.set())
    app.post_to_main_thread(w, shot); ev.wait()
    res["first_frame_unix"] = time.time()
    times = []
    for i in range(frames):
        ev.clear()
        def step(i=i):
            a = 0.2 * (i + 1)
            d = np.array([np.cos(a) - np.sin(a), np.sin(a) + np.cos(a), 0.8])
            sw.look_at(centre, centre + d * r, np.array([0, 0, 1.0]))
            sw.scene.scene.render_to_image(lambda im: ev.set())
        s = time.perf_counter()
        app.post_to_main_thread(w, step)
        ev.wait()
        times.append(time.perf_counter() - s)
    res["orbit_frame_s"] = times
    app.post_to_main_thread(w, w.close)
threading.Thread(target=worker, daemon=True).start()
app.run()
res["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
open(out_path, "w").write(json.dumps(res))
"""


# ---- parent -----------------------------------------------------------------------------------------


def _run(cmd: list[str], env: dict, timeout: float, log: Path) -> tuple[int | None, float, float]:
    """Run a child (its output into `log`); (exit code or None on timeout, wall seconds, peak RSS MiB)."""
    t = time.time()
    with log.open("w") as err:
        proc = subprocess.Popen(cmd, env=env, stdout=err, stderr=subprocess.STDOUT)
    deadline = t + timeout
    while time.time() < deadline:
        pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, time.time() - t, ru.ru_maxrss / 1024
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    return None, time.time() - t, float("nan")


def measure_viewer(map_path: Path, frames: int, env: dict, tmp: Path) -> dict:
    state = tmp / "state.json"
    script = tmp / "orbit.json"
    steps = [{"do": "orbit", "frames": frames, "degrees": 10}, {"do": "state", "path": str(state)}]
    script.write_text(json.dumps(steps + [{"do": "quit"}]))
    t0 = time.time()
    cmd = [sys.executable, "-m", "papl_mapper.cli", "view", str(map_path), "--script", str(script)]
    code, wall, rss = _run(cmd + ["--no-detect"], env, 600, tmp / "viewer.log")
    if code != 0:
        return {"error": f"exit {code}"}
    s = json.loads(state.read_text())
    t = s["timings_s"]
    return {
        "first_frame_from_launch_s": t["first_frame_unix"] - t0,
        "first_frame_in_command_s": t["first_frame_s"],
        "orbit_frame_median_s": float(np.median(t["orbit_frame_s"])),
        "orbit_frame_max_s": float(np.max(t["orbit_frame_s"])),
        "drawn": s["drawn"],
        "peak_rss_mib": rss,
        "wall_s": wall,
    }


def measure_open3d(map_path: Path, frames: int, env: dict, tmp: Path, timeout: float) -> dict:
    out = tmp / "o3d.json"
    out.unlink(missing_ok=True)
    t0 = time.time()
    cmd = [sys.executable, "-c", _O3D_CHILD, str(map_path), str(frames), str(out)]
    code, wall, rss = _run(cmd, env, timeout, tmp / "o3d.log")
    lines = (tmp / "o3d.log").read_text().splitlines()
    device = next((ln.split("'")[1] for ln in lines if "physical device '" in ln), "unknown")
    if code is None:
        return {"error": f"no frame within {timeout:.0f} s", "wall_s": wall, "vulkan_device": device}
    if code != 0 or not out.exists():
        return {"error": f"exit {code}", "vulkan_device": device}
    r = json.loads(out.read_text())
    return {
        "vulkan_device": device,
        "first_frame_from_launch_s": r["first_frame_unix"] - t0,
        "orbit_frame_median_s": float(np.median(r["orbit_frame_s"])),
        "orbit_frame_max_s": float(np.max(r["orbit_frame_s"])),
        "peak_rss_mib": rss,
        "wall_s": wall,
    }


def _display(env: dict) -> subprocess.Popen | None:
    if env.get("DISPLAY"):
        return None
    xvfb = shutil.which("Xvfb")
    if not xvfb:
        raise SystemExit("no DISPLAY and no Xvfb: run scripts/setup.sh or give a display")
    r, w = os.pipe()
    proc = subprocess.Popen(
        [xvfb, "-displayfd", str(w), "-screen", "0", "1920x1080x24", "-nolisten", "tcp"],
        pass_fds=(w,),
        stderr=subprocess.DEVNULL,
    )
    os.close(w)
    with os.fdopen(r) as fh:
        env["DISPLAY"] = ":" + fh.readline().strip()
    return proc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="100000,1000000")
    ap.add_argument("--frames", type=int, default=6, help="orbit frames per run")
    ap.add_argument("--o3d-frames", type=int, default=3, help="orbit frames per Open3D run")
    ap.add_argument("--o3d-timeout", type=float, default=240.0, help="seconds an Open3D run may take")
    ap.add_argument("--no-open3d", action="store_true", help="measure the viewer only")
    args = ap.parse_args()
    env = {**os.environ, "QT_LOGGING_RULES": "*.debug=false"}
    xvfb = _display(env)
    results: dict = {"sizes": {}}
    try:
        with tempfile.TemporaryDirectory(prefix="papl-viewer-bench-") as d:
            tmp = Path(d)
            for n in (int(s) for s in args.sizes.split(",")):
                path = tmp / f"map_{n}.papl"
                observed_map(n).save(path)
                code = (
                    "import json, sys; sys.path.insert(0, 'benchmarks'); import viewer; "
                    f"print(json.dumps(viewer._child_data({str(path)!r})))"
                )
                data = json.loads(
                    subprocess.run(
                        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
                    )
                    .stdout.strip()
                    .splitlines()[-1]
                )
                row = {"data_path": data, "viewer_vtk_qt": measure_viewer(path, args.frames, env, tmp)}
                if not args.no_open3d:
                    row["open3d_gui"] = measure_open3d(path, args.o3d_frames, env, tmp, args.o3d_timeout)
                results["sizes"][str(n)] = row
                path.unlink()
                _print_row(n, row)
    finally:
        if xvfb is not None:
            xvfb.terminate()
    from papl_mapper.gui.viewer_window import ViewerOptions

    results["decimation_threshold_lines"] = ViewerOptions().max_lines
    results["goal_first_frame_s"] = GOAL_FIRST_FRAME_S
    results["vtk_opengl_renderer"] = _gl_renderer(env)
    results["machine"] = machine_info()
    results["commit"] = git_commit()
    out = ROOT / "benchmarks" / "results" / "viewer.json"
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")


def _gl_renderer(env: dict) -> str:
    """The OpenGL renderer VTK gets on the display (as `papl-map view`'s probe reports it)."""
    from papl_mapper.cli.view import finish_probe, start_probe

    return finish_probe(start_probe(env), env)


def _print_row(n: int, row: dict) -> None:
    d = row["data_path"]
    print(f"\n{n:,} segments")
    print(
        f"  data path: load {d['load_s']:.2f} s, scene {d['scene_s']:.3f} s, "
        f"filter {d['select_filtered_s']:.3f} s, "
        f"polydata {d['polydata_s']:.3f} s, rms {d['rms_s']:.2f} s, peak {d['peak_rss_mib']:.0f} MiB"
    )
    for name in ("viewer_vtk_qt", "open3d_gui"):
        r = row.get(name)
        if r is None:
            continue
        if "error" in r:
            print(f"  {name:14s} {r['error']}")
            continue
        print(
            f"  {name:14s} first frame {r['first_frame_from_launch_s']:.2f} s from launch, orbit frame "
            f"median {r['orbit_frame_median_s']:.3f} s (max {r['orbit_frame_max_s']:.3f}), "
            f"peak RSS {r['peak_rss_mib']:.0f} MiB"
        )


if __name__ == "__main__":
    main()
