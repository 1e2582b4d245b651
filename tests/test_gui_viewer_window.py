"""The viewer's real window under Xvfb, driven by its scripted-control hook through `papl-map view`.

One viewer process runs a script over the demo's ground-truth map (named as the recording's map)
and writes screenshots and state; the tests check pixels and state. A second process opens an old
map with no lines and no recording. Xvfb comes from scripts/setup.sh.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from papl_mapper.map import Lines, Map

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "samples" / "demo"
TOL = 30  # summed |RGB| difference that still counts as a palette colour


@pytest.fixture(scope="module")
def display():
    """A private Xvfb display for this module."""
    xvfb = shutil.which("Xvfb")
    assert xvfb, "Xvfb is missing: run scripts/setup.sh (it installs xvfb for the viewer's tests)"
    r, w = os.pipe()
    proc = subprocess.Popen(
        [xvfb, "-displayfd", str(w), "-screen", "0", "1920x1080x24", "-nolisten", "tcp"],
        pass_fds=(w,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(w)
    with os.fdopen(r) as fh:
        number = fh.readline().strip()
    assert number, "Xvfb did not start"
    yield f":{number}"
    proc.terminate()
    proc.wait(10)


def run_viewer(source: Path, steps: list[dict], display: str, tmp: Path, *extra: str) -> None:
    script = tmp / "script.json"
    script.write_text(json.dumps(steps + [{"do": "quit"}]))
    env = {**os.environ, "DISPLAY": display}
    proc = subprocess.run(
        [sys.executable, "-m", "papl_mapper.cli", "view", str(source), "--script", str(script), *extra],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


def colour_pixels(img: np.ndarray, rgb) -> int:
    return int((np.abs(img[..., :3].astype(int) - np.asarray(rgb)).sum(axis=2) < TOL).sum())


def crop(img: np.ndarray, rect: list[int]) -> np.ndarray:
    x, y, w, h = rect
    return img[y : y + h, x : x + w]


@pytest.fixture(scope="module")
def demo_run(display, tmp_path_factory):
    """The window on a run folder whose map is the demo's ground truth and names the demo video."""
    tmp = tmp_path_factory.mktemp("viewer")
    run = tmp / "run"
    run.mkdir()
    m = Map.load(DEMO / "gt" / "map.papl")
    m = dataclasses.replace(m, metadata={**m.metadata, "source_path": str(DEMO / "video.mp4")})
    m.save(run / "map.papl")
    axis = m.lines.axis_of_line()
    vertical = m.axes.vertical_index
    # the longest vertical line: the one the pick test clicks
    rows = np.flatnonzero(axis == vertical)
    pick_row = rows[np.argmax(m.lines.lengths()[rows])]
    pick_id = int(m.lines.ids[pick_row])
    ends = m.lines.endpoints_w[pick_row]
    o = tmp / "out"
    steps = [
        {"do": "wait", "ms": 300},
        {"do": "render", "path": str(o / "all.png")},
        {"do": "state", "path": str(o / "all.json")},
        {"do": "key", "keys": str(vertical + 1)},  # toggles the vertical axis off
        {"do": "render", "path": str(o / "no_vertical.png")},
        {"do": "state", "path": str(o / "no_vertical.json")},
        {"do": "key", "keys": str(vertical + 1)},
        {"do": "call", "method": "set_filters", "kwargs": {"min_observations": 5}},
        {"do": "state", "path": str(o / "min_obs.json")},
        {"do": "call", "method": "set_filters", "kwargs": {"min_observations": 0}},
        {"do": "click_line", "id": pick_id},
        {"do": "state", "path": str(o / "picked.json")},
        {"do": "screenshot", "path": str(o / "picked.png")},
        {"do": "key", "keys": "Esc"},
        {"do": "click", "xyz": ends[0].tolist(), "shift": True},
        {"do": "click", "xyz": ends[1].tolist(), "shift": True},
        {"do": "state", "path": str(o / "measured.json")},
        {"do": "key", "keys": "Esc"},
        {"do": "call", "method": "save_viewpoint", "kwargs": {"path": str(o / "vp.json")}},
        {"do": "key", "keys": "T"},
        {"do": "state", "path": str(o / "top.json")},
        {"do": "key", "keys": "Ctrl+O"},  # restores the default file: not the one saved above
        {"do": "call", "method": "restore_viewpoint", "kwargs": {"path": str(o / "vp.json")}},
        {"do": "state", "path": str(o / "restored.json")},
        {"do": "key", "keys": "P"},
        {"do": "key", "keys": "+"},
        {"do": "state", "path": str(o / "no_points.json")},
        {"do": "key", "keys": "P"},
        {"do": "key", "keys": "Space"},
        {"do": "wait", "ms": 1200},
        {"do": "key", "keys": "Space"},
        {"do": "state", "path": str(o / "played.json")},
        {"do": "call", "method": "save_png", "kwargs": {"path": str(o / "saved.png")}},
        {"do": "key", "keys": "C"},  # the 3D camera follows the walk
        {"do": "call", "method": "set_keyframe", "kwargs": {"row": 10}},
        {"do": "state", "path": str(o / "k10.json")},
        {"do": "screenshot", "path": str(o / "k10.png")},
        {"do": "key", "keys": "Right"},
        {"do": "call", "method": "set_keyframe", "kwargs": {"row": 30}},
        {"do": "state", "path": str(o / "k30.json")},
        {"do": "screenshot", "path": str(o / "k30.png")},
    ]
    run_viewer(run, steps, display, tmp)
    state = {p.stem: json.loads(p.read_text()) for p in o.glob("*.json")}
    images = {p.stem: np.asarray(Image.open(p).convert("RGB")) for p in o.glob("*.png")}
    return m, pick_id, state, images


