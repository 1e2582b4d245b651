"""Line tracks triangulated during registration (mapping/registration_lines.py) and their use in tracking."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from papl_mapper.geometry.lines import line_distance, line_parallax_deg, plucker_from_endpoints
from papl_mapper.geometry.se3 import retract, rotation_angle_deg
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Camera
from papl_mapper.mapping.incremental import IncrementalConfig, register_keyframes
from papl_mapper.mapping.lines import LineInitConfig
from papl_mapper.mapping.registration_lines import RegistrationLines, RegistrationLinesConfig
from papl_mapper.mapping.tracking import LinePoseConfig, PnPConfig, track_pnp
from papl_mapper.tracks import Tracks

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
K = CAM.K
AXES = np.eye(3)  # world x, y and z (up)

EXACT_LINE_TOL = 1e-6  # Pluecker distance (unit direction), noise-free
NOISY_LINE_TOL = 0.04  # world units: endpoints to the true line, ~6 units away, 0.5 px noise, 20 deg parallax
MAX_REL_POSITION_ERR = 0.02  # of the path length, after Sim(3) alignment


def _look_T_cw(centre: np.ndarray, yaw: float, pitch: float = 0.0) -> np.ndarray:
    """World-to-camera pose of a camera at `centre` looking along `yaw` in the XY plane (+Z up)."""
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(np.array([0.0, 0.0, -1.0]), fwd)
    right /= np.linalg.norm(right)
    R_wc = np.column_stack([right, np.cross(fwd, right), fwd])
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ centre
    return T


def _project(T_cw: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv = Xc @ K.T
    return uv[..., :2] / uv[..., 2:3], Xc[..., 2]


def _scene(
    n_frames: int = 12, noise_px: float = 0.0, seed: int = 0, n_texture: int = 0, baseline: float = 1.0
):
    """A wall 6 units ahead (x = 6) with axis-aligned segments (vertical and horizontal), floor lines
    running away from the camera, points on the wall, and a camera sliding 2.6 units sideways and
    towards it while looking at it (plenty of parallax; `baseline` scales the path). Texture segments
    are labelled -1 and run diagonally.
    Returns the tracks, the true T_cw (F, 4, 4), the segments (S, 2, 3) and which are texture (S,)."""
    rng = np.random.default_rng(seed)
    segs, lab = [], []
    for k in range(24):
        axis = (2, 1)[k % 2]  # vertical, along the wall
        mid = np.array([6.0, rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 1.0)])
        segs.append([mid - 0.5 * AXES[axis], mid + 0.5 * AXES[axis]])
        lab.append(axis)
    for y in (-1.0, 1.0):  # floor lines along the viewing direction
        segs.append([[5.0, y, -1.3], [5.8, y, -1.3]])
        lab.append(0)
    for _ in range(n_texture):
        mid = np.array([6.0, rng.uniform(-1.5, 1.5), rng.uniform(-0.8, 0.8)])
        d = np.array([0.0, 0.6, 0.8])
        segs.append([mid - 0.4 * d, mid + 0.4 * d])
        lab.append(-1)
    segs, lab = np.array(segs), np.array(lab)
    pts = np.column_stack([np.full(200, 6.0), rng.uniform(-3, 3, 200), rng.uniform(-1.4, 1.4, 200)])
    pts[::2, 0] += rng.uniform(-2.0, 0.0, 100)  # some depth spread
    t = np.linspace(0.0, 1.0, n_frames)
    centres = baseline * np.column_stack(
        [0.8 * t - 0.4 + 0.15 * np.sin(5 * t), 2.4 * t - 1.2, 0.5 * t - 0.25]
    )
    T_cw = np.stack([_look_T_cw(c, 0.1 * np.sin(4 * s), 0.05 * s) for c, s in zip(centres, t, strict=True)])
    pf, pt, puv, lf, lt, lxy, lvp = [], [], [], [], [], [], []
    for f, T in enumerate(T_cw):
        uv, z = _project(T, pts)
        seen = np.flatnonzero((z > 0) & (uv >= 0).all(1) & (uv[:, 0] < 640) & (uv[:, 1] < 480))
        pf.append(np.full(len(seen), f))
        pt.append(seen)
        puv.append(uv[seen] + rng.normal(0, noise_px, (len(seen), 2)))
        e, z = _project(T, segs)
        assert (z > 0).all() and (e >= 0).all() and (e[..., 0] < 640).all() and (e[..., 1] < 480).all()
        slide = rng.uniform(-0.1, 0.1, (len(segs), 2, 1))  # observed extents differ from view to view
        e = e + slide * (e[:, 1:2] - e[:, 0:1])
        lf.append(np.full(len(segs), f))
        lt.append(np.arange(len(segs)) + 1000)
        lxy.append(e.reshape(-1, 4) + rng.normal(0, noise_px, (len(segs), 4)))
        lvp.append(lab)
    n = n_frames
    vp = np.stack([AXES @ T[:3, :3].T for T in T_cw])  # (F, 3, 3) camera directions of the world axes
    tracks = Tracks(
        CAM,
        np.arange(n),
        np.arange(n) / 10.0,
        np.ones(n, bool),
        np.concatenate(pf),
        np.concatenate(pt),
        np.concatenate(puv),
        np.concatenate(lf),
        np.concatenate(lt),
        np.concatenate(lxy),
        np.concatenate(lvp),
        vp,
        vertical_vp=np.full(n, 2),
    )
    return tracks, T_cw, segs, lab < 0


def _lines_from(tracks: Tracks, T_cw: dict[int, np.ndarray], config=None) -> RegistrationLines:
    rl = RegistrationLines(tracks, config)
    for f in T_cw:
        rl.frame_lines(f, T_cw)
    return rl


def _parallax_deg(T_cw: np.ndarray, segs: np.ndarray) -> np.ndarray:
    """(S,) angle that the camera centres span about each true line (geometry.lines.line_parallax_deg)."""
    centres = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_cw])
    index = np.tile(np.arange(len(segs)), len(centres))
    L = plucker_from_endpoints(segs[:, 0], segs[:, 1])
    return line_parallax_deg(L, index, np.repeat(centres, len(segs), axis=0), len(segs))


def _point_line_distance(P: np.ndarray, seg: np.ndarray) -> np.ndarray:
    d = (seg[1] - seg[0]) / np.linalg.norm(seg[1] - seg[0])
    v = P - seg[0]
    return np.linalg.norm(v - np.outer(v @ d, d), axis=-1)


def test_lines_triangulated_from_keyframes_match_the_true_lines() -> None:
    tracks, T_true, segs, texture = _scene()
    rl = _lines_from(tracks, dict(enumerate(T_true)))
    ids, ends = rl.lines()
    # the tracks with enough parallax (5 degrees): both wall directions and the floor lines
    wide = _parallax_deg(T_true, segs) >= rl.cfg.triangulation.min_plane_angle_deg
    assert 15 <= wide.sum() < len(segs)
    np.testing.assert_array_equal(ids, np.flatnonzero(wide) + 1000)
    L_est = plucker_from_endpoints(ends[:, 0], ends[:, 1])
    L_true = plucker_from_endpoints(segs[wide, 0], segs[wide, 1])
    assert line_distance(L_est, L_true).max() < EXACT_LINE_TOL
    # what frame 3 is given: its own segments of those tracks with the world lines, in track order
    L, xy, tid = rl.frame_lines(3, dict(enumerate(T_true)))
    np.testing.assert_array_equal(tid, ids)
    np.testing.assert_allclose(xy, tracks.line_xy[tracks.line_frame == 3][wide])
    assert line_distance(L, L_true).max() < EXACT_LINE_TOL


def test_noisy_lines_and_texture_edges() -> None:
    tracks, T_true, segs, texture = _scene(noise_px=0.5, seed=1, n_texture=6)
    ids, ends = _lines_from(tracks, dict(enumerate(T_true))).lines()
    parallax = _parallax_deg(T_true, segs)
    assert not np.isin(np.flatnonzero(texture) + 1000, ids).any()  # the diagonal texture edges
    assert np.isin(np.flatnonzero(~texture & (parallax > 7.0)) + 1000, ids).all()
    assert np.isin(ids, np.flatnonzero(parallax > 3.0) + 1000).all()
    for t, e in zip(ids, ends, strict=True):  # the depth error of a line grows as 1 / parallax
        assert _point_line_distance(e, segs[t - 1000]).max() < NOISY_LINE_TOL * 20.0 / parallax[t - 1000]


def test_tracks_need_enough_keyframes_and_parallax() -> None:
    tracks, T_true, segs, _ = _scene()
    two = {0: T_true[0], 6: T_true[6]}
    assert len(_lines_from(tracks, two).lines()[0]) == 0  # min_views 3 keyframes
    three = {0: T_true[0], 6: T_true[6], 11: T_true[11]}
    assert len(_lines_from(tracks, three).lines()[0]) >= 15
    # a camera moving a hair (0.03 units over 12 views): too little parallax for any line
    tracks, T_true, segs, _ = _scene(baseline=0.01)
    cfg = RegistrationLinesConfig(triangulation=LineInitConfig(min_views=3, min_plane_angle_deg=1.0))
    assert len(_lines_from(tracks, dict(enumerate(T_true)), cfg).lines()[0]) == 0


def _moved(T_cw: np.ndarray, S: np.ndarray, s: float) -> np.ndarray:
    """The world-to-camera pose after the world moved by the similarity S (scale s)."""
    T = T_cw @ np.linalg.inv(S)
    T[:3] *= s
    return T


def test_lines_follow_moving_and_new_keyframes() -> None:
    tracks, T_true, segs, _ = _scene()
    T_cw = {f: T_true[f] for f in range(6)}
    rl = _lines_from(tracks, T_cw)
    n0 = rl.triangulated
    rl.frame_lines(7, T_cw)  # nothing changed: nothing is triangulated again
    assert rl.triangulated == n0
    # the windowed BA moves the keyframes (here: the whole map by a similarity): the lines follow
    s, R = 2.5, retract(np.eye(4), np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.0]))[:3, :3]
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = s * R, [1.0, -2.0, 0.5]
    for f in T_cw:  # camera coordinates scale with the world: T_cw' = s T_cw S^-1 (rows 0-2)
        T_cw[f] = _moved(T_true[f], S, s)
    L, _, tid = rl.frame_lines(7, T_cw)
    assert rl.triangulated > n0
    moved = segs[tid - 1000] @ (s * R).T + S[:3, 3]
    assert line_distance(L, plucker_from_endpoints(moved[:, 0], moved[:, 1])).max() < EXACT_LINE_TOL
    # a new keyframe: the tracks without a line are tried again at once, a line is made again once
    # the keyframes seeing it grew by `regrow` (6 -> 7 views: not yet; 8 >= 1.2 * 6: yes)
    n1, with_line = rl.triangulated, len(rl.lines()[0])
    T_cw[9] = _moved(T_true[9], S, s)
    rl.frame_lines(10, T_cw)
    assert rl.triangulated == n1 + len(segs) - with_line
    T_cw[8] = _moved(T_true[8], S, s)
    rl.frame_lines(10, T_cw)
    assert rl.triangulated == n1 + 2 * len(segs) - with_line
    every = _lines_from(tracks, {f: T_true[f] for f in range(6)}, RegistrationLinesConfig(regrow=1.0))
    n2 = every.triangulated
    every.frame_lines(10, {f: T_true[f] for f in (0, 1, 2, 3, 4, 5, 9)})
    assert every.triangulated == n2 + len(segs)


def test_few_points_and_good_lines_give_a_better_pose() -> None:
    """A frame whose few points bunch in one corner: the lines the keyframes triangulate hold its pose."""
    rot_without, rot_with, pos_without, pos_with = [], [], [], []
    for seed in range(8):
        tracks, T_true, segs, _ = _scene(n_frames=12, noise_px=0.5, seed=seed)
        keyframes = {f: T_true[f] for f in range(12) if f != 5}
        rl = RegistrationLines(tracks)
        L, xy, _ = rl.frame_lines(5, keyframes)
        assert len(L) >= 15
        rng = np.random.default_rng(100 + seed)
        pts = np.column_stack([np.full(20, 6.0), rng.uniform(-0.4, 0.4, 20), rng.uniform(-0.3, 0.3, 20)])
        uv, _ = _project(T_true[5], pts)
        uv += rng.normal(0, 0.7, uv.shape)
        guess = T_true[4]
        pnp = PnPConfig()
        plain = track_pnp(pts, uv, K, guess, pnp)
        lined = track_pnp(pts, uv, K, guess, rl.pnp_config(pnp), lines_w=L, line_xy=xy)
        assert plain.ok and lined.ok and lined.refine is not None and lined.refine.n_lines > 0.8 * len(L)
        for res, rot, pos in ((plain, rot_without, pos_without), (lined, rot_with, pos_with)):
            rot.append(rotation_angle_deg(res.T_cw[:3, :3], T_true[5][:3, :3]))
            c = -res.T_cw[:3, :3].T @ res.T_cw[:3, 3]
            pos.append(np.linalg.norm(c - (-T_true[5][:3, :3].T @ T_true[5][:3, 3])))
    assert np.median(rot_with) < 0.3 * np.median(rot_without)
    assert np.median(pos_with) < 0.3 * np.median(pos_without)


def test_gate_leaves_out_a_wrong_line() -> None:
    tracks, T_true, segs, _ = _scene()
    rl = RegistrationLines(tracks, RegistrationLinesConfig(gate_px=8.0))
    L, xy, _ = rl.frame_lines(5, {f: T_true[f] for f in range(12) if f != 5})
    xy = xy.copy()
    xy[0] = xy[1]  # the first track's segment is another line's in this frame
    X = np.column_stack([np.full(30, 6.0), np.linspace(-2, 2, 30), np.linspace(-1, 1, 30) ** 3])
    uv, _ = _project(T_true[5], X)
    res = track_pnp(X, uv, K, T_true[4], rl.pnp_config(PnPConfig()), lines_w=L, line_xy=xy)
    assert res.ok and res.refine.n_lines == len(L) - 1
    assert rotation_angle_deg(res.T_cw[:3, :3], T_true[5][:3, :3]) < 1e-5


def test_lines_only_below_the_inlier_count() -> None:
    tracks, T_true, _, _ = _scene()
    rl = RegistrationLines(tracks, RegistrationLinesConfig(below_inliers=50))
    L, xy, _ = rl.frame_lines(5, {f: T_true[f] for f in range(12) if f != 5})
    X = np.column_stack([np.full(60, 6.0), np.linspace(-2, 2, 60), np.sin(np.arange(60))])
    uv, _ = _project(T_true[5], X)
    pnp = rl.pnp_config(PnPConfig())
    assert track_pnp(X, uv, K, T_true[4], pnp, lines_w=L, line_xy=xy).refine is None
    res = track_pnp(X[:40], uv[:40], K, T_true[4], pnp, lines_w=L, line_xy=xy)
    assert res.refine is not None and res.refine.n_lines == len(L)


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_registration_with_lines(noise_px: float) -> None:
    tracks, T_true, _, _ = _scene(n_frames=20, noise_px=noise_px, seed=2)
    cfg = IncrementalConfig(track_lines=RegistrationLinesConfig(enabled=True))
    reg = register_keyframes(tracks, cfg)
    assert not reg.lost
    frames = sorted(set(reg.T_cw) | set(reg.T_cw_frames))
    assert frames == list(range(len(tracks)))
    poses = {**reg.T_cw_frames, **reg.T_cw}
    est = np.stack([-poses[f][:3, :3].T @ poses[f][:3, 3] for f in frames])
    gt = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_true])
    sim = umeyama(est, gt)
    err = np.linalg.norm(sim.apply(est) - gt, axis=1)
    path = np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()
    assert np.sqrt(np.mean(err**2)) < MAX_REL_POSITION_ERR * path


def _blank_stretch(tracks: Tracks, frames: range, keep: int) -> Tracks:
    """The tracks with every point of `frames` dropped but the `keep` lowest track ids (blank walls)."""
    drop = np.isin(tracks.point_frame, list(frames)) & (tracks.point_track >= keep)
    return dataclasses.replace(
        tracks,
        point_frame=tracks.point_frame[~drop],
        point_track=tracks.point_track[~drop],
        point_uv=tracks.point_uv[~drop],
    )


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_lines_pose_a_stretch_without_points(noise_px: float) -> None:
    tracks, T_true, _, _ = _scene(n_frames=24, noise_px=noise_px, seed=3)
    blank = range(12, 16)
    tracks = _blank_stretch(tracks, blank, keep=4)
    off = IncrementalConfig(pnp=PnPConfig(from_lines=LinePoseConfig(enabled=False)))
    assert set(blank) <= set(register_keyframes(tracks, off).lost)  # PnP needs more than 4 points
    reg = register_keyframes(tracks, IncrementalConfig())
    assert not reg.lost
    poses = {**reg.T_cw_frames, **reg.T_cw}
    est = np.stack([-poses[f][:3, :3].T @ poses[f][:3, 3] for f in range(len(tracks))])
    gt = np.stack([-T[:3, :3].T @ T[:3, 3] for T in T_true])
    sim = umeyama(est, gt)
    err = np.linalg.norm(sim.apply(est) - gt, axis=1)
    path = np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()
    assert err[list(blank)].max() < MAX_REL_POSITION_ERR * path
