"""A tracking segment the map cannot be joined with is mapped on its own and written beside the map."""

from __future__ import annotations

import json

import numpy as np

from papl_mapper.pipelines.checkpoint import StageStore
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.run import _silent, _Timer, build_map, frame_trajectory, register, segment_maps
from papl_mapper.pipelines.run_outputs import write_extras, write_outputs
from papl_mapper.pipelines.summary import RecordingInfo, RunSummary
from tests.test_mapping_incremental import _umeyama_sim3, make_tracks

CUT = 25  # the recording's tracks all restart here: nothing links the frames before to those after


def _cut_recording():
    tracks, T_cw, _ = make_tracks(n_frames=60, noise_px=0.3)
    tracks.point_track[tracks.point_frame >= CUT] += 100_000  # the same points, new tracks
    return tracks, T_cw


def test_a_segment_left_out_gets_its_own_map_trajectory_and_folder(tmp_path):
    tracks, T_cw = _cut_recording()
    cfg = RunConfig()
    timer = _Timer()
    reg = register(tracks, cfg, timer, _silent, StageStore.off())
    assert reg.segments_left_out == [(0, CUT - 1)]  # the later, longer segment is the map
    m, _ = build_map(tracks, reg, cfg, timer, _silent, StageStore.off())
    traj = frame_trajectory(tracks, m, cfg)
    ids = tracks.point_track.copy()
    segments = segment_maps(tracks, reg, cfg, timer, _silent)
    assert np.array_equal(tracks.point_track, ids)  # the map's track ids are as they were
    assert len(segments) == 1
    seg = segments[0]
    assert (seg.first, seg.last) == (0, CUT - 1)
    assert seg.folder == f"segments/000000-{CUT - 1:06d}"
    # every frame of the segment posed in its own frame: right up to a similarity
    frames = np.rint(seg.trajectory.timestamps * 10.0).astype(int)  # make_tracks: 10 frames a second
    assert frames.tolist() == list(range(CUT))
    est = seg.trajectory.T_wc[:, :3, 3]
    gt = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_cw[:CUT]])
    s, R, t = _umeyama_sim3(est, gt)
    err = np.linalg.norm((s * (R @ est.T)).T + t - gt, axis=1)
    assert err.max() < 0.02 * np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()
    assert not set(np.rint(traj.timestamps * 10.0).astype(int)) & set(range(CUT))  # not in the map's

    summary = RunSummary(
        recording=RecordingInfo("cut", "0", len(tracks)),
        frontend={},
        segment_maps=[seg.summary()],
    )
    write_outputs(tmp_path, m, traj, cfg, summary, segments)
    folder = tmp_path / seg.folder
    assert sorted(p.name for p in folder.iterdir()) == ["keyframes.tum", "map.papl", "trajectory.tum"]
    listed = json.loads((tmp_path / "manifest.json").read_text())["files"]
    assert {f"{seg.folder}/{n}" for n in ("map.papl", "trajectory.tum", "keyframes.tum")} <= set(listed)
    written = json.loads((tmp_path / "summary.json").read_text())["segment_maps"]
    assert written == [{**seg.summary(), "frames_posed": CUT}]
    # an export asked for is written for the segment too, in its folder, and listed
    cfg.output.export = ["ply"]
    extras = write_extras(tmp_path, m, cfg, _silent, segments)
    assert {tmp_path / "map.ply", folder / "map.ply"} <= set(extras.exports)
    assert f"{seg.folder}/map.ply" in json.loads((tmp_path / "manifest.json").read_text())["files"]


def test_a_segment_whose_stages_fail_is_named_and_the_map_kept(monkeypatch, caplog):
    """A segment's own map is extra: when its stages fail, one warning names it, and the track ids are
    put back for the map's trajectory."""
    import papl_mapper.pipelines.run as run_mod

    tracks, _ = _cut_recording()
    cfg = RunConfig()
    reg = register(tracks, cfg, _Timer(), _silent, StageStore.off())
    ids = tracks.point_track.copy()

    def broken(*args, **kwargs):
        tracks.point_track[:5] = -1  # as a completion would rename tracks before failing
        raise ValueError("singular matrix")

    monkeypatch.setattr(run_mod, "build_map", broken)
    with caplog.at_level("WARNING", logger="papl_mapper.pipelines.run"):
        assert segment_maps(tracks, reg, cfg, _Timer(), _silent) == []
    assert np.array_equal(tracks.point_track, ids)
    (record,) = [r for r in caplog.records if r.name == "papl_mapper.pipelines.run"]
    expected = f"tracking segment of frames 0-{CUT - 1}: no map of its own (singular matrix)"
    assert record.getMessage() == expected
