"""Incremental registration on tracks projected from a known scene: poses match up to Sim(3)."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.map import Camera
from papl_mapper.mapping.incremental import IncrementalConfig, register_keyframes
from papl_mapper.tracks import Tracks

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
MAX_REL_POSITION_ERR = 0.02  # of the path length, after Sim(3) alignment


def _look_T_cw(centre: np.ndarray, yaw: float) -> np.ndarray:
    """Camera at `centre` looking along yaw in the world XY plane, world +Z up."""
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, fwd)
    R_wc = np.column_stack([right, down, fwd])
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ centre
    return T


def make_tracks(n_frames=60, noise_px=0.0, seed=0):
    """A room of random points, a camera walking and turning slowly: every frame a keyframe."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000), rng.uniform(-1.5, 1.5, 3000)])
    pts = pts[np.abs(pts[:, :2]).max(axis=1) > 3.0]  # points on the outer part of the room
    t = np.arange(n_frames) / n_frames
    centres = np.column_stack([1.5 * np.cos(2 * t), 1.5 * np.sin(2 * t), 0.05 * np.sin(9 * t)])
    yaws = 2 * t + 0.3
    T_cw = np.stack([_look_T_cw(c, y) for c, y in zip(centres, yaws, strict=True)])
    return project_tracks(pts, T_cw, rng, noise_px, fps=10.0), T_cw, pts


def project_tracks(pts, T_cw, rng, noise_px, fps, track_of=None):
    """Point tracks of `pts` seen by cameras T_cw (every frame a keyframe, `fps` frames a second): each
    point visible in front of a camera, at its projection plus `noise_px` of noise drawn from `rng`.
    A point's track id is its index, or `track_of(frame, indices)` where tracks end and restart."""
    pf, pt, puv = [], [], []
    for f, T in enumerate(T_cw):
        Xc = pts @ T[:3, :3].T + T[:3, 3]
        uv = Xc @ CAM.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        vis = (Xc[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        idx = np.flatnonzero(vis)
        pf.append(np.full(len(idx), f))
        pt.append(idx if track_of is None else track_of(f, idx))
        puv.append(uv[idx] + rng.normal(0, noise_px, (len(idx), 2)))
    n = len(T_cw)
    return Tracks(
        CAM,
        np.arange(n),
        np.arange(n) / fps,
        np.ones(n, bool),
        np.concatenate(pf),
        np.concatenate(pt),
        np.concatenate(puv),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4)),
        np.zeros(0, np.int64),
        np.full((n, 3, 3), np.nan),
    )


def _umeyama_sim3(src, dst):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    S, D = src - mu_s, dst - mu_d
    U, sig, Vt = np.linalg.svd(D.T @ S / len(src))
    E = np.eye(3)
    E[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ E @ Vt
    s = np.trace(np.diag(sig) @ E) / S.var(0).sum()
    return s, R, mu_d - s * R @ mu_s


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_registers_all_keyframes(noise_px):
    tracks, T_cw, _ = make_tracks(noise_px=noise_px)
    reg = register_keyframes(tracks)
    assert not reg.lost
    assert len(reg.frames) == len(tracks)
    est = np.stack([-reg.T_cw[f][:3, :3].T @ reg.T_cw[f][:3, 3] for f in range(len(tracks))])
    gt = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_cw])
    s, R, t = _umeyama_sim3(est, gt)
    err = np.linalg.norm((s * est @ R.T + t) - gt, axis=1)
    path = np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()
    assert np.sqrt(np.mean(err**2)) < MAX_REL_POSITION_ERR * path


def test_static_camera_cannot_initialise():
    from papl_mapper.errors import InputError

    tracks, _, _ = make_tracks(n_frames=10)
    first = tracks.point_frame == 0
    uv0 = dict(zip(tracks.point_track[first].tolist(), tracks.point_uv[first], strict=True))
    keep = np.isin(tracks.point_track, list(uv0))
    tracks.point_frame, tracks.point_track = tracks.point_frame[keep], tracks.point_track[keep]
    tracks.point_uv = np.stack([uv0[t] for t in tracks.point_track.tolist()])  # nothing moves
    with pytest.raises(InputError, match="could not initialise"):
        register_keyframes(tracks)


