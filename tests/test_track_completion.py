"""Track merging, completion and retriangulation on tracks projected from a known scene.

Each physical point's track is cut in two at a frame (as a KLT break does); with the true poses,
completion must rename the second piece to the first, never join pieces of different points or
put one track twice in a frame, and triangulate unmapped tracks at the true points.
"""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.mapping.assemble import assemble_map
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.mapping.track_completion import CompletionConfig, complete_tracks
from papl_mapper.tracks import Tracks

from .test_mapping_incremental import make_tracks

CUT = 1_000_000  # id offset of the second piece of a cut track


def _scene(noise_px: float = 0.3, seed: int = 0):
    """Tracks of a known walk with true poses and points, descriptors at every observation."""
    tracks, T_cw, pts = make_tracks(n_frames=40, noise_px=noise_px, seed=seed)
    rng = np.random.default_rng(seed + 1)
    point_desc = rng.integers(0, 256, (len(pts), 32), dtype=np.uint8)
    # a few flipped bits per observation: the same corner seen again, not the same bytes
    flips = rng.random((len(tracks.point_track), 32, 8)) < 0.02
    noise = np.packbits(flips, axis=2)[:, :, 0]
    tracks.point_desc_row = np.arange(len(tracks.point_track))
    tracks.point_desc = point_desc[tracks.point_track] ^ noise
    T_wc = {f: np.linalg.inv(T) for f, T in enumerate(T_cw)}
    return tracks, T_wc, pts


def _cut(tracks: Tracks, frame: int, ids: np.ndarray) -> np.ndarray:
    """Cut the tracks of `ids` seen before and from `frame`: the later piece gets id + CUT; returns them."""
    before = np.unique(tracks.point_track[tracks.point_frame < frame])
    after = np.unique(tracks.point_track[tracks.point_frame >= frame])
    cut = np.intersect1d(np.intersect1d(before, after), ids)
    tracks.point_track[np.isin(tracks.point_track, cut) & (tracks.point_frame >= frame)] += CUT
    return cut


def _map(tracks: Tracks, T_wc: dict, points_w: dict):
    return assemble_map(tracks, T_wc, points_w, LineEstimates.empty())


def _seen_twice_in_a_frame(tracks: Tracks) -> bool:
    pairs = np.column_stack([tracks.point_track, tracks.point_frame])
    return len(np.unique(pairs, axis=0)) < len(pairs)


@pytest.mark.parametrize("mapped_second_piece", [True, False])
def test_cut_tracks_are_joined_to_their_point(mapped_second_piece):
    tracks, T_wc, pts = _scene()
    ids = np.unique(tracks.point_track)
    cut = _cut(tracks, 20, ids[::2])
    assert len(cut) > 50
    points_w = {int(t): pts[t] for t in ids}
    if mapped_second_piece:
        points_w.update({int(t) + CUT: pts[t] for t in cut})
    truth = tracks.point_track % CUT
    joined, stats = complete_tracks(
        tracks, _map(tracks, T_wc, points_w), CompletionConfig(retriangulate=False)
    )
    # every cut piece is renamed to its own point, and nothing to another point
    assert np.array_equal(tracks.point_track, truth)
    if mapped_second_piece:
        assert (stats.merged, stats.completed) == (len(cut), 0)
        assert not any(int(t) + CUT in joined for t in cut)
    else:
        assert (stats.merged, stats.completed) == (0, len(cut))
    assert stats.observations_added == int(((tracks.point_frame >= 20) & np.isin(truth, cut)).sum())
    assert not _seen_twice_in_a_frame(tracks)


def test_pieces_whose_descriptors_disagree_stay_apart():
    tracks, T_wc, pts = _scene()
    ids = np.unique(tracks.point_track)
    cut = _cut(tracks, 20, ids[::2])
    later = tracks.point_track >= CUT
    tracks.point_desc[later] = np.random.default_rng(5).integers(0, 256, (int(later.sum()), 32), np.uint8)
    before = tracks.point_track.copy()
    points_w = {int(t): pts[t] for t in ids} | {int(t) + CUT: pts[t] for t in cut}
    _, stats = complete_tracks(tracks, _map(tracks, T_wc, points_w), CompletionConfig(retriangulate=False))
    assert stats.merged == 0 and np.array_equal(tracks.point_track, before)


