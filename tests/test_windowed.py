"""Registration's bookkeeping at scale: track-grouped observation rows, the windowed BA's small map
and the keyframe rule, each against the straightforward computation it replaces."""

from __future__ import annotations

import numpy as np

from papl_mapper.backend import BAConfig, local_ba
from papl_mapper.mapping.assemble import assemble_map, cull_observations
from papl_mapper.mapping.incremental import IncrementalConfig, register_keyframes
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.mapping.windowed import WindowedRefiner
from papl_mapper.tracks import PointRows
from tests.test_mapping_incremental import make_tracks

EXACT = 1e-9  # the same computation on the same numbers


def test_point_rows_match_a_scan_and_follow_renamed_tracks():
    tracks, _, _ = make_tracks(n_frames=20)
    rng = np.random.default_rng(1)
    ids = np.unique(np.r_[rng.choice(tracks.point_track, 50), -7, 10**9])  # two ids nobody has
    rows = PointRows(tracks).rows(ids)
    assert np.array_equal(rows, np.flatnonzero(np.isin(tracks.point_track, ids)))
    tracks.point_track[tracks.point_track == ids[1]] = ids[2]  # a loop closure fuses two tracks
    assert np.array_equal(PointRows(tracks).rows(ids[2:3]), np.flatnonzero(tracks.point_track == ids[2]))


def test_point_rows_renamed_in_place_match_rows_grouped_again():
    tracks, _, _ = make_tracks(n_frames=20)
    rows = PointRows(tracks)
    rng = np.random.default_rng(2)
    ids = np.unique(tracks.point_track)
    for _ in range(3):  # three loop closures, each fusing a few tracks into others
        picked = rng.choice(np.unique(tracks.point_track), 12, replace=False)
        pairs = np.stack([picked[:6], picked[6:]], axis=1)
        new_of = dict(pairs.tolist())
        tracks.point_track[:] = [new_of.get(t, t) for t in tracks.point_track.tolist()]
        rows.rename(pairs)
        fresh = PointRows(tracks)
        for t in ids.tolist():
            assert np.array_equal(rows.rows(np.array([t])), fresh.rows(np.array([t])))
        assert np.array_equal(rows.rows(ids), fresh.rows(ids))


def test_points_in_matches_a_scan_in_and_out_of_frame_order():
    tracks, _, _ = make_tracks(n_frames=12)
    for f in (0, 5, 11, 12):
        sel = tracks.point_frame == f
        ids, uv = tracks.points_in(f)
        assert np.array_equal(ids, tracks.point_track[sel]) and np.array_equal(uv, tracks.point_uv[sel])
    order = np.random.default_rng(0).permutation(len(tracks.point_frame))  # not in frame order
    tracks.point_frame, tracks.point_track = tracks.point_frame[order], tracks.point_track[order]
    tracks.point_uv = tracks.point_uv[order]
    ids, _ = tracks.points_in(5)
    assert np.array_equal(ids, tracks.point_track[tracks.point_frame == 5])


def test_WindowedRefiner_equals_local_ba_on_the_whole_map():
    tracks, _, _ = make_tracks(n_frames=40, noise_px=0.7, seed=3)
    reg = register_keyframes(tracks, IncrementalConfig())
    ba, window = BAConfig(), 8
    # reference: the whole registration assembled, culled and adjusted in the same window
    T_wc = {f: np.linalg.inv(reg.T_cw[f]) for f in reg.frames}
    m = assemble_map(tracks, T_wc, reg.points_w, LineEstimates.empty())
    cull_observations(m, 4.0, 4.0, ba.min_views)
    frames = sorted(reg.frames)
    ref = local_ba(m, np.array(frames[len(frames) - window :]), ba).map
    WindowedRefiner(tracks, ba, window, 4.0)(reg)
    moved = 0
    for k, T in zip(ref.keyframes.ids, ref.keyframes.T_wc, strict=True):
        assert np.abs(np.linalg.inv(reg.T_cw[int(k)]) - T).max() < EXACT
    for p, x in zip(ref.points.ids, ref.points.xyz, strict=True):
        assert np.abs(reg.points_w[int(p)] - x).max() < EXACT
        moved += 1
    assert moved > 100


def test_keyframes_do_not_depend_on_how_many_mapped_points_are_outliers():
    """With 0.8 px noise a 1 px PnP threshold rejects about half the mapped points, a 3 px one almost
    none. The old rule (inliers under half the tracks) made most frames keyframes with the tight
    threshold; the rule counts mapped points, so both thresholds choose about as many keyframes."""
    chosen = []
    for threshold in (1.0, 3.0):
        tracks, _, _ = make_tracks(n_frames=40, noise_px=0.8, seed=4)
        tracks.is_keyframe[:] = False
        tracks.is_keyframe[::5] = True
        cfg = IncrementalConfig(keyframe_min_inliers=12)
        cfg.pnp.ransac_threshold_px = threshold
        reg = register_keyframes(tracks, cfg)
        assert len(reg.T_cw) + len(reg.T_cw_frames) == 40
        chosen.append(set(reg.frames))
    # the frontend's 8 and a few for tracks entering the view (the old rule: 40 with the tight threshold)
    assert len(chosen[0]) <= 8 + 7 and abs(len(chosen[0]) - len(chosen[1])) <= 2, chosen