def test_tracks_save_load_round_trip(tmp_path):
    tracks, _, _ = make_tracks(n_frames=5)
    tracks.vertical_vp = np.zeros(5, np.int64)
    path = tracks.save(tmp_path / "tracks.npz")
    back = Tracks.load(path)
    assert back.camera.to_dict() == tracks.camera.to_dict()
    for name in ("frame_index", "point_uv", "point_track", "vp_dirs_c", "vertical_vp", "line_xy"):
        assert np.array_equal(getattr(back, name), getattr(tracks, name), equal_nan=True)
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a tracks file"):
        Tracks.load(tmp_path / "other.npz")


def test_segments_merge_on_matching_descriptors():
    """Two tracking segments see the same points under different track ids; keyframe ORB descriptors
    pair them up and the second segment is brought into the first's frame by their Sim(3)."""
    from papl_mapper.geometry.se3 import so3_exp
    from papl_mapper.mapping.incremental import IncrementalConfig, Registration, _merge_segments
    from papl_mapper.mapping.revisit import TrackIndex

    rng = np.random.default_rng(5)
    X = rng.uniform(-3, 3, (60, 3)) + [0, 0, 8]
    R, t, s = so3_exp(np.array([0.1, -0.3, 0.2])), np.array([1.0, -2.0, 0.5]), 0.7
    a = Registration(frames=list(range(10)), T_cw={f: np.eye(4) for f in range(10)})
    b = Registration(frames=list(range(10, 15)), T_cw={f: np.eye(4) for f in range(10, 15)})
    a.points_w = {i: X[i] for i in range(60)}
    b.points_w = {100 + i: (X[i] - t) @ R / s for i in range(40)}  # y = s R x + t maps b into a
    b.points_w.update({200 + i: rng.normal(size=3) for i in range(10)})  # unmatched clutter
    desc = rng.integers(0, 256, (60, 32), dtype=np.uint8)
    ids = np.r_[np.arange(60), 100 + np.arange(40)]
    n = len(ids)
    tracks = Tracks(
        CAM,
        np.arange(15),
        np.arange(15) / 10.0,
        np.ones(15, bool),
        np.r_[np.zeros(60, int), np.full(40, 10)],
        ids,
        rng.uniform(0, 400, (n, 2)),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4)),
        np.zeros(0, np.int64),
        np.full((15, 3, 3), np.nan),
        point_desc_row=np.arange(n),
        point_desc=np.r_[desc, desc[:40]],
    )
    T_b = np.eye(4)
    T_b[:3, 3] = [0.3, 0.0, 0.1]
    b.T_cw[12] = T_b
    merged = _merge_segments([a, b], IncrementalConfig(), TrackIndex.build(tracks))
    assert merged is a and 12 in a.T_cw
    # the camera of frame 12 sees a's point 0 where it saw b's point 100, up to the scale s
    x_b = b.T_cw[12][:3, :3] @ b.points_w[100] + b.T_cw[12][:3, 3]
    x_a = a.T_cw[12][:3, :3] @ a.points_w[0] + a.T_cw[12][:3, 3]
    assert np.allclose(x_a, s * x_b, atol=1e-6)