def test_a_look_alike_far_from_the_projection_is_not_joined():
    """Geometry gates first: a cut piece moved 10 px (another corner) is left alone."""
    tracks, T_wc, pts = _scene(noise_px=0.0)
    ids = np.unique(tracks.point_track)
    cut = _cut(tracks, 20, ids[::2])
    tracks.point_uv[tracks.point_track >= CUT] += 10.0
    points_w = {int(t): pts[t] for t in ids}
    _, stats = complete_tracks(tracks, _map(tracks, T_wc, points_w), CompletionConfig(retriangulate=False))
    assert stats.merged + stats.completed == 0
    assert len(cut) > 0


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_unmapped_tracks_are_triangulated_where_they_are(noise_px):
    tracks, T_wc, pts = _scene(noise_px=noise_px)
    ids = np.unique(tracks.point_track)
    mapped, unmapped = ids[::3], np.setdiff1d(ids, ids[::3])
    # one observation of a few unmapped tracks is an outlier: those must not enter the map
    bad = unmapped[:20]
    order = np.argsort(tracks.point_track, kind="stable")
    tracks.point_uv[order[np.searchsorted(tracks.point_track[order], bad)]] += 25.0
    points_w = {int(t): pts[t] for t in mapped}
    out, stats = complete_tracks(tracks, _map(tracks, T_wc, points_w), CompletionConfig())
    new = np.array(sorted(set(out) - set(points_w)), np.int64)
    assert len(new) == stats.retriangulated
    assert stats.retriangulated > 0.8 * (len(unmapped) - len(bad))
    assert not np.isin(bad, new).any()
    err = np.linalg.norm(np.stack([out[int(t)] for t in new]) - pts[new], axis=1)
    assert np.median(err) < (1e-9 if noise_px == 0 else 0.02)


def test_the_one_pass_projection_screen_matches_the_test_pair_by_pair():
    """`_projects_near` decides for every candidate pair at once what the completion loop's projection
    test decides for one pair: point p in front of and near every keyframe observation of track b."""
    from papl_mapper.geometry.se3 import project_points
    from papl_mapper.mapping.track_completion import _candidates, _projects_near
    from papl_mapper.tracks import PointRows

    tracks, T_wc, pts = _scene(noise_px=0.5)
    ids = np.unique(tracks.point_track)
    cut = _cut(tracks, 20, ids[::2])
    points_w = {int(t): pts[t] for t in ids}
    points_w.update({int(t) + CUT: pts[t] + 0.3 for t in cut[::3]})  # some far off: they fail the test
    m = _map(tracks, T_wc, points_w)
    cfg = CompletionConfig()
    T_kf = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    pairs = _candidates(tracks, m, T_kf, cfg)
    pairs.append((int(ids[0]), 10**9))  # a track with no observation at all: not near
    rows_index = PointRows(tracks)
    in_kf = np.isin(tracks.point_frame, m.keyframes.ids)
    near = _projects_near(tracks, rows_index, in_kf, T_kf, points_w, pairs, cfg.max_error_px)
    expected = []
    for p, b in pairs:
        rows = rows_index.rows(np.array([b]))
        rows = rows[in_kf[rows]]
        if len(rows) == 0 or p not in points_w:
            expected.append(False)
            continue
        uv, z = project_points(
            tracks.camera.K, np.stack([T_kf[int(f)] for f in tracks.point_frame[rows]]), points_w[p]
        )
        expected.append(
            bool(
                (z > 0).all() and np.linalg.norm(uv - tracks.point_uv[rows], axis=1).max() <= cfg.max_error_px
            )
        )
    assert near.tolist() == expected
    assert 0 < sum(expected) < len(expected)
