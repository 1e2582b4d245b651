"""process(): a rendered walk through the test room, written as a video, back to Tracks."""

from __future__ import annotations

import dataclasses
import threading

import cv2
import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.frontend import FrontendConfig, FrontendStats, open_recording, process, scale_camera
from papl_mapper.map import Camera
from papl_mapper.tracks import Tracks
from tests.test_frontend_scene import backproject, make_room, project, rendered_walk, segment_match

N_FRAMES = 24
BLACK = (10, 11)  # frames replaced by black: textureless, skipped
MAX_POINT_REPROJ_PX = 1.0  # median over all observations (mp4v compression included)
MIN_MATCH_PRECISION = 0.95
MAX_VERTICAL_ERR_DEG = 2.0  # median; the tracked vertical (point-track rotation + per-frame refinement)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    frames, cam, poses, gts = rendered_walk(N_FRAMES)
    path = tmp_path_factory.mktemp("walk") / "walk.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (cam.width, cam.height))
    for k, img in enumerate(frames):
        w.write(cv2.cvtColor(np.zeros_like(img) if k in BLACK else img, cv2.COLOR_GRAY2BGR))
    w.release()
    return path, cam, poses, gts


@pytest.fixture(scope="module")
def result(video):
    path, cam, _, _ = video
    calls = []
    stats = FrontendStats()
    tracks = process(
        open_recording(path), cam, FrontendConfig(), lambda d, t, m: calls.append((d, t, m)), stats
    )
    return tracks, calls, stats


def test_tracks_structure_skipped_frames_and_progress(result):
    tracks, calls, stats = result
    tracks.validate()
    kept = [k for k in range(N_FRAMES) if k not in BLACK]
    assert tracks.frame_index.tolist() == kept
    assert tracks.skipped_frames.tolist() == list(BLACK)
    assert stats.skipped == len(BLACK) and stats.frames == len(kept)
    np.testing.assert_allclose(tracks.timestamp, np.array(kept) / 30.0, atol=1e-3)
    assert tracks.is_keyframe[0] and tracks.is_keyframe[kept.index(BLACK[-1] + 1)]  # restart after the gap
    assert 2 < tracks.is_keyframe.sum() < len(kept)
    assert [c[0] for c in calls] == list(range(1, N_FRAMES + 1)) and calls[-1][1] == N_FRAMES
    assert "skipped" in calls[BLACK[0]][2]
    assert np.all(tracks.camera.distortion == 0)
    for f in range(len(tracks)):
        ids, uv = tracks.points_in(f)
        assert len(np.unique(ids)) == len(ids) and len(ids) > 100
        lids, xy, vp = tracks.lines_in(f)
        assert len(np.unique(lids)) == len(lids) and len(lids) > 20
    # descriptors: one per described observation, on keyframes only
    assert len(tracks.point_desc) == len(tracks.point_desc_row) > 0
    assert len(tracks.line_desc) == len(tracks.line_desc_row) > 0
    assert tracks.is_keyframe[tracks.point_frame[tracks.point_desc_row]].all()
    assert tracks.is_keyframe[tracks.line_frame[tracks.line_desc_row]].all()


def test_point_tracks_follow_scene_points(video, result):
    """Each track's first observation, ray-cast into the room, reprojects onto its later observations."""
    _, cam, poses, _ = video
    tracks, _, _ = result
    room = make_room(0)
    fi = tracks.frame_index
    errors = []
    for tid in np.unique(tracks.point_track):
        rows = np.flatnonzero(tracks.point_track == tid)
        if len(rows) < 3:
            continue
        first = rows[0]
        X = backproject(room, cam, poses[fi[tracks.point_frame[first]]], tracks.point_uv[first][None])
        for r in rows[1:]:
            uv = project(cam, poses[fi[tracks.point_frame[r]]], X)[0]
            errors.append(np.linalg.norm(uv - tracks.point_uv[r]))
    errors = np.array(errors)
    assert len(errors) > 1000
    assert np.median(errors) < MAX_POINT_REPROJ_PX
    assert np.mean(errors < 3.0) > 0.95


def test_segment_tracks_stay_on_one_ground_truth_edge(video, result):
    _, _, _, gts = video
    tracks, _, _ = result
    gt_of: dict[int, int] = {}
    good = bad = on_gt = 0
    for f in range(len(tracks)):
        ids, xy, _ = tracks.lines_in(f)
        gt, gid = gts[tracks.frame_index[f]]
        m = segment_match(xy, gt)
        on_gt += int((m >= 0).sum())
        for t, g in zip(ids.tolist(), m.tolist(), strict=True):
            if g < 0:
                continue
            if t in gt_of:
                good += gt_of[t] == gid[g]
                bad += gt_of[t] != gid[g]
            gt_of[t] = int(gid[g])
    assert good / (good + bad) >= MIN_MATCH_PRECISION
    assert on_gt / len(tracks.line_frame) > 0.5


