"""Map points found again at a new keyframe (search by projection) on tracks projected from a known scene.

Tracks are cut in two at a frame, as a KLT break does; registered up to that frame with the true poses,
the keyframe's young pieces must take their own point's id and never another's.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.mapping.refind import RefindConfig, Refinder
from papl_mapper.tracks import PointRows

from .test_track_completion import CUT, _cut, _scene, _seen_twice_in_a_frame

FRAME = 20


def _registered(noise_px: float = 0.3, seed: int = 0):
    """Tracks with every other track cut at FRAME, the true points of the first pieces as the map, and
    the true poses of frames 0..FRAME (what registration holds when FRAME becomes a keyframe)."""
    tracks, T_wc, pts = _scene(noise_px, seed)
    ids = np.unique(tracks.point_track)
    cut = _cut(tracks, FRAME, ids[::2])
    points_w = {int(t): pts[t] for t in ids if (tracks.point_track == t).any()}
    poses = {f: np.linalg.inv(T_wc[f]) for f in range(FRAME + 1)}
    return tracks, points_w, poses, cut


def test_young_pieces_take_their_own_points_id():
    tracks, points_w, poses, cut = _registered()
    truth = tracks.point_track % CUT
    rows = PointRows(tracks)
    seen = np.unique(tracks.point_track[tracks.point_frame == FRAME])
    young = seen[seen >= CUT]
    assert len(young) > 30
    n = Refinder(tracks, RefindConfig()).refind(rows, FRAME, poses[FRAME], points_w, poses)
    assert n == len(young)
    assert np.array_equal(tracks.point_track, truth)  # each to its own point, none to another
    assert not _seen_twice_in_a_frame(tracks)
    # the row index follows the renames without a rebuild
    for t in (young[:5] - CUT).tolist():
        assert np.array_equal(rows.rows(np.array([t])), np.flatnonzero(tracks.point_track == t))
        assert len(rows.rows(np.array([t + CUT]))) == 0


def test_pieces_whose_descriptors_disagree_stay_apart():
    tracks, points_w, poses, _ = _registered()
    later = tracks.point_track >= CUT
    tracks.point_desc = tracks.point_desc.copy()
    tracks.point_desc[later] ^= 0xFF  # every bit flipped: another corner's descriptor
    before = tracks.point_track.copy()
    n = Refinder(tracks, RefindConfig()).refind(PointRows(tracks), FRAME, poses[FRAME], points_w, poses)
    assert n == 0
    assert np.array_equal(tracks.point_track, before)


def test_a_wrong_pose_finds_nothing():
    """Projected from a pose 20 px off, no young corner is near its point: nothing is joined."""
    tracks, points_w, poses, _ = _registered()
    T = poses[FRAME].copy()
    T[0, 3] += 20.0 / 500.0 * np.median([np.linalg.norm(T[:3, :3] @ X + T[:3, 3]) for X in points_w.values()])
    before = tracks.point_track.copy()
    n = Refinder(tracks, RefindConfig()).refind(PointRows(tracks), FRAME, T, points_w, poses)
    assert n == 0
    assert np.array_equal(tracks.point_track, before)


def test_point_rows_rename_folds_rows():
    tracks, _, _, cut = _registered()
    rows = PointRows(tracks)
    a, b = int(cut[0]), int(cut[0]) + CUT
    tracks.point_track[tracks.point_track == b] = a
    rows.rename(b, a)
    got, which = rows.rows_by_id(np.array([b, a, a]))
    expect = np.flatnonzero(tracks.point_track == a)
    assert np.array_equal(np.sort(got[which == 1]), expect)
    assert np.array_equal(np.sort(got[which == 2]), expect)
    assert not (which == 0).any()
