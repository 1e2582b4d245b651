"""Revisit detection and loop closure on a synthetic loop with known drift and known correspondences."""

from __future__ import annotations

import numpy as np

from papl_mapper.map import Camera
from papl_mapper.mapping.point_store import PointStore
from papl_mapper.mapping.revisit import RevisitConfig, RevisitGate, TrackIndex, close_loop, find_revisit
from papl_mapper.tracks import Tracks

LOOP = 120  # frames per loop (3 deg per frame)
FRAMES = LOOP + 40
KEYFRAME_EVERY = 5
QUERY = LOOP + 20  # a keyframe of the second lap
DRIFT_M_PER_LOOP = np.array([0.4, -0.2, 0.1])
DRIFT_DEG_PER_LOOP = 4.0
MAX_POSE_ERR_AFTER_M = 0.05  # the drift at the query is about 0.5 m
NEW_ID = 100_000
DRIFT_FROM = 60


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _true_T_cw(f: int) -> np.ndarray:
    """Camera on a circle of radius 2 looking outward, x along the tangent, y down."""
    th = 2 * np.pi * f / LOOP
    z = np.array([np.cos(th), np.sin(th), 0.0])
    y = np.array([0.0, 0.0, -1.0])
    R_wc = np.stack([np.cross(y, z), y, z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ (2.0 * z)
    return T


def _drift(f: int) -> np.ndarray:
    """World-frame drift of the map as tracked at frame f (none over the first half lap, then growing
    up to the query, then steady: the keyframes after the query share its correction)."""
    a = max(0, min(f, QUERY) - DRIFT_FROM) / LOOP
    D = np.eye(4)
    D[:3, :3] = _yaw(a * DRIFT_DEG_PER_LOOP)
    D[:3, 3] = a * DRIFT_M_PER_LOOP
    return D


def _build(scramble: bool = False, last_keyframe: int = QUERY):
    rng = np.random.default_rng(0)
    n = 800
    phi = rng.uniform(0, 2 * np.pi, n)
    X = np.stack([6 * np.cos(phi), 6 * np.sin(phi), rng.uniform(-1.5, 1.5, n)], axis=1)
    base_desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    cam = Camera(640, 480, 400.0, 400.0, 320.0, 240.0)
    K = cam.K
    rows_f, rows_t, rows_uv, desc_rows, descs = [], [], [], [], []
    live: dict[int, tuple[int, int]] = {}
    point_of: dict[int, int] = {}
    first_frame: dict[int, int] = {}
    next_id = {"old": 0, "new": NEW_ID}
    for f in range(FRAMES):
        T = _true_T_cw(f)
        Xc = X @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
        vis = (Xc[:, 2] > 0.5) & (uv[:, 0] > 5) & (uv[:, 0] < 635) & (uv[:, 1] > 5) & (uv[:, 1] < 475)
        for p in np.flatnonzero(vis).tolist():
            tid, last = live.get(p, (-1, -10))
            if last != f - 1:  # a new pass by the point starts a new track
                key = "old" if f < LOOP else "new"
                tid = next_id[key]
                next_id[key] += 1
                point_of[tid], first_frame[tid] = p, f
            live[p] = (tid, f)
            rows_f.append(f)
            rows_t.append(tid)
            rows_uv.append(uv[p] + rng.normal(0, 0.5, 2))
            if f % KEYFRAME_EVERY == 0:
                d = base_desc[p].copy()
                d[rng.integers(0, 32, 3)] ^= np.uint8(1 << int(rng.integers(0, 8)))
                if scramble and f >= LOOP:
                    d = rng.integers(0, 256, 32, dtype=np.uint8)
                desc_rows.append(len(rows_f) - 1)
                descs.append(d)
    tracks = Tracks(
        camera=cam,
        frame_index=np.arange(FRAMES),
        timestamp=np.arange(FRAMES) / 30.0,
        is_keyframe=np.arange(FRAMES) % KEYFRAME_EVERY == 0,
        point_frame=np.array(rows_f, np.int64),
        point_track=np.array(rows_t, np.int64),
        point_uv=np.array(rows_uv),
        line_frame=np.zeros(0, np.int64),
        line_track=np.zeros(0, np.int64),
        line_xy=np.zeros((0, 4)),
        line_vp=np.zeros(0, np.int64),
        vp_dirs_c=np.full((FRAMES, 3, 3), np.nan),
        point_desc_row=np.array(desc_rows, np.int64),
        point_desc=np.array(descs, np.uint8),
    )
    kfs = list(range(0, last_keyframe + 1, KEYFRAME_EVERY))
    T_cw = {f: _true_T_cw(f) @ _drift(f) for f in kfs}
    # each point as mapped when it was first seen: in the drifted world of that frame
    points_w = PointStore()
    for t, f in first_frame.items():
        if f <= QUERY:
            D_inv = np.linalg.inv(_drift(f))
            points_w[t] = D_inv[:3, :3] @ X[point_of[t]] + D_inv[:3, 3]
    return tracks, T_cw, points_w, point_of


def _pose_err(T_cw: np.ndarray, f: int) -> float:
    c = -T_cw[:3, :3].T @ T_cw[:3, 3]
    T = _true_T_cw(f)
    return float(np.linalg.norm(c - (-T[:3, :3].T @ T[:3, 3])))


def test_revisit_found_with_true_correspondences_and_loop_closed():
    tracks, T_cw, points_w, point_of = _build()
    index = TrackIndex.build(tracks)
    cfg = RevisitConfig()
    rv = find_revisit(tracks, points_w, T_cw, QUERY, index, cfg)
    assert rv is not None and len(rv.pairs) >= cfg.min_inliers
    assert all(point_of[n] == point_of[o] for n, o in rv.pairs.tolist())
    assert rv.old_frame < DRIFT_FROM
    err_before = _pose_err(T_cw[QUERY], QUERY)
    mid = 100
    mid_before = _pose_err(T_cw[mid], mid)
    assert err_before > 0.2
    frames_before = tracks.point_frame.copy()
    fused = close_loop(tracks, points_w, T_cw, {}, rv, index)
    assert fused == len(rv.pairs)
    assert _pose_err(T_cw[QUERY], QUERY) < MAX_POSE_ERR_AFTER_M
    assert _pose_err(T_cw[mid], mid) < 0.5 * mid_before
    assert _pose_err(T_cw[0], 0) < 1e-9  # frames before the old visit do not move
    new_ids = set(rv.pairs[:, 0].tolist())
    assert not new_ids & set(tracks.point_track.tolist())
    assert not new_ids & set(points_w)
    np.testing.assert_array_equal(tracks.point_frame, frames_before)
    # a fused track continues the old one: it spans both visits
    old = int(rv.pairs[0, 1])
    frames = tracks.point_frame[tracks.point_track == old]
    assert frames.min() < DRIFT_FROM and frames.max() > LOOP


def test_no_revisit_without_matching_descriptors():
    tracks, T_cw, points_w, _ = _build(scramble=True)
    assert find_revisit(tracks, points_w, T_cw, QUERY, TrackIndex.build(tracks), RevisitConfig()) is None


def _revisits_after_query(cfg: RevisitConfig, count: int = 3, parallax_deg: float = 10.0):
    """Revisits at `count` consecutive keyframes from the query; old points triangulated at `parallax_deg`."""
    tracks, T_cw, points_w, _ = _build(last_keyframe=QUERY + KEYFRAME_EVERY * (count - 1))
    index = TrackIndex.build(tracks)
    frames = [QUERY + KEYFRAME_EVERY * i for i in range(count)]
    angles = dict.fromkeys(points_w, parallax_deg)
    return [find_revisit(tracks, points_w, T_cw, f, index, cfg, 0, angles) for f in frames]


def test_large_correction_closes_only_when_consecutive_keyframes_agree():
    cfg = RevisitConfig(max_drift=0.01, confirm_keyframes=2)  # the query's 0.5 m is "large" here
    rvs = _revisits_after_query(cfg)
    assert all(rv is not None and rv.drift > cfg.max_drift * rv.path for rv in rvs)
    gate = RevisitGate(cfg)
    assert [gate.admit(rv) for rv in rvs] == [False, False, True]
    # the correction that closes the loop puts the keyframe where the truth is
    R, t, s = rvs[-1].correction()
    c = -rvs[-1].tracked_T_cw[:3, :3].T @ rvs[-1].tracked_T_cw[:3, 3]
    T = _true_T_cw(rvs[-1].frame)
    assert np.linalg.norm(s * R @ c + t - (-T[:3, :3].T @ T[:3, 3])) < MAX_POSE_ERR_AFTER_M
    # a keyframe without a revisit breaks the streak
    gate = RevisitGate(cfg)
    assert [gate.admit(rv) for rv in (rvs[0], None, rvs[1], rvs[2])] == [False, False, False, False]
    # refused outright when confirmation is off
    off = RevisitGate(RevisitConfig(max_drift=0.01, confirm_keyframes=0))
    assert not any(off.admit(rv) for rv in rvs)
    # within max_drift a single keyframe closes the loop
    assert RevisitGate(RevisitConfig()).admit(rvs[0])


def test_large_correction_from_starved_old_points_is_refused():
    """Old points triangulated at a turn's starved parallax: agreeing corrections are not enough."""
    cfg = RevisitConfig(max_drift=0.01, confirm_keyframes=2)
    rvs = _revisits_after_query(cfg, parallax_deg=0.6)
    assert all(rv is not None and rv.old_parallax_deg == 0.6 for rv in rvs)
    gate = RevisitGate(cfg)
    assert [gate.admit(rv) for rv in rvs] == [False, False, False]
    # a small correction does not depend on them
    assert RevisitGate(RevisitConfig()).admit(rvs[0])


def test_disagreeing_large_corrections_are_refused():
    """A look-alike place: the middle keyframe's old points put it 0.3 m elsewhere."""
    cfg = RevisitConfig(max_drift=0.01, confirm_keyframes=2)
    rvs = _revisits_after_query(cfg, count=4)
    shifted = rvs[1].T_cw.copy()
    shifted[:3, 3] -= shifted[:3, :3] @ np.array([0.3, 0.0, 0.0])  # the camera centre moves 0.3 m
    rvs[1].T_cw = shifted
    gate = RevisitGate(cfg)
    assert [gate.admit(rv) for rv in rvs] == [False, False, False, False]


def test_recent_tracks_are_not_a_revisit():
    tracks, T_cw, points_w, _ = _build()
    cfg = RevisitConfig(min_gap_frames=QUERY)  # nothing ended long enough ago
    assert find_revisit(tracks, points_w, T_cw, QUERY, TrackIndex.build(tracks), cfg) is None
