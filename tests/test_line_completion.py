"""Segment track merging and completion on segments projected from known 3D lines.

A camera walks past vertical and horizontal lines on the walls of a room; each line's segment track
is cut in two at a frame (as a break of the point flow does). With the true poses, completion must
rename the second piece to the first, never join a piece to a neighbouring parallel line (one
10 cm away, which projects 5-20 px off) and never put two segments of one frame in a track.
"""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.mapping.assemble import assemble_map
from papl_mapper.mapping.line_completion import _lines_near_segments, complete_lines, segment_line_errors
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.tracks import Tracks

from .test_mapping_incremental import CAM, _look_T_cw

CUT = 1_000_000  # id offset of the second piece of a cut track
MAX_ERR_PX, MIN_OVERLAP, MAX_HAMMING, MIN_VIEWS = 1.0, 0.5, 70, 2


def _lines(rng: np.random.Generator) -> np.ndarray:
    """(M, 2, 3) vertical and horizontal segments on the walls x = +-5, y = +-5, each with a twin
    10 cm beside it (the look-alike a loose gate would join)."""
    out = []
    for wall in range(4):
        for k in range(10):
            s = rng.uniform(-3.5, 3.5)
            if k % 2:
                a, b = np.array([s, 5.0, -0.8]), np.array([s, 5.0, 0.8])
            else:
                z = rng.uniform(-0.8, 0.8)
                a, b = np.array([s - 0.6, 5.0, z]), np.array([s + 0.6, 5.0, z])
            R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
            R = np.linalg.matrix_power(R, wall)
            twin = np.array([0.1, 0, 0]) if k % 2 else np.array([0, 0, 0.1])
            out += [np.stack([R @ a, R @ b]), np.stack([R @ (a + twin), R @ (b + twin)])]
    return np.array(out)


def _scene(noise_px: float = 0.2, seed: int = 0):
    rng = np.random.default_rng(seed)
    ends = _lines(rng)
    n = 40
    t = np.arange(n) / n
    centres = np.column_stack([1.5 * np.cos(2 * t), 1.5 * np.sin(2 * t), 0.05 * np.sin(9 * t)])
    T_cw = np.stack([_look_T_cw(c, 2 * s + 0.3) for c, s in zip(centres, t, strict=True)])
    lf, lt, lxy = [], [], []
    for f, T in enumerate(T_cw):
        Xc = ends @ T[:3, :3].T + T[:3, 3]
        uv = Xc @ CAM.K.T
        uv = uv[..., :2] / uv[..., 2:3]
        vis = (
            (Xc[..., 2] > 0.5).all(1)
            & (uv > 0).all((1, 2))
            & (uv[..., 0] < 640).all(1)
            & (uv[..., 1] < 480).all(1)
        )
        idx = np.flatnonzero(vis)
        lf.append(np.full(len(idx), f))
        lt.append(idx)
        lxy.append(uv[idx].reshape(-1, 4) + rng.normal(0, noise_px, (len(idx), 4)))
    tracks = Tracks(
        CAM, np.arange(n), np.arange(n) / 10.0, np.ones(n, bool),
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)),
        np.concatenate(lf), np.concatenate(lt), np.concatenate(lxy), np.full(sum(map(len, lt)), -1, np.int64),
        np.full((n, 3, 3), np.nan),
    )  # fmt: skip
    desc = rng.integers(0, 256, (len(ends), 32), dtype=np.uint8)  # one LBD per physical line, a few bits off
    flips = np.packbits(rng.random((len(tracks.line_track), 32, 8)) < 0.02, axis=2)[:, :, 0]
    tracks.line_desc_row = np.arange(len(tracks.line_track))
    tracks.line_desc = desc[tracks.line_track] ^ flips
    T_wc = {f: np.linalg.inv(T) for f, T in enumerate(T_cw)}
    return tracks, T_wc, ends


def _cut(tracks: Tracks, frame: int) -> np.ndarray:
    before = np.unique(tracks.line_track[tracks.line_frame < frame])
    after = np.unique(tracks.line_track[tracks.line_frame >= frame])
    cut = np.intersect1d(before, after)
    tracks.line_track[np.isin(tracks.line_track, cut) & (tracks.line_frame >= frame)] += CUT
    return cut


def _map(tracks: Tracks, T_wc: dict, ends: np.ndarray, mapped: np.ndarray):
    est = LineEstimates(mapped, ends[mapped % CUT], np.zeros(len(mapped), bool), np.zeros(len(mapped)))
    return assemble_map(tracks, T_wc, {}, est)


def _complete(tracks, m):
    return complete_lines(tracks, m, MAX_ERR_PX, MIN_OVERLAP, MAX_HAMMING, MIN_VIEWS)


def _two_in_a_frame(tracks: Tracks) -> bool:
    pairs = np.column_stack([tracks.line_track, tracks.line_frame])
    return len(np.unique(pairs, axis=0)) < len(pairs)