def test_each_axis_colour_is_drawn_in_proportion_to_its_lines(demo_run) -> None:
    m, _, state, images = demo_run
    s, img = state["all"], images["all"]
    assert s["drawn"] == len(m.lines) and "decimated" not in s["status"]
    counts = np.array([colour_pixels(img, c) for c in s["colors"]], float)
    length = np.array(s["screen_length_px"])
    assert (counts > 0).all(), counts
    # pixel share of each colour follows its lines' on-screen length share (line width is constant)
    share_px, share_len = counts / counts.sum(), length / length.sum()
    assert np.all(np.abs(np.log(share_px / share_len)) < np.log(2.0)), (share_px, share_len)


def test_axis_toggle_removes_its_colour_and_its_count(demo_run) -> None:
    m, _, state, images = demo_run
    v = m.axes.vertical_index
    blue = state["all"]["colors"][v]
    before, after = colour_pixels(images["all"], blue), colour_pixels(images["no_vertical"], blue)
    assert before > 500 and after < 0.02 * before
    s = state["no_vertical"]
    assert s["filters"]["axes_on"][v] is False and s["counts"][v] == 0
    assert s["passing"] == len(m.lines) - state["all"]["counts"][v]
    others = [c for i, c in enumerate(state["all"]["colors"]) if i != v]
    for c in others:
        assert colour_pixels(images["no_vertical"], c) > 0.5 * colour_pixels(images["all"], c)


def test_min_observations_filter_changes_the_count(demo_run) -> None:
    m, _, state, _ = demo_run
    n_obs = np.bincount(m.lines.obs_ids[:, 0], minlength=len(m.lines))
    assert state["min_obs"]["passing"] == int((n_obs >= 5).sum()) < len(m.lines)
    assert state["min_obs"]["filters"]["min_observations"] == 5


def test_slider_moves_the_camera_and_changes_the_2d_panel(demo_run) -> None:
    m, _, state, images = demo_run
    k10, k30 = state["k10"], state["k30"]
    assert k10["keyframe_row"] == 10 and k30["keyframe_row"] == 30 and k30["follow"]
    for s, row in ((k10, 10), (k30, 30)):
        centre, forward = m.keyframes.T_wc[row, :3, 3], m.keyframes.T_wc[row, :3, 2]
        assert np.allclose(s["viewpoint"]["position"], centre)  # the camera stands at the keyframe
        assert np.allclose(s["viewpoint"]["focal_point"], centre + forward)
        assert f"frame {m.keyframes.frame_index[row]}" in s["panel"]["caption"]
    assert np.linalg.norm(np.subtract(k10["viewpoint"]["position"], k30["viewpoint"]["position"])) > 0.5
    a, b = crop(images["k10"], k10["panel_rect"]), crop(images["k30"], k30["panel_rect"])
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 10
    v3a, v3b = crop(images["k10"], k10["view_rect"]), crop(images["k30"], k30["view_rect"])
    assert np.abs(v3a.astype(int) - v3b.astype(int)).mean() > 5