def test_segments_join_each_other_and_the_group_posing_most_frames_is_the_map():
    """After a blind stretch two segments share tracks with each other but none with the map before it:
    they join by their Sim(3) and, together posing more frames than the first, become the map."""
    from papl_mapper.geometry.se3 import so3_exp
    from papl_mapper.mapping.incremental import IncrementalConfig, Registration, _merge_segments
    from papl_mapper.mapping.revisit import TrackIndex

    rng = np.random.default_rng(7)
    X = rng.uniform(-3, 3, (40, 3)) + [0, 0, 8]
    R, t, s = so3_exp(np.array([0.2, 0.1, -0.3])), np.array([0.5, 1.0, -1.0]), 1.6

    def segment(frames: range, points: dict[int, np.ndarray]) -> Registration:
        reg = Registration(frames=list(frames), T_cw={f: np.eye(4) for f in frames})
        reg.points_w = points
        return reg

    first = segment(range(0, 50), {1000 + i: rng.normal(size=3) for i in range(30)})
    second = segment(range(60, 90), {i: X[i] for i in range(40)})
    third = segment(range(90, 120), {i: (X[i] - t) @ R / s for i in range(20, 40)})  # s R x + t -> second
    third.points_w.update({500 + i: rng.normal(size=3) for i in range(5)})
    tracks = Tracks(
        CAM,
        np.arange(120),
        np.arange(120) / 10.0,
        np.ones(120, bool),
        np.zeros(1, np.int64),
        np.zeros(1, np.int64),
        np.zeros((1, 2)),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4)),
        np.zeros(0, np.int64),
        np.full((120, 3, 3), np.nan),
    )
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.1, 0.4]
    third.T_cw[100] = T
    merged = _merge_segments([first, second, third], IncrementalConfig(), TrackIndex.build(tracks))
    assert merged is second
    assert sorted(merged.T_cw) == list(range(60, 120))
    assert not set(range(50)) & set(merged.T_cw)
    assert merged.segments_left_out == [(0, 49)]  # named in summary.json and the partial-map warning
    assert merged.left_out == [first]  # mapped on its own
    # frame 100 sees the same point in both frames, up to the scale s
    x3 = third.T_cw[100][:3, :3] @ third.points_w[25] + third.T_cw[100][:3, 3]
    x2 = merged.T_cw[100][:3, :3] @ merged.points_w[25] + merged.T_cw[100][:3, 3]
    assert np.allclose(x2, s * x3, atol=1e-6)
    assert np.allclose(merged.points_w[500], s * R @ third.points_w[500] + t)


def _shared_frame_segments(seed: int, depth_noise: float):
    """A segment (frames 0-39) and one tracked back into its last frames (34-79), the second in its own
    world frame by a known Sim(3); the second segment's points carry multiplicative depth errors."""
    from papl_mapper.geometry.se3 import so3_exp
    from papl_mapper.mapping.incremental import Registration

    tracks, T_cw, pts = make_tracks(80, seed=seed)
    rng = np.random.default_rng(seed)
    R, t, s = so3_exp(np.array([0.3, -0.2, 0.4])), np.array([2.0, -1.0, 0.5]), 0.6  # base = s R seg + t
    base = Registration(frames=list(range(40)), T_cw={f: T_cw[f] for f in range(40)})
    seg = Registration(frames=list(range(34, 80)))
    for f in range(34, 80):  # a world point x of seg is s R x + t in base's
        T = np.eye(4)
        T[:3, :3] = T_cw[f][:3, :3] @ R
        T[:3, 3] = (T_cw[f][:3, :3] @ t + T_cw[f][:3, 3]) / s
        seg.T_cw[f] = T
    seen = np.unique(tracks.points_in(36)[0])
    base.points_w = {int(i): pts[i] for i in seen}
    for i in seen:  # the segment's depths along its rays from frame 36 are off by up to depth_noise
        c = -T_cw[36][:3, :3].T @ T_cw[36][:3, 3]
        X = c + (pts[i] - c) * (1.0 + rng.uniform(-depth_noise, depth_noise))
        seg.points_w[int(i)] = (X - t) @ R / s
    return tracks, base, seg, (R, t, s)


