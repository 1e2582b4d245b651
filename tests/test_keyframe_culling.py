"""Redundant keyframe culling on hand-built registrations with a known answer, and after real registration."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.errors import ConfigError
from papl_mapper.map import Camera
from papl_mapper.mapping.culling import CullConfig, CullStats, cull_keyframes
from papl_mapper.mapping.incremental import Registration, register_keyframes
from papl_mapper.tracks import Tracks
from tests.test_mapping_incremental import _umeyama_sim3, make_tracks

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
MAX_REL_POSITION_ERR = {0.0: 1e-6, 0.5: 0.015}  # of the path length after Sim(3), by image noise (px)
MAX_POSE_CHANGE = 1e-12  # a culled keyframe's pose is moved, not re-estimated


def _T_cw(centre: np.ndarray) -> np.ndarray:
    """Camera at `centre` looking along world +Z (identity rotation)."""
    T = np.eye(4)
    T[:3, 3] = -centre
    return T


def _scene(
    centres: np.ndarray,
    visible: np.ndarray,
    lines: dict[int, list[int]] | None = None,
    is_keyframe: np.ndarray | None = None,
) -> tuple[Tracks, Registration]:
    """Frames at `centres` (F, 3) looking along +Z at points on the plane z = 0..; `visible` (F, P) says
    which point each frame sees; `lines` maps a line track to the frames that see it. Every frame is
    registered, the `is_keyframe` ones (default all) as keyframes; the first two are the initial pair."""
    rng = np.random.default_rng(0)
    F, P = visible.shape
    X = np.column_stack([rng.uniform(-2, 2, P), rng.uniform(-1.5, 1.5, P), np.full(P, 30.0)])
    pf, pt, puv = [], [], []
    for f in range(F):
        idx = np.flatnonzero(visible[f])
        Xc = X[idx] - centres[f]
        uv = Xc @ CAM.K.T
        pf.append(np.full(len(idx), f))
        pt.append(idx)
        puv.append(uv[:, :2] / uv[:, 2:3])
    lf, lt = [], []
    for t, fs in (lines or {}).items():
        lf += fs
        lt += [t] * len(fs)
    is_kf = np.ones(F, bool) if is_keyframe is None else is_keyframe
    tracks = Tracks(
        CAM,
        np.arange(F),
        np.arange(F) / 30.0,
        is_kf,
        np.concatenate(pf),
        np.concatenate(pt),
        np.concatenate(puv),
        np.array(lf, np.int64),
        np.array(lt, np.int64),
        np.tile([100.0, 100.0, 200.0, 100.0], (len(lf), 1)),
        np.full(len(lf), -1, np.int64),
        np.full((F, 3, 3), np.nan),
    )
    tracks.validate()
    kf = np.flatnonzero(is_kf)
    reg = Registration(
        frames=kf.tolist(),
        T_cw={int(f): _T_cw(centres[f]) for f in kf},
        points_w={p: X[p] for p in range(P)},
        T_cw_frames={f: _T_cw(centres[f]) for f in range(F) if not is_kf[f]},
        init_frames=(int(kf[0]), int(kf[1])),
    )
    return tracks, reg


def _sideways(n: int) -> np.ndarray:
    return np.column_stack([np.linspace(0.0, 1.0, n), np.zeros(n), np.zeros(n)])


def test_all_seeing_the_same_points_leaves_first_pair_and_last():
    tracks, reg = _scene(_sideways(10), np.ones((10, 60), bool))
    stats = CullStats()
    out = cull_keyframes(tracks, reg, CullConfig(), stats)
    assert out.frames == [0, 1, 9]
    assert stats.culled == list(range(2, 9))
    assert stats.keyframes_before == 10 and stats.keyframes_after == 3
    for f in range(2, 9):  # a culled keyframe stays registered as a frame, with the same pose
        assert f not in out.T_cw
        assert np.abs(out.T_cw_frames[f] - reg.T_cw[f]).max() < MAX_POSE_CHANGE
    assert set(out.T_cw) | set(out.T_cw_frames) == set(range(10))
    assert out.points_w.keys() == reg.points_w.keys()
    assert reg.frames == list(range(10)) and len(reg.T_cw) == 10  # the input is left unchanged
    assert out.init_frames == reg.init_frames


def test_fewer_than_three_other_views_is_not_redundant():
    # 5 keyframes: each of slots 2..3 has exactly 4 other views, the last culling leaves 3
    tracks, reg = _scene(_sideways(5), np.ones((5, 40), bool))
    out = cull_keyframes(tracks, reg, CullConfig(min_other_views=4))
    assert out.frames == [0, 1, 3, 4]  # 2 is culled (4 others), then 3 has only 3 others left
    out = cull_keyframes(tracks, reg, CullConfig(min_other_views=5))
    assert out.frames == [0, 1, 2, 3, 4]


def test_redundant_fraction_threshold():
    # keyframe 2 sees 10 points nobody else sees, besides 90 shared ones: 90% redundant
    vis = np.zeros((6, 100), bool)
    vis[:, :90] = True
    vis[2, 90:] = True
    tracks, reg = _scene(_sideways(6), vis)
    assert 2 not in cull_keyframes(tracks, reg, CullConfig(redundant_fraction=0.9)).frames
    assert 2 in cull_keyframes(tracks, reg, CullConfig(redundant_fraction=0.91)).frames


def test_coarser_views_do_not_count():
    # the initial pair and the last keyframe are far (z = -20), keyframes 2..4 close to the points (z = 25)
    centres = np.zeros((6, 3))
    centres[:, 0] = np.linspace(0, 0.5, 6)
    centres[2:5, 2] = 25.0
    tracks, reg = _scene(centres, np.ones((6, 50), bool))
    # seen from 30 (far) vs 5 (close): only the two other close keyframes are at the same scale
    assert cull_keyframes(tracks, reg, CullConfig()).frames == [0, 1, 2, 3, 4, 5]
    # with a factor over 6 the far views count as the same scale, and all close ones are redundant
    assert cull_keyframes(tracks, reg, CullConfig(scale_factor=6.5)).frames == [0, 1, 5]
    # the far keyframes see finer: ... and the close ones see coarser
    centres[2:5, 2] = -20.0
    centres[[0, 1, 5], 2] = 25.0
    tracks, reg = _scene(centres, np.ones((6, 50), bool))
    assert cull_keyframes(tracks, reg, CullConfig()).frames == [0, 1, 5]


def test_points_behind_a_keyframe_are_not_counted():
    centres = _sideways(6)
    centres[3, 2] = 40.0  # keyframe 3 is beyond the points: it sees none of them in front
    tracks, reg = _scene(centres, np.ones((6, 50), bool))
    stats = CullStats()
    out = cull_keyframes(tracks, reg, CullConfig(), stats)
    # 3 has no mapped point in front, so nothing holds it and it goes; 2 stays because its neighbours
    # 1 and 3 share no point at the time it is visited
    assert out.frames == [0, 1, 2, 5]
    assert stats.kept_for == {"protected": 1, "shared_points": 1}


def test_lines_keep_their_keyframes():
    # line 7 is seen by keyframes 4 and 6 (and the frames 3, 5 that are not keyframes)
    is_kf = np.array([1, 1, 1, 0, 1, 0, 1, 1, 1], bool)
    lines = {7: [3, 4, 5, 6], 8: [2]}  # line 8: one frame only, too short a track to hold anything
    tracks, reg = _scene(_sideways(9), np.ones((9, 50), bool), lines, is_kf)
    stats = CullStats()
    out = cull_keyframes(tracks, reg, CullConfig(line_min_frames=4), stats)
    assert 4 in out.frames and 6 in out.frames
    assert 2 not in out.frames
    assert stats.kept_for == {"protected": 1, "lines": 2}
    # a line seen by 3 keyframes keeps 2 of them: one of its keyframes may go
    lines = {7: [3, 4, 5, 6, 7]}
    tracks, reg = _scene(_sideways(9), np.ones((9, 50), bool), lines, is_kf)
    out = cull_keyframes(tracks, reg, CullConfig(line_min_frames=4))
    assert sum(f in out.frames for f in (4, 6, 7)) == 2
    # the line needs 5 registered frames to count: with 6 it holds, and without a floor it never does
    assert cull_keyframes(tracks, reg, CullConfig(line_min_frames=6)).frames == [0, 1, 8]
    assert cull_keyframes(tracks, reg, CullConfig(min_line_views=0, line_min_frames=1)).frames == [0, 1, 8]


def test_keyframes_that_bridge_disjoint_views_stay():
    # points 0..39 are seen by frames 0..4, points 40..79 by frames 4..8: only keyframe 4 sees both
    vis = np.zeros((9, 80), bool)
    vis[:5, :40] = True
    vis[4:, 40:] = True
    tracks, reg = _scene(_sideways(9), vis)
    stats = CullStats()
    out = cull_keyframes(tracks, reg, CullConfig(min_other_views=2), stats)
    assert out.frames == [0, 1, 4, 8]
    assert stats.kept_for == {"protected": 1, "shared_points": 1}
    # with no shared-point floor the bridge goes, and the two halves of the map share no keyframe
    out = cull_keyframes(tracks, reg, CullConfig(min_other_views=2, min_shared_points=0))
    assert out.frames == [0, 1, 7, 8]


def test_gap_limit():
    tracks, reg = _scene(_sideways(10), np.ones((10, 60), bool))
    out = cull_keyframes(tracks, reg, CullConfig(max_gap_frames=3))
    assert np.diff(out.frames).max() <= 3
    assert out.frames[:2] == [0, 1] and out.frames[-1] == 9


def test_disabled_and_tiny_registrations_are_copies():
    tracks, reg = _scene(_sideways(10), np.ones((10, 60), bool))
    out = cull_keyframes(tracks, reg, CullConfig(enabled=False))
    assert out.frames == reg.frames and out.T_cw.keys() == reg.T_cw.keys()
    assert out is not reg and out.T_cw is not reg.T_cw
    tracks, reg = _scene(_sideways(2), np.ones((2, 60), bool))
    assert cull_keyframes(tracks, reg).frames == [0, 1]


@pytest.mark.parametrize(
    "kw",
    [
        {"redundant_fraction": 0.0},
        {"redundant_fraction": 1.5},
        {"min_other_views": 0},
        {"scale_factor": 0.9},
        {"min_line_views": -1},
        {"max_gap_frames": -2},
    ],
)
def test_bad_config_raises(kw):
    with pytest.raises(ConfigError, match="cull"):
        CullConfig(**kw)


def _rel_position_error(T_cw: dict[int, np.ndarray], T_cw_gt: np.ndarray) -> float:
    frames = sorted(T_cw)
    est = np.array([np.linalg.inv(T_cw[f])[:3, 3] for f in frames])
    gt = np.array([np.linalg.inv(T_cw_gt[f])[:3, 3] for f in frames])
    s, R, t = _umeyama_sim3(est, gt)
    err = np.linalg.norm(s * est @ R.T + t - gt, axis=1)
    return float(np.sqrt(np.mean(err**2)) / np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_culls_a_dense_registration_and_global_ba_keeps_the_trajectory(noise_px):
    """60 frames, all keyframes: culling removes most of them; BA on the rest still fits the truth."""
    from papl_mapper.backend import BAConfig, global_ba
    from papl_mapper.mapping.assemble import assemble_map
    from papl_mapper.mapping.lines import LineEstimates

    tracks, T_cw_gt, _ = make_tracks(noise_px=noise_px)
    reg = register_keyframes(tracks)
    stats = CullStats()
    out = cull_keyframes(tracks, reg, CullConfig(), stats)
    assert len(out.frames) < 0.25 * len(reg.frames)  # 60 -> 8 here
    assert min(out.frames) == min(reg.frames) and set(reg.init_frames) <= set(out.frames)
    assert set(out.T_cw) | set(out.T_cw_frames) == set(reg.T_cw) | set(reg.T_cw_frames)
    m = assemble_map(
        tracks, {f: np.linalg.inv(T) for f, T in out.T_cw.items()}, out.points_w, LineEstimates.empty()
    )
    res = global_ba(m, BAConfig())
    kf = res.map.keyframes
    T_cw = {int(k): np.linalg.inv(T) for k, T in zip(kf.ids, kf.T_wc, strict=True)}
    assert len(T_cw) == len(out.frames)
    assert _rel_position_error(T_cw, T_cw_gt) < MAX_REL_POSITION_ERR[noise_px]