def test_vanishing_outputs_are_consistent(video, result):
    _, _, poses, _ = video
    tracks, _, stats = result
    F = len(tracks)
    assert tracks.vp_dirs_c.shape[0] == F and tracks.vp_dirs_c.shape[2] == 3
    assert tracks.vertical_vp.shape == (F,)
    V = tracks.vp_dirs_c.shape[1]
    assert tracks.line_vp.min() >= -1 and tracks.line_vp.max() < V
    for f in range(F):
        _, _, vp = tracks.lines_in(f)
        dirs = tracks.vp_dirs_c[f]
        for k in np.unique(vp[vp >= 0]):
            assert np.all(np.isfinite(dirs[k])) and abs(np.linalg.norm(dirs[k]) - 1) < 1e-6
    # the vertical, where found, is the room's (world up is -y) seen from the camera
    errs = []
    for f in np.flatnonzero(tracks.vertical_vp >= 0):
        R_cw = np.linalg.inv(poses[tracks.frame_index[f]])[:3, :3]
        up_c = R_cw @ np.array([0.0, -1.0, 0.0])
        d = tracks.vp_dirs_c[f, tracks.vertical_vp[f]]
        errs.append(np.degrees(np.arccos(min(1.0, abs(float(d @ up_c))))))
    assert stats.vertical_source in ("initialised", "per-frame")
    assert len(errs) >= F // 2
    assert np.median(errs) < MAX_VERTICAL_ERR_DEG


def test_tracks_save_and_load_round_trip(result, tmp_path):
    tracks, _, _ = result
    back = Tracks.load(tracks.save(tmp_path / "tracks.npz"))
    np.testing.assert_array_equal(back.point_desc, tracks.point_desc)
    np.testing.assert_array_equal(back.skipped_frames, tracks.skipped_frames)


def test_camera_of_another_size(video):
    path, cam, _, _ = video
    rec = open_recording(path, end_s=0.2)
    # same aspect ratio: scaled to the video
    big = scale_camera(cam, 2 * cam.width, 2 * cam.height)
    tracks = process(rec, big, FrontendConfig(vanishing=False))
    assert tracks.camera.fx == pytest.approx(cam.fx) and tracks.camera.cx == pytest.approx(cam.cx)
    assert np.isnan(tracks.vp_dirs_c).all() and (tracks.line_vp == -1).all()
    wrong = Camera(1280, 720, 900, 900, 640, 360)
    with pytest.raises(InputError, match="aspect"):
        process(rec, wrong)


def test_downscaled_recording_uses_scaled_camera(video):
    path, cam, _, _ = video
    rec = open_recording(path, end_s=0.2, max_size=320)
    tracks = process(rec, cam, FrontendConfig(vanishing=False))
    assert (tracks.camera.width, tracks.camera.height) == (320, 240)
    assert tracks.camera.fx == pytest.approx(cam.fx / 2)


def test_all_textureless_is_an_input_error(tmp_path):
    path = tmp_path / "grey.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 120))
    for _ in range(5):
        w.write(np.full((120, 160, 3), 128, np.uint8))
    w.release()
    cam = Camera(160, 120, 150, 150, 79.5, 59.5)
    with pytest.raises(InputError, match="textureless"):
        process(open_recording(path), cam)


def test_config_loads_from_toml_and_overrides(tmp_path):
    from papl_mapper.config import load_config

    p = tmp_path / "frontend.toml"
    p.write_text('work_max_size = 480\n[lines]\ndetector = "lsd"\n[vp]\nmanhattan_only = true\n')
    cfg = load_config(FrontendConfig, p, ["points.max_points=200", "keyframes.min_parallax_px=12.5"])
    assert cfg.work_max_size == 480 and cfg.lines.detector == "lsd" and cfg.vp.manhattan_only
    assert cfg.points.max_points == 200 and cfg.keyframes.min_parallax_px == 12.5
    assert cfg.vp.track_gate_deg == FrontendConfig().vp.track_gate_deg


def test_presets_and_segments_at_reduced_size(video):
    from papl_mapper.frontend import frontend_preset

    path, cam, _, gts = video
    assert frontend_preset("accurate") == FrontendConfig()
    assert frontend_preset("realtime").vp_stride > 1
    with pytest.raises(InputError, match="unknown frontend preset"):
        frontend_preset("turbo")
    cfg = dataclasses.replace(frontend_preset("realtime"), segments_max_size=320)
    tracks = process(open_recording(path, end_s=0.3), cam, cfg)
    on_gt = []
    for f in range(len(tracks)):
        _, xy, _ = tracks.lines_in(f)
        on_gt.append(segment_match(xy, gts[tracks.frame_index[f]][0], dist_px=4.0) >= 0)
    assert np.mean(np.concatenate(on_gt)) > 0.5  # endpoints mapped back to full-resolution pixels


def test_threaded_stages_give_the_same_tracks(video, result):
    """Vanishing points and segments in worker threads (the default) or in the main thread: same tracks."""
    path, cam, _, _ = video
    threaded, _, stats = result
    assert FrontendConfig().vp_thread and FrontendConfig().parallel
    assert set(stats.cpu_seconds) == set(stats.seconds) and stats.cpu_seconds["vp"] > 0
    cv_threads = cv2.getNumThreads()
    sequential = FrontendConfig(vp_thread=False, parallel=False, opencv_threads=1)
    for cfg in (sequential, FrontendConfig(vp_thread=False)):
        other = process(open_recording(path), cam, cfg)
        assert cv2.getNumThreads() == cv_threads  # restored
        for f in dataclasses.fields(Tracks):
            a, b = getattr(threaded, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b, err_msg=f.name)


def test_an_interrupt_stops_the_decoder_thread_before_it_propagates(video):
    """Ctrl-C in the middle of the frontend: the decoding thread has ended when the interrupt leaves
    `process` (a decoder still running holds the interpreter at exit, or aborts it inside OpenCV)."""
    path, cam, _, _ = video

    def interrupt(done: int, total: int, message: str) -> None:
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # the traceback keeps process()'s frame (and its iterator) alive
        process(open_recording(path), cam, FrontendConfig(), interrupt)
    assert not [t for t in threading.enumerate() if t.name.startswith("decode-")]
