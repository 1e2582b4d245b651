"""Cameras that turn in place: refused as a two-view start, reported as rotation only, oriented by rays."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.errors import UnmappableError
from papl_mapper.geometry.se3 import bearings, rotation_angle_deg, rotation_between_rays, so3_exp
from papl_mapper.map import Camera
from papl_mapper.mapping.incremental import register_keyframes
from papl_mapper.mapping.initialise import initialise_two_view
from papl_mapper.mapping.rotation_only import RotationOnlyConfig, fill_rotation_only
from papl_mapper.tracks import Tracks
from tests.test_mapping_incremental import _look_T_cw

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)


def _room_tracks(T_cw: np.ndarray, noise_px: float = 0.0, seed: int = 0) -> Tracks:
    """Points on the walls of a 12 m room seen by poses T_cw (F, 4, 4); one track per point."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-6, 6, 4000), rng.uniform(-6, 6, 4000), rng.uniform(-1.5, 1.5, 4000)])
    pts = pts[np.abs(pts[:, :2]).max(axis=1) > 3.0]
    pf, pt, puv = [], [], []
    for f, T in enumerate(T_cw):
        Xc = pts @ T[:3, :3].T + T[:3, 3]
        uv = Xc @ CAM.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        vis = (Xc[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        idx = np.flatnonzero(vis)
        pf.append(np.full(len(idx), f))
        pt.append(idx)
        puv.append(uv[idx] + rng.normal(0, noise_px, (len(idx), 2)))
    n = len(T_cw)
    return Tracks(
        CAM,
        np.arange(n),
        np.arange(n) / 10.0,
        np.arange(n) % 3 == 0,
        np.concatenate(pf),
        np.concatenate(pt),
        np.concatenate(puv),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4)),
        np.zeros(0, np.int64),
        np.full((n, 3, 3), np.nan),
    )


def _pan(n: int, degrees: float, centre=(0.5, -0.3, 0.0)) -> np.ndarray:
    yaws = np.radians(np.linspace(0.0, degrees, n)) + 0.3
    return np.stack([_look_T_cw(np.array(centre), y) for y in yaws])


def test_rotation_between_rays_recovers_a_known_rotation_with_outliers():
    rng = np.random.default_rng(1)
    b1 = bearings(rng.uniform(-0.6, 0.6, (300, 2)))
    R = so3_exp(np.array([0.05, -0.2, 0.1]))
    b2 = b1 @ R.T
    b2[:30] = bearings(rng.uniform(-0.6, 0.6, (30, 2)))  # 10% wrong matches
    R_est, err = rotation_between_rays(b1, b2)
    assert rotation_angle_deg(R_est, R) < 1e-6
    assert np.median(err) < 1e-6 and (err[:30] > 1.0).all()


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_two_view_start_refuses_a_pure_rotation(noise_px):
    T_cw = _pan(2, 25.0)
    tracks = _room_tracks(T_cw, noise_px)
    id1, uv1 = tracks.points_in(0)
    id2, uv2 = tracks.points_in(1)
    _, i1, i2 = np.intersect1d(id1, id2, return_indices=True)
    K = CAM.K
    x1 = (uv1[i1] - K[:2, 2]) / K[0, 0]
    x2 = (uv2[i2] - K[:2, 2]) / K[0, 0]
    res = initialise_two_view(x1, x2, K[0, 0])
    assert not res.ok and res.rotation_only, res.reason
    R_21 = T_cw[1][:3, :3] @ T_cw[0][:3, :3].T
    assert rotation_angle_deg(res.R_21, R_21) < 0.05


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_rotation_only_recording_is_reported_with_its_orientations(noise_px):
    T_cw = _pan(40, 60.0)
    tracks = _room_tracks(T_cw, noise_px)
    with pytest.raises(UnmappableError, match="rotation only") as err:
        register_keyframes(tracks)
    poses = err.value.T_cw_frames
    assert sorted(poses) == list(range(40))
    for f, T in poses.items():  # orientations relative to the first frame, centres at the origin
        R_gt = T_cw[f][:3, :3] @ T_cw[0][:3, :3].T
        assert rotation_angle_deg(T[:3, :3], R_gt) < 0.1
        assert np.allclose(T[:3, 3], 0.0)


def test_static_camera_is_reported_as_no_motion():
    tracks = _room_tracks(_pan(12, 0.0))
    with pytest.raises(UnmappableError, match="no motion"):
        register_keyframes(tracks)


def test_pan_before_the_walk_gets_orientations_from_the_first_posed_frame():
    """Frames 0-19 turn in place, 20-49 walk: with the walk posed, the pan is oriented by rays."""
    pan = _pan(20, 30.0, centre=(0.5, -0.3, 0.0))
    yaw0 = np.radians(30.0) + 0.3
    walk = np.stack(
        [_look_T_cw(np.array([0.5 + 0.04 * k, -0.3 + 0.02 * k, 0.0]), yaw0) for k in range(1, 31)]
    )
    T_cw = np.concatenate([pan, walk])
    tracks = _room_tracks(T_cw, 0.5)
    posed = {f: T_cw[f] for f in range(20, 50)}
    filled = fill_rotation_only(tracks, posed, RotationOnlyConfig())
    assert sorted(filled) == list(range(20))
    centre20 = -T_cw[20][:3, :3].T @ T_cw[20][:3, 3]
    for f, T in filled.items():
        assert rotation_angle_deg(T[:3, :3], T_cw[f][:3, :3]) < 0.2
        assert np.allclose(-T[:3, :3].T @ T[:3, 3], centre20)


def test_a_walk_is_not_oriented_as_a_rotation():
    """Frames that translate show parallax against their anchor: the rotation chain stops."""
    walk = np.stack([_look_T_cw(np.array([0.15 * k, 0.1 * k, 0.0]), 0.3) for k in range(30)])
    tracks = _room_tracks(walk, 0.3)
    filled = fill_rotation_only(tracks, {29: walk[29]}, RotationOnlyConfig())
    assert len(filled) <= 2


def test_one_frame_is_reported_as_too_few_frames():
    tracks = _room_tracks(_pan(1, 0.0))
    with pytest.raises(UnmappableError, match="too few frames: 1 decoded frame"):
        register_keyframes(tracks)