def test_projected_line_errors_known_answer():
    """A segment on the projected line has zero distance and full overlap; one shifted 3 px across has
    3 px; one sliding half off the end overlaps half; a line behind the camera gives inf."""
    T_wc = np.eye(4)
    ends = np.array([[[-1.0, 0.0, 5.0], [1.0, 0.0, 5.0]], [[-1.0, 0.0, -5.0], [1.0, 0.0, -5.0]]])
    a, b = (ends[0] @ CAM.K.T)[:, :2] / 5.0
    segs = np.array([[*a, *b], [*(a + [0, 3]), *(b + [0, 3])], [*((a + b) / 2), *(b + (b - a) / 2)]])
    dist, overlap = segment_line_errors(CAM.K, T_wc, ends, segs)
    np.testing.assert_allclose(dist[0, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(dist[0, 1], 3.0, atol=1e-9)
    np.testing.assert_allclose(overlap[0], [1.0, 1.0, 0.5], atol=1e-9)
    assert np.isinf(dist[1]).all() and (overlap[1] == 0).all()


def test_prefilter_keeps_every_line_a_segment_can_match():
    """The visibility prefilter of line completion leaves out only lines no segment could match: over
    random 3D segments (many off-screen or behind) and image segments along the images of some of them
    (reaching past their ends, 1 px noise), every pair within the error limit with overlap is among the
    kept lines, and most lines that no segment reaches are left out."""
    rng = np.random.default_rng(3)
    T_wc = np.eye(4)
    mid = rng.uniform([-20, -15, -10], [20, 15, 30], (3000, 3))
    d = rng.normal(size=(3000, 3))
    ends = np.stack([mid - d, mid + d], axis=1)
    front = np.flatnonzero((ends[..., 2] > 1.0).all(axis=1))[:400]
    uv = (ends[front] @ CAM.K.T)[..., :2] / ends[front][..., 2:3]
    t = rng.uniform(-0.4, 1.4, (len(front), 2, 1))
    pieces = uv[:, :1] + t * (uv[:, 1:] - uv[:, :1]) + rng.normal(0, 1.0, (len(front), 2, 2))
    inside = ((pieces >= 0) & (pieces <= [640, 480])).all(axis=(1, 2))
    segs = np.concatenate([pieces[inside].reshape(-1, 4), rng.uniform(0, [640, 480, 640, 480], (100, 4))])
    limit = 3.0
    dist, overlap = segment_line_errors(CAM.K, T_wc, ends, segs)
    hit_lines = np.unique(np.nonzero((dist.max(axis=2) <= limit) & (overlap > 0))[0])
    kept = _lines_near_segments(CAM.K, T_wc, ends, segs, limit)
    assert len(hit_lines) > 50
    assert np.isin(hit_lines, kept).all()
    assert len(kept) < 0.6 * len(ends)


@pytest.mark.parametrize("mapped_second_piece", [True, False])
def test_cut_segment_tracks_join_their_line_and_not_its_twin(mapped_second_piece):
    tracks, T_wc, ends = _scene()
    ids = np.unique(tracks.line_track)
    cut = _cut(tracks, 20)
    assert len(cut) >= 10
    mapped = np.concatenate([ids, cut + CUT]) if mapped_second_piece else ids
    m = _map(tracks, T_wc, ends, mapped)
    n_obs = len(m.lines.obs_ids)
    truth = tracks.line_track % CUT
    stats, joined = _complete(tracks, m)
    # every physical line has one track id now, and no track holds two physical lines (no twin joined)
    pairs = np.unique(np.column_stack([truth, tracks.line_track]), axis=0)
    assert len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1]))
    if mapped_second_piece:
        assert (stats.merged, stats.completed) == (len(cut), 0)
        assert len(m.lines) == len(ids)  # one of the two pieces' lines stays
        assert (np.isin(cut, m.lines.ids) != np.isin(cut + CUT, m.lines.ids)).all()
        assert len(m.lines.obs_ids) == n_obs  # the merged lines' observations moved, none lost or doubled
    else:
        assert (stats.merged, stats.completed) == (0, len(cut))
        assert len(m.lines.obs_ids) == n_obs + stats.observations_added
    assert {(a % CUT, b % CUT) for a, b in joined.items()} == {(int(t), int(t)) for t in cut}
    if not mapped_second_piece:
        assert joined == {int(t) + CUT: int(t) for t in cut}
    assert set(map(tuple, m.lines.obs_ids.tolist())) == set(
        map(tuple, np.column_stack([tracks.line_track, tracks.line_frame]).tolist())
    )
    assert not _two_in_a_frame(tracks)


def test_pieces_whose_descriptors_disagree_stay_apart():
    tracks, T_wc, ends = _scene()
    ids = np.unique(tracks.line_track)
    cut = _cut(tracks, 20)
    second = np.isin(tracks.line_track, cut + CUT)
    tracks.line_desc[second] ^= 0xFF  # every bit flipped: another line by its looks
    m = _map(tracks, T_wc, ends, ids)
    stats, joined = _complete(tracks, m)
    assert stats.completed == 0 and joined == {}
    assert np.isin(cut + CUT, tracks.line_track).all()


def test_wrong_pose_joins_nothing():
    """With the later keyframes turned 2 deg about two axes (every image line moves 15-25 px across
    itself) the projections miss the segments: geometry must refuse."""
    tracks, T_wc, ends = _scene()
    ids = np.unique(tracks.line_track)
    cut = _cut(tracks, 20)
    m = _map(tracks, T_wc, ends, ids)
    c, s = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    m.keyframes.T_wc[20:, :3, :3] = m.keyframes.T_wc[20:, :3, :3] @ turn
    stats, _ = _complete(tracks, m)
    assert stats.completed == 0 and np.isin(cut + CUT, tracks.line_track).all()
