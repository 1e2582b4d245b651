"""Visibility clip of the ground truth and line recall against it, on hand-built scenes with known answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.eval import EvalConfig, evaluate, segment_visibility
from papl_mapper.eval.visibility import frustum_intervals, occluded_intervals
from papl_mapper.map import Camera, Keyframes, Lines, LineState, Map
from papl_mapper.synth.path import walkthrough
from papl_mapper.synth.project import NEAR, occluded, project, quads_in_view
from papl_mapper.synth.scenes import make_scene
from papl_mapper.trajectory_io import Trajectory, write_tum

# named tolerances
EXACT = 1e-9  # closed-form intervals
SPACING = 0.01  # piece length of the visibility clip in these tests
LENGTH_TOL = SPACING  # a visible run is exact to within a piece at each of its ends (boundaries fall on
#                       piece edges here, so this is loose)
BRUTE_AGREEMENT = 0.995  # share of pieces whose frame count equals the per-sample ray test's (margins
#                          are measured along the ray there and perpendicular to the quad here)

# 90 degrees horizontal field of view: the image spans x/z in [-1, 1] and y/z in [-0.75, 0.75]
CAM = Camera(640, 480, 320.0, 320.0, 319.5, 239.5)
WALL = np.array([[[0, -1, 3], [2, -1, 3], [2, 1, 3], [0, 1, 3.0]]])  # z = 3, x in [0, 2], y in [-1, 1]
SEGMENTS = np.array(
    [
        [[-1, 2.5, 5], [1, 2.5, 5]],  # fully visible (passes above the wall), length 2
        [[-2, 0.5, 6], [2, 0.5, 6]],  # the half x > 0 behind the wall, length 4
        [[20, 0, 1], [21, 0, 1]],  # never in view, length 1
        [[2, -2, 4], [6, -2, 4]],  # leaves the image at x/z = 1 (x = 4), length 4
        [[-1, 0, -5], [1, 0, -5]],  # behind the camera but in the 2 turned frames, length 2
        [[0.5, -0.5, 3], [1.5, -0.5, 3]],  # lies on the wall: not hidden by it, length 1
    ],
    float,
)
N_FORWARD, N_TURNED = 8, 2


def poses() -> np.ndarray:
    """8 frames looking along +z, then 2 turned 180 degrees about y (looking along -z); the camera moves
    up along y a little (this leaves every x/z, and so every answer here, unchanged)."""
    n = N_FORWARD + N_TURNED
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 1, 3] = -0.05 * np.arange(n)  # y points down in this camera: moving up
    T[N_FORWARD:, :3, :3] = np.diag([-1.0, 1.0, -1.0])
    return T


def test_interval_functions_are_exact():
    lo, hi = frustum_intervals(CAM, np.eye(4), SEGMENTS)
    expected = [(0, 1), (0, 1), None, (0, 0.5), None, (0, 1)]
    for k, e in enumerate(expected):
        if e is None:
            assert lo[k] > hi[k]
        else:
            assert lo[k] == pytest.approx(e[0], abs=EXACT) and hi[k] == pytest.approx(e[1], abs=EXACT)
    olo, ohi = occluded_intervals(np.zeros(3), WALL, SEGMENTS)
    assert olo[1, 0] == pytest.approx(0.5, abs=EXACT) and ohi[1, 0] == pytest.approx(1.0, abs=EXACT)
    hidden = olo[:, 0] < ohi[:, 0]
    assert hidden.tolist() == [False, True, False, False, False, False]


def test_visible_lengths_of_the_hand_built_scene():
    vis = segment_visibility(SEGMENTS, CAM, poses(), SPACING, WALL)
    assert vis.n_frames == N_FORWARD + N_TURNED and vis.occlusion
    want = {5: [2, 2, 0, 2, 0, 1], 2: [2, 2, 0, 2, 2, 1], 9: [0, 0, 0, 0, 0, 0]}
    for n, lengths in want.items():
        np.testing.assert_allclose(vis.visible_length(n), lengths, atol=LENGTH_TOL)
    # without the wall the second segment is seen whole
    free = segment_visibility(SEGMENTS, CAM, poses(), SPACING, None)
    np.testing.assert_allclose(free.visible_length(5), [2, 4, 0, 2, 0, 1], atol=LENGTH_TOL)
    # the clip as segments: one run per seen segment, with the right ends
    parts, axis = vis.parts(5)
    assert len(parts) == 4 and len(axis) == 4
    np.testing.assert_allclose(parts[1], [[-2, 0.5, 6], [0, 0.5, 6]], atol=LENGTH_TOL)
    np.testing.assert_allclose(parts[2], [[2, -2, 4], [4, -2, 4]], atol=LENGTH_TOL)


def test_a_quad_seen_edge_on_or_behind_the_segment_hides_nothing():
    seg = np.array([[[-2, 0.5, 2], [2, 0.5, 2]]])  # in front of the wall
    olo, ohi = occluded_intervals(np.zeros(3), WALL, seg)
    assert not (olo < ohi).any()
    edge_on = np.array([[[-1, 0, 1], [1, 0, 1], [1, 0, 9], [-1, 0, 9.0]]])  # the plane y = 0 holds the camera
    olo, ohi = occluded_intervals(np.zeros(3), edge_on, SEGMENTS)
    assert not (olo < ohi).any()


def test_counts_agree_with_a_per_sample_ray_test_on_a_synthetic_scene():
    """On the corridor scene, the frame counts equal a brute-force test of every piece's midpoint
    (frustum, then a ray-quad test) in nearly every piece."""
    scene = make_scene("corridor", 0)
    _, T = walkthrough(scene, 40, 4.0, seed=0)  # 10 s of walking in 40 frames
    T = T[::4]
    vis = segment_visibility(scene.segments, CAM, T, 0.05, scene.quad_corners)
    d = scene.segments[vis.owner, 1] - scene.segments[vis.owner, 0]
    mid = scene.segments[vis.owner, 0] + (0.5 * (vis.t0 + vis.t1))[:, None] * d
    count = np.zeros(len(mid), np.int64)
    for Twc in T:
        uv, z = project(CAM, Twc, mid)
        ok = (z > NEAR) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= CAM.width - 0.5)
        ok &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= CAM.height - 0.5)
        idx = np.flatnonzero(ok)
        ok[idx[occluded(scene, Twc[:3, 3], mid[idx], quads_in_view(scene.quad_corners, CAM, Twc))]] = False
        count += ok
    assert count.max() > 0 and (count == 0).any()  # the test sees some and misses some
    assert np.mean(count == vis.frames) >= BRUTE_AGREEMENT


# ---- through evaluate ---------------------------------------------------------------------------


def write_recording(folder: Path, segs: np.ndarray, T_wc: np.ndarray) -> Path:
    """A recording folder: camera.json and gt/ (trajectory, segments, axes); no scene.json."""
    gt = folder / "gt"
    gt.mkdir(parents=True)
    traj = Trajectory(np.arange(len(T_wc)) / 30.0, T_wc, "gt")
    write_tum(gt / "trajectory.tum", traj)
    rows = [" ".join(f"{v:.17g}" for v in s.ravel()) + " -1" for s in segs]
    (gt / "segments.txt").write_text("\n".join(rows) + "\n")
    (folder / "camera.json").write_text(json.dumps(CAM.to_dict()))
    return folder


def line_map(T_wc: np.ndarray, segs: np.ndarray) -> Map:
    m = len(segs)
    lines = Lines(
        np.arange(m),
        np.asarray(segs, float),
        np.zeros((m, 0)),
        np.full(m, LineState.ORTHONORMAL, np.int8),
        np.full(m, -1),
        np.full(m, np.nan),
        np.zeros((0, 2), np.int64),
        np.zeros((0, 4)),
    )
    n = len(T_wc)
    kf = Keyframes(np.arange(n), np.arange(n), np.arange(n) / 30.0, T_wc.copy())
    return Map(CAM, kf, lines=lines)


def test_recall_against_the_visible_ground_truth_is_the_hand_value(tmp_path):
    """GT: the first five segments (no occluders without scene.json), length 13, seen (>= 5 frames) 8.
    Map: the first segment, the seen half of the fourth and the fifth (seen in 2 frames only).
    recall_visible = (2 + 2) / 8; recall = (2 + 2 + 2 + tau) / 13 (the map's half of the fourth
    segment also covers tau of its unseen half); precision 1."""
    T = poses()
    gt = SEGMENTS[:5]
    folder = write_recording(tmp_path / "rec", gt, T)
    est = np.array([gt[0], [[2, -2, 4], [4, -2, 4]], gt[4]])
    tum = tmp_path / "est.tum"
    write_tum(tum, Trajectory(np.arange(len(T)) / 30.0, T, "est"))
    res = evaluate(folder, line_map(T, est), tum)
    assert res.gt_line_length == pytest.approx(13.0, abs=EXACT)
    assert res.gt_visible_length == pytest.approx(8.0, abs=2 * LENGTH_TOL)
    assert res.gt_visible_fraction == pytest.approx(8.0 / 13.0, abs=2 * LENGTH_TOL / 13)
    assert "occlusion not tested" in " ".join(res.notes)
    spacing = EvalConfig().sample_spacing_rel * min(res.line_thresholds.values())
    for key, tau in res.line_thresholds.items():
        assert res.line_recall_visible[key] == pytest.approx(0.5, abs=2 * spacing / 8)
        assert res.line_recall[key] == pytest.approx((6 + tau) / 13, abs=2 * spacing / 13)
        assert res.line_precision[key] == pytest.approx(1.0, abs=EXACT)
    assert "of visible GT" in res.table()
    assert set(res.to_dict()["line_recall_visible"]) == set(res.line_recall)
    # two frames are enough: the fifth segment counts as seen, and the map has it
    res2 = evaluate(folder, line_map(T, est), tum, EvalConfig(line_visible_min_frames=2))
    assert res2.gt_visible_length == pytest.approx(10.0, abs=2 * LENGTH_TOL)
    for key in res2.line_thresholds:
        assert res2.line_recall_visible[key] == pytest.approx(0.6, abs=2 * spacing / 10)


def test_no_camera_means_no_visible_recall_and_a_note(tmp_path):
    T = poses()
    folder = write_recording(tmp_path / "rec", SEGMENTS[:2], T)
    (folder / "camera.json").unlink()
    res = evaluate(folder, line_map(T, SEGMENTS[:2]), None)
    assert res.line_recall_visible == {} and res.gt_visible_fraction is None
    assert any("no camera.json" in n for n in res.notes)
    assert res.line_recall  # the full-GT metrics stay


def test_bad_min_frames_is_a_config_error():
    from papl_mapper.errors import ConfigError

    with pytest.raises(ConfigError, match="line_visible_min_frames"):
        EvalConfig(line_visible_min_frames=0).check()


def test_demo_ground_truth_seen_share(tmp_path):
    """The bundled demo scores its own ground truth: recall 1 against all and against the visible part."""
    folder = Path(__file__).resolve().parents[1] / "samples" / "demo"
    if not (folder / "gt" / "map.papl").is_file():
        pytest.skip("samples/demo absent")
    gt_map = Map.load(folder / "gt" / "map.papl")
    res = evaluate(folder, gt_map, folder / "gt" / "trajectory.tum")
    assert res.line_visibility.startswith("GT seen in >= 5")
    assert "quads" in res.line_visibility  # the scene's quads were used as occluders
    assert 0.3 < res.gt_visible_fraction < 0.7  # a one-way walk sees about half of the ring corridor
    for key in res.line_thresholds:
        assert res.line_recall_visible[key] == pytest.approx(1.0, abs=EXACT)


def test_report_shows_recall_of_the_seen_ground_truth_beside_recall(tmp_path):
    from papl_mapper.gui.report import ReportOptions, build_report_html

    T = poses()
    folder = write_recording(tmp_path / "rec", SEGMENTS[:5], T)
    est = np.array([SEGMENTS[0], [[2, -2, 4], [4, -2, 4]], SEGMENTS[4]])
    text = build_report_html(line_map(T, est), gt_dir=folder, options=ReportOptions(previews=False))
    i_recall = text.index("line recall @ 1%")
    i_seen = text.index("line recall of the seen GT @ 1%")
    i_prec = text.index("line precision @ 1%")
    assert i_recall < i_seen < i_prec
    assert "0.5" in text[i_seen:i_prec]  # the hand value, (2 + 2) / 8
    assert "share of the GT line length seen in &gt;= 5 frames" in text


def test_only_the_frames_of_the_evaluated_time_span_count(tmp_path):
    """An estimate of the first 8 frames only: the turned frames are outside its span, so the fifth
    segment is not seen even when 2 frames suffice (seen length 8 instead of 10)."""
    T = poses()
    folder = write_recording(tmp_path / "rec", SEGMENTS[:5], T)
    tum = tmp_path / "est.tum"
    write_tum(tum, Trajectory(np.arange(N_FORWARD) / 30.0, T[:N_FORWARD], "est"))
    res = evaluate(folder, line_map(T, SEGMENTS[:1]), tum, EvalConfig(line_visible_min_frames=2))
    assert res.n_matched_poses == N_FORWARD
    assert res.gt_visible_length == pytest.approx(8.0, abs=2 * LENGTH_TOL)
    assert f"of {N_FORWARD} GT frames" in res.line_visibility


def test_recall_of_the_seen_ground_truth_with_offset_lines(tmp_path):
    """Map lines parallel to the seen GT at known distances: the first 0.05 off (within every tau), the
    second 0.2 off (within tau at 1% and 2% only: taus 0.129, 0.259, 0.518 here), the seen half of the
    fourth 1.0 off (within none). Seen length 8: recall_visible 2/8, 6/8, 6/8."""
    T = poses()
    folder = write_recording(tmp_path / "rec", SEGMENTS[:5], T)
    up = np.array([0.0, 1.0, 0.0])
    est = np.array([SEGMENTS[0] + 0.05 * up, SEGMENTS[1] + 0.2 * up, [[2, -1, 4], [4, -1, 4]]])
    tum = tmp_path / "est.tum"
    write_tum(tum, Trajectory(np.arange(len(T)) / 30.0, T, "est"))
    res = evaluate(folder, line_map(T, est), tum)
    taus = np.array(list(res.line_thresholds.values()))
    assert (taus[0] < 0.2 < taus[1]) and taus[2] < 1.0
    spacing = EvalConfig().sample_spacing_rel * taus.min()
    want = dict(zip(res.line_thresholds, (2 / 8, 6 / 8, 6 / 8), strict=True))
    for key, value in want.items():
        assert res.line_recall_visible[key] == pytest.approx(value, abs=2 * spacing / 8)