def test_segments_join_on_the_frames_both_posed_where_points_disagree():
    """Points triangulated in a turn carry poor depths, so no Sim(3) of them agrees; the frames both
    segments posed give the rotation and translation, the points' median depth ratio the scale."""
    from papl_mapper.mapping.incremental import IncrementalConfig, _merge_segments, _sim3_from_shared_frames
    from papl_mapper.mapping.revisit import TrackIndex

    tracks, base, seg, (R, t, s) = _shared_frame_segments(3, 0.4)
    cfg = IncrementalConfig()
    sim = _sim3_from_shared_frames(base, seg, cfg)
    assert sim is not None and sim.method == "shared frames"
    assert np.allclose(sim.R, R, atol=1e-9)
    assert abs(sim.scale / s - 1.0) < 0.05
    assert np.linalg.norm(sim.t - t) < 0.05 * np.linalg.norm(t)
    merged = _merge_segments([base, seg], cfg, TrackIndex.build(tracks))
    assert merged is seg and sorted({**merged.T_cw}) == list(range(80))
    # exact depths: exact Sim(3)
    _, base, seg, (R, t, s) = _shared_frame_segments(3, 0.0)
    sim = _sim3_from_shared_frames(base, seg, cfg)
    assert np.allclose(sim.R, R, atol=1e-9) and np.isclose(sim.scale, s) and np.allclose(sim.t, t, atol=1e-9)


def test_segments_are_not_joined_on_frames_whose_poses_disagree():
    from papl_mapper.geometry.se3 import so3_exp
    from papl_mapper.mapping.incremental import IncrementalConfig, _sim3_from_shared_frames

    _, base, seg, _ = _shared_frame_segments(3, 0.0)
    seg.T_cw[37][:3, :3] = so3_exp(np.array([0.0, np.radians(5.0), 0.0])) @ seg.T_cw[37][:3, :3]
    assert _sim3_from_shared_frames(base, seg, IncrementalConfig()) is None
    _, base, seg, _ = _shared_frame_segments(3, 0.0)
    for f in range(34, 38):  # two shared frames (38, 39) are too few
        del base.T_cw[f]
    assert _sim3_from_shared_frames(base, seg, IncrementalConfig()) is None


def test_frames_after_the_last_registered_one_get_a_segment_of_their_own():
    """A cut three frames before the end (fewer than `max_lost_frames`): the first segment cannot
    register those frames, and they are mapped as a segment of their own instead of never being tried
    (they share nothing with the map, so it is named as left out)."""
    tracks, _, _ = make_tracks(n_frames=40)
    after = tracks.point_frame >= 37
    tracks.point_track[after] += 100_000  # the same points, new tracks: nothing links them to before
    reg = register_keyframes(tracks)
    assert set(range(37)) <= set(reg.poses())
    assert reg.segments_left_out == [(37, 39)]
    assert reg.lost == [37, 38, 39]


def test_a_frame_out_of_order_is_registered_against_the_whole_map():
    """Photos out of order: the walk's last view comes eleventh. The pass in frame order finds none of
    its points mapped yet; tried again once the walk has mapped its place, it is posed there as a
    keyframe (and with the retry off it stays lost)."""
    _, T_cw, pts = make_tracks(n_frames=60)
    order = [*range(10), 59, *range(10, 59)]
    tracks = project_tracks(pts, T_cw[order], np.random.default_rng(1), 0.5, fps=10.0)
    assert 10 in register_keyframes(tracks, IncrementalConfig(retry_lost=False)).lost
    reg = register_keyframes(tracks)
    assert not reg.lost
    assert 10 in reg.T_cw
    est = np.stack([-reg.T_cw[f][:3, :3].T @ reg.T_cw[f][:3, 3] for f in range(len(tracks))])
    gt = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_cw[order]])
    s, R, t = _umeyama_sim3(est, gt)
    err = np.linalg.norm((s * (R @ est.T)).T + t - gt, axis=1)
    path = np.linalg.norm(np.diff(gt[np.argsort(order)], axis=0), axis=1).sum()
    assert err[10] < MAX_REL_POSITION_ERR * path
    assert err.max() < MAX_REL_POSITION_ERR * path
