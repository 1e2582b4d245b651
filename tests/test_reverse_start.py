"""The recording registered backwards as a second start for the global BA (mapping/reverse_start.py)."""

from __future__ import annotations

import numpy as np

from papl_mapper.backend import BAConfig, global_ba
from papl_mapper.geometry.se3 import invert, so3_exp
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.geometry.triangulation import triangulate_points
from papl_mapper.mapping.assemble import assemble_map
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.mapping.reverse_start import backward_poses, reverse_checked
from tests.test_mapping_incremental import make_tracks

FRAMES = np.arange(0, 30, 2)  # the map's keyframes (frame rows)


def _recording():
    tracks, T_cw, _ = make_tracks(n_frames=30, noise_px=0.3)
    return tracks, invert(T_cw)


def _bent(T_wc: np.ndarray, deg: float, scale: float) -> np.ndarray:
    """Poses whose second half is turned by `deg` about the vertical and scaled about the middle one."""
    T = T_wc.copy()
    k = len(T) // 2
    c = T[k, :3, 3].copy()
    R = so3_exp(np.radians([0.0, 0.0, deg]))
    for i in range(k + 1, len(T)):
        T[i, :3, :3] = R @ T[i, :3, :3]
        T[i, :3, 3] = c + scale * (R @ (T[i, :3, 3] - c))
    return T


def _adjusted_map(tracks, T_wc: np.ndarray):
    """The points map of FRAMES at poses T_wc (points triangulated where they can be), after its BA."""
    sel = np.isin(tracks.point_frame, FRAMES)
    ids, row = np.unique(tracks.point_track[sel], return_inverse=True)
    X, ok = triangulate_points(
        row,
        T_wc[np.searchsorted(FRAMES, tracks.point_frame[sel])],
        tracks.camera.K,
        tracks.point_uv[sel],
        len(ids),
    )
    points = {int(t): x for t, x, good in zip(ids, X, ok, strict=True) if good}
    m = assemble_map(
        tracks, {int(f): T for f, T in zip(FRAMES, T_wc, strict=True)}, points, LineEstimates.empty()
    )
    return global_ba(m, BAConfig(max_iterations=30)).map


def _centre_error(T_wc: np.ndarray, truth: np.ndarray) -> float:
    s = umeyama(T_wc[:, :3, 3], truth[:, :3, 3])
    return float(np.abs(s.apply(T_wc[:, :3, 3]) - truth[:, :3, 3]).max())


def test_reversed_tracks_play_the_recording_backwards() -> None:
    tracks, _ = _recording()
    n = len(tracks)
    rev = tracks.reversed()
    rev.validate()
    assert np.all(np.diff(rev.point_frame) >= 0)  # in frame order, as the frontend writes them
    assert rev.timestamp[0] == 0.0 and np.all(np.diff(rev.timestamp) > 0)
    assert np.array_equal(rev.frame_index, tracks.frame_index[::-1])
    for f in (0, 7, n - 1):
        ids, uv = tracks.points_in(f)
        ids_r, uv_r = rev.points_in(n - 1 - f)
        assert np.array_equal(ids, ids_r) and np.array_equal(uv, uv_r)
    back = rev.reversed()
    for name in ("point_frame", "point_track", "point_uv", "timestamp", "is_keyframe"):
        assert np.allclose(getattr(back, name), getattr(tracks, name)), name
    rev.point_track[:] = -1
    assert tracks.point_track.min() >= 0  # a copy: the original's track ids stay


def test_reversed_tracks_keep_each_descriptor_on_its_observation() -> None:
    """Keyframe descriptors index observation rows: after the rows are re-sorted, each descriptor still
    belongs to the observation (frame, track) it described."""
    import dataclasses

    tracks, _ = _recording()
    rng = np.random.default_rng(3)
    rows = np.sort(rng.choice(len(tracks.point_frame), 300, replace=False))
    desc = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    tracks = dataclasses.replace(tracks, point_desc_row=rows, point_desc=desc)
    n = len(tracks)
    rev = tracks.reversed()
    assert np.all(np.diff(rev.point_desc_row) > 0)
    before = {
        (int(tracks.point_frame[r]), int(tracks.point_track[r])): d.tobytes()
        for r, d in zip(rows, desc, strict=True)
    }
    after = {
        (n - 1 - int(rev.point_frame[r]), int(rev.point_track[r])): d.tobytes()
        for r, d in zip(rev.point_desc_row, rev.point_desc, strict=True)
    }
    assert after == before


def test_backward_poses_are_returned_by_forward_frame_row() -> None:
    tracks, truth = _recording()
    n = len(tracks)

    def register(rev):
        assert len(rev) == n
        return Registration(frames=[0, 3], T_cw={0: invert(truth[n - 1]), 3: invert(truth[n - 4])})

    poses = backward_poses(tracks.reversed(), register)
    assert sorted(poses) == [n - 4, n - 1]
    assert np.allclose(poses[n - 1], truth[n - 1]) and np.allclose(poses[n - 4], truth[n - 4])


def test_a_backward_registration_that_fails_gives_no_poses() -> None:
    from papl_mapper.errors import UnmappableError

    tracks, _ = _recording()

    def register(rev):
        raise UnmappableError("could not initialise from 3 keyframes: too little parallax")

    assert backward_poses(tracks.reversed(), register) == {}


def test_a_map_in_a_wrong_basin_is_replaced_by_the_backward_start() -> None:
    """The forward map's second half turned 90 degrees and halved: its own BA keeps it there (the points
    it could triangulate hold it); the backward poses (the truth, in another frame and scale) fit every
    observation of the tracks, and the map from them is kept."""
    tracks, truth = _recording()
    m = _adjusted_map(tracks, _bent(truth[FRAMES], 90.0, 0.5))
    assert _centre_error(m.keyframes.T_wc, truth[FRAMES]) > 0.3
    other_frame = _bent(truth, 0.0, 1.0)
    other_frame[:, :3, 3] *= 3.0  # the backward registration has a scale and a frame of its own
    out, check = reverse_checked(m, tracks, dict(enumerate(other_frame)), BAConfig(max_iterations=30), 4.0)
    assert check.kept == "backward" and check.posed_backward == len(FRAMES)
    assert check.cost_backward < check.cost_forward and check.z < -3.0
    assert _centre_error(out.keyframes.T_wc, truth[FRAMES]) < 0.01
    assert np.array_equal(out.keyframes.ids, m.keyframes.ids) and out.metadata == m.metadata


def test_starts_that_reach_one_basin_keep_the_forward_map() -> None:
    tracks, truth = _recording()
    m = _adjusted_map(tracks, truth[FRAMES])
    rng = np.random.default_rng(1)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (len(truth), 3))
    out, check = reverse_checked(m, tracks, dict(enumerate(noisy)), BAConfig(max_iterations=30), 4.0)
    assert out is m and check.kept == "forward"
    assert abs(check.z) < 3.0


def test_a_backward_map_without_every_keyframe_is_not_judged() -> None:
    tracks, truth = _recording()
    m = _adjusted_map(tracks, truth[FRAMES])
    partial = {f: truth[f] for f in range(20)}  # the backward registration lost the last frames
    out, check = reverse_checked(m, tracks, partial, BAConfig(), 4.0)
    assert out is m and check.kept == "forward" and check.cost_backward is None
    assert check.posed_backward == int(np.sum(FRAMES < 20))
