"""The viewer's data path, 2D panel and command line, without a window (see test_gui_viewer_window.py).

The demo's ground-truth map (samples/demo/gt/map.papl) is the known answer: exact lines, axes and
keyframe poses of samples/demo/video.mp4, so reprojected lines must sit on the frame's edges.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.gui.viewer_pick import clearest_spot, line_facts, pick_point, pick_segment, to_pixels
from papl_mapper.gui.viewer_scene import Filters, ViewerScene, line_rms_px
from papl_mapper.gui.viewer_walk import FrameSource, keyframe_panel, open_frames, reproject_lines
from papl_mapper.map import Map

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "samples" / "demo"


@pytest.fixture(scope="module")
def gt_map() -> Map:
    return Map.load(DEMO / "gt" / "map.papl")


def with_recording(m: Map, path: Path) -> Map:
    """A copy of `m` that names `path` as its recording, as `papl-map run` writes it."""
    return dataclasses.replace(m, metadata={**m.metadata, "source_path": str(path)})


# ---- data path ------------------------------------------------------------------------------------


def test_axis_switches_and_min_observations_select_the_right_lines(gt_map: Map) -> None:
    scene = ViewerScene.from_map(gt_map)
    axis = gt_map.lines.axis_of_line()
    f = scene.default_filters()
    everything = scene.selection(f, 10**6)
    assert len(everything.passing) == len(gt_map.lines)
    assert everything.counts == [*np.bincount(axis[axis >= 0], minlength=3).tolist(), int((axis < 0).sum())]
    f.axes_on[0] = False
    off = scene.selection(f, 10**6)
    assert not np.isin(np.flatnonzero(axis == 0), off.passing).any()
    assert len(off.passing) == len(gt_map.lines) - (axis == 0).sum()
    n_obs = np.bincount(gt_map.lines.obs_ids[:, 0], minlength=len(gt_map.lines))
    sel = scene.selection(Filters([True] * 3, min_observations=5), 10**6)
    assert sel.passing.tolist() == np.flatnonzero(n_obs >= 5).tolist()
    assert 0 < len(sel.passing) < len(gt_map.lines)


def test_decimation_draws_a_nested_seeded_subset_and_says_so(gt_map: Map) -> None:
    scene = ViewerScene.from_map(gt_map)
    loose = scene.selection(scene.default_filters(), 50)
    assert loose.decimated and len(loose.drawn) == 50 and len(loose.passing) == len(gt_map.lines)
    assert loose.note == f"decimated: 50 of {len(gt_map.lines)} lines drawn"
    tight = scene.selection(Filters([True] * 3, min_observations=5), 50)
    # a line drawn at the looser filter that still passes the tighter one is still drawn
    assert set(np.intersect1d(loose.drawn, tight.passing)) <= set(tight.drawn)
    assert scene.selection(scene.default_filters(), 10**6).note == ""


def test_reprojection_rms_is_zero_for_exact_observations_and_grows_with_offset(gt_map: Map) -> None:
    m = dataclasses.replace(gt_map)
    rms = line_rms_px(m)
    seen = np.bincount(m.lines.obs_ids[:, 0], minlength=len(m.lines)) > 0
    assert np.isnan(rms[~seen]).all()
    base = np.nanmedian(rms)
    assert base < 2.0  # the ground truth's observations: noiseless projections clipped to the image
    # shift every observation of line 0 by 5 px across its image direction: its RMS grows by ~5 px
    lid = 0 if seen[0] else int(np.flatnonzero(seen)[0])
    rows = m.lines.obs_ids[:, 0] == lid
    xy = m.lines.obs_xy.copy()
    d = xy[rows, 2:] - xy[rows, :2]
    n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
    xy[rows] += np.concatenate([n, n], axis=1) * 5.0
    shifted = dataclasses.replace(m, lines=dataclasses.replace(m.lines, obs_xy=xy))
    assert line_rms_px(shifted)[lid] == pytest.approx(math.hypot(5.0, rms[lid]), abs=0.3)


def test_pick_segment_and_point_find_what_is_under_the_click() -> None:
    # an orthographic camera looking down -Z: world x, y -> NDC x, y in [-1, 1] over [-10, 10]
    M = np.diag([0.1, 0.1, -0.1, 1.0])
    size = (200, 200)
    ends = np.array([[[-5, 0, 0], [5, 0, 0]], [[0, -5, 1], [0, 5, 1]], [[6, 6, 0], [8, 8, 0]]], float)
    px, _ = to_pixels(M, ends.reshape(-1, 3), size)
    assert px[0].tolist() == [50.0, 100.0] and px[1].tolist() == [150.0, 100.0]
    assert pick_segment(M, size, ends, (70.0, 103.0)) == 0
    assert pick_segment(M, size, ends, (100.0, 60.0)) == 1
    assert pick_segment(M, size, ends, (100.0, 100.0)) == 1  # the crossing: segment 1 is nearer (z = 1)
    assert pick_segment(M, size, ends, (20.0, 20.0)) is None
    spot = clearest_spot(M, size, ends, 0)
    assert pick_segment(M, size, ends, spot) == 0 and abs(spot[0] - 100) > 10
    xyz = np.array([[0.0, 0, 0], [2, 2, 0]])
    assert pick_point(M, size, xyz, (121, 79)) == 1 and pick_point(M, size, xyz, (150, 150)) is None


def test_line_facts_name_axis_representation_and_the_keyframes_seeing_it(gt_map: Map) -> None:
    scene = ViewerScene.from_map(gt_map)
    scene.compute_rms(gt_map)
    row = int(np.argmax(scene.n_obs))
    facts = line_facts(gt_map, scene, row)
    assert facts.id == int(gt_map.lines.ids[row]) and facts.n_obs == scene.n_obs[row]
    assert facts.keyframe_ids == sorted(set(gt_map.lines.obs_ids[gt_map.lines.obs_ids[:, 0] == facts.id, 1]))
    assert facts.representation == "anchored" and facts.axis in ("vertical", "horizontal 1", "horizontal 2")
    assert facts.length == pytest.approx(np.linalg.norm(np.diff(gt_map.lines.endpoints_w[row], axis=0)))
    assert f"line {facts.id}: " in facts.text("m") and " m, " in facts.text("m")


# ---- 2D panel -------------------------------------------------------------------------------------


def _explained(det: np.ndarray, proj: np.ndarray, tol_px: float = 4.0) -> float:
    """Fraction of detected segments whose both endpoints lie within tol_px of a reprojected segment."""
    if not len(det) or not len(proj):
        return 0.0
    from papl_mapper.gui.viewer_pick import segment_distances

    hits = 0
    for x1, y1, x2, y2 in det:
        d1 = segment_distances(proj[:, :2], proj[:, 2:], np.array([x1, y1]))[0]
        d2 = segment_distances(proj[:, :2], proj[:, 2:], np.array([x2, y2]))[0]
        hits += bool(((d1 < tol_px) & (d2 < tol_px)).any())
    return hits / len(det)


def test_panel_shows_the_keyframes_own_frame_under_its_reprojected_lines(gt_map: Map) -> None:
    from papl_mapper.frontend.lines import LineConfig, SegmentDetector

    m = with_recording(gt_map, DEMO / "video.mp4")
    frames, why = open_frames(m, None)
    assert frames is not None and why == ""
    scene = ViewerScene.from_map(m)
    det = SegmentDetector(LineConfig())
    row = len(m.keyframes) // 2
    panel = keyframe_panel(m, row, frames, why, scene.endpoints_w, scene.line_rgb, det)
    assert panel.has_frame and panel.image.shape == (480, 640, 3)
    assert panel.n_detected > 10 and panel.n_reprojected > 10
    assert f"frame {m.keyframes.frame_index[row]}" in panel.caption
    proj, _ = reproject_lines(m, scene.endpoints_w, row)
    own = det.detect(frames.read(int(m.keyframes.frame_index[row])).mean(axis=2).astype(np.uint8))
    other = det.detect(frames.read(int(m.keyframes.frame_index[row]) + 60).mean(axis=2).astype(np.uint8))
    # the map explains its own keyframe's edges, and much less of a frame two seconds later
    assert _explained(own, proj) > 0.5
    assert _explained(other, proj) < 0.6 * _explained(own, proj)
    # the axis colours are drawn into the panel
    vertical = np.array(scene.axis_rgb[gt_map.axes.vertical_index])
    assert (np.abs(panel.image.astype(int) - vertical).sum(axis=2) < 30).sum() > 200
    frames.close()


def test_moved_or_unrecorded_recording_gives_a_panel_naming_where_it_looked(gt_map: Map, tmp_path) -> None:
    gone = tmp_path / "moved" / "video.mp4"
    frames, why = open_frames(with_recording(gt_map, gone), tmp_path)
    # where the map says, then the same name beside the run folder
    assert frames is None and why == f"recording not found, looked for {gone} and {tmp_path / 'video.mp4'}"
    scene = ViewerScene.from_map(gt_map)
    panel = keyframe_panel(gt_map, 0, None, why, scene.endpoints_w, scene.line_rgb, None)
    assert not panel.has_frame and panel.caption == why and panel.image.shape == (480, 640, 3)
    frames, why = open_frames(gt_map, None)  # an old map: no recording recorded at all
    assert frames is None and "does not record its recording" in why
    frames, why = open_frames(gt_map, None, DEMO / "video.mp4")  # the user says where it is
    assert frames is not None and why == ""
    frames.close()
    (tmp_path / "video.mp4").write_bytes(b"not a video")
    frames, why = open_frames(with_recording(gt_map, tmp_path / "video.mp4"), None)
    assert frames is None and "not a readable video" in why


def test_frame_source_reads_frames_by_index_like_a_sequential_decode() -> None:
    import cv2

    cap = cv2.VideoCapture(str(DEMO / "video.mp4"))
    seq = []
    for _ in range(45):
        seq.append(cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2RGB))
    cap.release()
    src = FrameSource(DEMO / "video.mp4", (640, 480))
    for i in (40, 3, 44, 10):  # backwards jumps seek, short forward gaps read through
        assert np.abs(src.read(i).astype(int) - seq[i]).mean() < 1.0
    with pytest.raises(OSError, match="frame 100000"):
        src.read(100000)
    src.close()


# ---- command line ---------------------------------------------------------------------------------


def test_view_without_a_display_says_so_in_one_line(monkeypatch, capsys) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code = main(["view", str(DEMO / "gt" / "map.papl")])
    err = capsys.readouterr().err.strip()
    assert code == 4 and len(err.splitlines()) == 1
    assert "no display" in err and "papl-map render" in err and "papl-map report" in err


@pytest.mark.parametrize(
    ("content", "fault"),
    [(b"hello", "corrupt or truncated map file"), (None, "no map.papl in this folder")],
)
def test_view_refuses_a_bad_map_in_one_line_naming_the_file(tmp_path, monkeypatch, capsys, content, fault):
    monkeypatch.setenv("DISPLAY", ":0")  # the map is read before any window is tried
    monkeypatch.setattr("papl_mapper.cli.view.check_display", lambda: None)
    if content is None:
        target = tmp_path
    else:
        target = tmp_path / "bad.papl"
        target.write_bytes(content)
    code = main(["view", str(target)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and str(target) in err and fault in err


def test_view_refuses_a_missing_recording_in_one_line(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr("papl_mapper.cli.view.check_display", lambda: None)
    gone = tmp_path / "walk.mp4"
    code = main(["view", str(DEMO / "gt" / "map.papl"), "--recording", str(gone)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and str(gone) in err


def test_view_refuses_a_bad_script_before_opening(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr("papl_mapper.cli.view.check_display", lambda: None)
    script = tmp_path / "s.json"
    script.write_text('[{"do": "call", "method": "__del__"}]')
    code = main(["view", str(DEMO / "gt" / "map.papl"), "--script", str(script)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and str(script) in err and "callable" in err


def test_unreachable_display_is_refused_in_one_line_naming_it() -> None:
    import os

    from papl_mapper.cli.view import finish_probe, start_probe
    from papl_mapper.errors import BackendUnavailableError

    env = {**os.environ, "DISPLAY": ":4321"}  # no X server there: Qt aborts the probe, not this process
    with pytest.raises(BackendUnavailableError) as err:
        finish_probe(start_probe(env), env)
    msg = str(err.value)
    assert (
        "\n" not in msg and "display :4321" in msg and "papl-map render" in msg and "papl-map report" in msg
    )


def test_readme_lists_every_keyboard_shortcut() -> None:
    from papl_mapper.gui.viewer_window import SHORTCUTS

    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## The desktop viewer") : readme.index("## The map file")]
    for keys, _, what in SHORTCUTS:
        assert f"| `{keys}` | {what} |" in section
