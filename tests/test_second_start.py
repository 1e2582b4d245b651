"""Second starts' tools (mapping/second_start.py): a map moved to other poses, poses judged alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from papl_mapper.geometry.se3 import invert, project_points, so3_exp
from papl_mapper.geometry.triangulation import triangulate_points
from papl_mapper.mapping.second_start import paired_z, pose_losses, refit_points, with_poses
from tests.test_mapping_incremental import make_tracks
from tests.test_rotation_averaging import _scene

FRAMES = np.arange(0, 30, 3)


def _observations(noise_px: float):
    tracks, T_cw, _ = make_tracks(n_frames=30, noise_px=noise_px)
    return tracks, invert(T_cw)


def test_refit_points_reaches_the_least_squares_point_of_each_track() -> None:
    """Against scipy's least squares with numerical derivatives (no Huber: errors below its threshold)."""
    tracks, T_wc = _observations(0.5)
    sel = np.flatnonzero(np.isin(tracks.point_frame, FRAMES) & (tracks.point_track < 40))
    ids, row = np.unique(tracks.point_track[sel], return_inverse=True)
    T = T_wc[tracks.point_frame[sel]]
    uv = tracks.point_uv[sel]
    K = tracks.camera.K
    X0, ok = triangulate_points(row, T, K, uv, len(ids), 0.0)
    X0 = X0 + np.random.default_rng(0).normal(0, 0.05, X0.shape)  # off the midpoint
    X = refit_points(row, T, K, uv, X0, ok, huber_px=100.0, iterations=10)
    for p in np.flatnonzero(ok)[:10]:
        mine = row == p

        def residual(x, mine=mine):
            return (project_points(K, T[mine], np.repeat(x[None], mine.sum(), 0))[0] - uv[mine]).ravel()

        ref = least_squares(residual, X0[p], method="lm", xtol=1e-12, ftol=1e-12).x
        assert np.allclose(X[p], ref, atol=1e-6), p


def test_pose_losses_are_zero_at_the_true_poses_and_grow_away_from_them() -> None:
    tracks, T_wc = _observations(0.0)
    losses, track = pose_losses(tracks, FRAMES, T_wc[FRAMES], 1.0, 1.345, 4.0)
    n = len(losses)
    seen = np.isin(tracks.point_frame, FRAMES)
    ids, counts = np.unique(tracks.point_track[seen], return_counts=True)
    assert n == counts[counts >= 2].sum()  # every observation of each track seen twice
    assert sorted(set(track.tolist())) == ids[counts >= 2].tolist()
    assert losses.sum() == pytest.approx(0.0, abs=1e-6)
    turned = T_wc[FRAMES].copy()
    turned[5:, :3, :3] = so3_exp(np.radians([0.0, 0.0, 1.0])) @ turned[5:, :3, :3]
    worse, _ = pose_losses(tracks, FRAMES, turned, 1.0, 1.345, 4.0)
    assert worse.sum() > 100.0
    flipped = T_wc[FRAMES].copy()
    flipped[:, :3, :3] = flipped[:, :3, :3] @ np.diag([-1.0, -1.0, 1.0])  # every camera looking backwards
    capped, _ = pose_losses(tracks, FRAMES, flipped, 1.0, 1.345, 4.0)
    assert capped.sum() == pytest.approx(
        n * (1.345 * 4.0 - 0.5 * 1.345**2), rel=0.05
    )  # nearly all at the cap


def test_paired_z_counts_tracks_not_observations() -> None:
    """A difference that every track shows is significant; the same total from one track is not, however
    many observations that track has; no spread or one track gives 0."""
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(200), 10)
    consistent = -0.1 + rng.normal(0, 0.05, len(groups))
    assert paired_z(consistent, groups) < -10
    one_track = np.zeros(len(groups))
    one_track[groups == 7] = -20.0  # the same total, all from one track
    one_track += rng.normal(0, 0.05, len(groups))
    assert -3 < paired_z(one_track, groups) < 0
    assert paired_z(np.zeros(10), np.arange(10)) == 0.0
    assert paired_z(np.ones(5), np.zeros(5, int)) == 0.0


def test_with_poses_moves_the_points_with_a_rigid_motion_of_the_keyframes() -> None:
    m = _scene(noise_px=0.0)
    motion = np.eye(4)
    motion[:3, :3] = so3_exp(np.radians([10.0, -20.0, 5.0]))
    motion[:3, 3] = [1.0, -2.0, 0.5]
    out = with_poses(m, motion[None] @ m.keyframes.T_wc)
    seen = np.isin(m.points.ids, m.points.obs_ids[:, 0])
    assert seen.sum() > 300
    moved = m.points.xyz @ motion[:3, :3].T + motion[:3, 3]
    assert np.allclose(out.points.xyz[seen], moved[seen], atol=1e-6)
    assert np.array_equal(out.points.xyz[~seen], m.points.xyz[~seen])  # unobserved points stay
    assert np.array_equal(out.points.obs_ids, m.points.obs_ids)