def test_2d_panel_shows_the_frame_with_overlaid_segments(demo_run) -> None:
    m, _, state, images = demo_run
    s = state["k30"]
    assert s["panel"]["has_frame"] and s["panel"]["detected"] > 0 and s["panel"]["reprojected"] > 0
    panel = crop(images["k30"], s["panel_rect"])
    colours = s["colors"][:-1]  # every axis colour that is in this view of the corridor
    assert sum(colour_pixels(panel, c) for c in colours) > 300
    assert colour_pixels(panel, (20, 20, 20)) > 50  # detected segments, near black
    # the frame itself: many distinct grey levels of the corridor's texture, not a flat card
    assert len(np.unique(panel.reshape(-1, 3)[:, 0])) > 100


def test_picking_a_known_line_reports_its_id(demo_run) -> None:
    m, pick_id, state, images = demo_run
    p = state["picked"]["picked"]
    assert p is not None and p["id"] == pick_id and p["axis"] == "vertical"
    assert state["picked"]["pick_text"].startswith(f"line {pick_id}: vertical, length ")
    seen = sorted(set(m.lines.obs_ids[m.lines.obs_ids[:, 0] == pick_id, 1].tolist()))
    assert p["keyframe_ids"] == seen and p["n_obs"] == len(seen)
    assert colour_pixels(crop(images["picked"], state["picked"]["view_rect"]), (230, 0, 120)) > 50


def test_saved_png_has_the_previews_title_band_and_legend(demo_run) -> None:
    _, _, state, images = demo_run
    img = images["saved"]
    assert img.shape[0] > 500 and img.shape[1] > 500
    band = img[:20, 200:]
    assert (np.abs(band.astype(int) - (245, 245, 245)).sum(axis=2) < 6).mean() > 0.9  # the previews' panel
    legend = img[: img.shape[0] // 2, -360:]
    for c in state["all"]["colors"]:
        assert colour_pixels(legend, c) > 50, c


def test_old_map_without_lines_or_recording_opens_and_says_why(display, tmp_path) -> None:
    m = Map.load(DEMO / "gt" / "map.papl")
    empty = dataclasses.replace(m, lines=Lines.empty(len(m.axes)))
    path = tmp_path / "old.papl"
    empty.save(path)
    out = tmp_path / "state.json"
    run_viewer(path, [{"do": "wait", "ms": 200}, {"do": "state", "path": str(out)}], display, tmp_path)
    s = json.loads(out.read_text())
    assert s["lines"] == 0 and "no lines in this map" in s["status"]
    assert not s["panel"]["has_frame"] and "does not record its recording" in s["panel"]["caption"]


def test_measuring_two_endpoints_gives_their_distance(demo_run) -> None:
    m, pick_id, state, _ = demo_run
    row = int(np.flatnonzero(m.lines.ids == pick_id)[0])
    s = state["measured"]
    assert s["measured"] == pytest.approx(float(m.lines.lengths()[row]), abs=1e-6)
    assert s["pick_text"] == f"distance {s['measured']:.3f} m"


def test_viewpoint_restores_and_keys_reach_points_and_play(demo_run) -> None:
    _, _, state, _ = demo_run
    top, restored = state["top"]["viewpoint"], state["restored"]["viewpoint"]
    before = state["measured"]["viewpoint"]  # the view when it was saved
    assert not np.allclose(top["position"], before["position"])
    assert np.allclose(restored["position"], before["position"])
    assert np.allclose(restored["view_up"], before["view_up"])
    assert state["no_points"]["show_points"] is False and state["no_points"]["point_size"] == 4.0
    played = state["played"]
    assert played["playing"] is False and played["keyframe_row"] >= 2  # 4 keyframes a second for ~1.2 s


def test_more_lines_than_the_renderer_holds_are_decimated_and_the_window_says_so(display, tmp_path) -> None:
    out = tmp_path / "state.json"
    steps = [{"do": "state", "path": str(out)}]
    run_viewer(DEMO / "gt" / "map.papl", steps, display, tmp_path, "--max-lines", "50", "--no-detect")
    s = json.loads(out.read_text())
    assert s["drawn"] == 50 and s["passing"] == s["lines"] > 50
    assert f"decimated: 50 of {s['lines']} lines drawn" in s["status"]
