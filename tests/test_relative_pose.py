"""Registering a frame from its essential matrix to the last keyframe, scaled by a few mapped points."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.geometry.se3 import rotation_angle_deg, so3_exp
from papl_mapper.map import Camera
from papl_mapper.mapping.relative_pose import RelativePoseConfig, register_relative
from papl_mapper.tracks import Tracks

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)


def _two_views(noise_px: float, seed: int = 0, n: int = 300, strip: bool = False):
    """Frame 0 (posed) and frame 1 a wide step away; n shared tracks, world = frame 0 scaled by 2.
    With `strip`, the points fill a strip 0.1 wide and 2 deep and frame 1 turns 20 deg on a short step."""
    rng = np.random.default_rng(seed)
    if strip:
        X = np.column_stack([rng.uniform(-1.0, -0.9, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2.5, 4.5, n)])
    else:
        X = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 9, n)])
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[:3, :3] = so3_exp(np.array([0.0, -0.35, 0.0]) if strip else np.array([0.02, -0.25, 0.03]))
    T1[:3, 3] = [0.15, 0.0, -0.05] if strip else [-0.8, 0.05, -0.3]
    uv = []
    for T in (T0, T1):
        Xc = X @ T[:3, :3].T + T[:3, 3]
        p = Xc @ CAM.K.T
        uv.append(p[:, :2] / p[:, 2:3] + rng.normal(0, noise_px, (n, 2)))
    tracks = Tracks(
        CAM,
        np.arange(2),
        np.arange(2.0),
        np.ones(2, bool),
        np.repeat([0, 1], n),
        np.tile(np.arange(n), 2),
        np.vstack(uv),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4)),
        np.zeros(0, np.int64),
        np.full((2, 3, 3), np.nan),
    )
    return tracks, X, T1


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_pose_from_the_step_and_six_mapped_points(noise_px):
    tracks, X, T1 = _two_views(noise_px)
    mapped = {i: X[i] for i in range(6)}  # too few for a reliable PnP, enough for one step length
    res = register_relative(tracks, 1, 0, np.eye(4), mapped, RelativePoseConfig())
    assert res.ok, res.reason
    assert rotation_angle_deg(res.T_cw[:3, :3], T1[:3, :3]) < 0.1
    c_est = -res.T_cw[:3, :3].T @ res.T_cw[:3, 3]
    c_gt = -T1[:3, :3].T @ T1[:3, 3]
    assert np.linalg.norm(c_est - c_gt) < 0.02 * np.linalg.norm(c_gt)


def test_wrong_mapped_points_do_not_scale_the_step():
    tracks, X, T1 = _two_views(0.3)
    mapped = {i: X[i] for i in range(8)}
    mapped.update({i: X[i] * 3.0 for i in range(8, 11)})  # three points from a wrong scale
    res = register_relative(tracks, 1, 0, np.eye(4), mapped, RelativePoseConfig())
    assert res.ok
    c_est = -res.T_cw[:3, :3].T @ res.T_cw[:3, 3]
    c_gt = -T1[:3, :3].T @ T1[:3, 3]
    assert np.linalg.norm(c_est - c_gt) < 0.02 * np.linalg.norm(c_gt)


def test_too_few_mapped_points_is_refused():
    tracks, X, _ = _two_views(0.0)
    res = register_relative(tracks, 1, 0, np.eye(4), {0: X[0], 1: X[1]}, RelativePoseConfig())
    assert not res.ok and "mapped points" in res.reason


def test_two_disagreeing_scale_groups_are_refused_without_a_warning():
    """Four mapped points, two at the true scale and two at twice it: the median falls between the groups,
    none agrees with it, and the frame is refused in words (no NaN pose, no RuntimeWarning)."""
    import warnings

    tracks, X, _ = _two_views(0.0)
    mapped = {0: X[0], 1: X[1], 2: 2.0 * X[2], 3: 2.0 * X[3]}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = register_relative(tracks, 1, 0, np.eye(4), mapped, RelativePoseConfig(min_scale_points=2))
    assert not res.ok and "agree on the step length" in res.reason


def test_a_pair_with_as_few_shared_tracks_as_a_verified_feature_pair_registers():
    """30 shared tracks (a sparse photo set's neighbours share few): enough, as for a verified feature
    pair (25 inliers); 20 are refused."""
    tracks, X, T1 = _two_views(0.5, seed=3, n=30)
    res = register_relative(tracks, 1, 0, np.eye(4), {i: X[i] for i in range(6)}, RelativePoseConfig())
    assert res.ok, res.reason
    assert rotation_angle_deg(res.T_cw[:3, :3], T1[:3, :3]) < 1.0  # 30 points at 0.5 px: BA refines it
    c_est = -res.T_cw[:3, :3].T @ res.T_cw[:3, 3]
    c_gt = -T1[:3, :3].T @ T1[:3, 3]
    assert np.linalg.norm(c_est - c_gt) < 0.1 * np.linalg.norm(c_gt)
    tracks, X, _ = _two_views(0.5, seed=3, n=20)
    refused = register_relative(tracks, 1, 0, np.eye(4), {i: X[i] for i in range(6)}, RelativePoseConfig())
    assert not refused.ok


def test_matches_in_a_narrow_strip_are_refused_as_not_fixed():
    """The relative rotation of matches crowded into a strip of the image is degrees uncertain: the frame
    is refused, not posed off by as much (the gate is off in the loose config to show it)."""
    tracks, X, T1 = _two_views(1.0, seed=2, n=110, strip=True)
    mapped = {i: X[i] for i in range(20)}
    res = register_relative(tracks, 1, 0, np.eye(4), mapped, RelativePoseConfig())
    assert not res.ok and "not fixed" in res.reason
    loose = register_relative(
        tracks, 1, 0, np.eye(4), mapped, RelativePoseConfig(max_rotation_std_deg=np.inf)
    )
    assert loose.ok, loose.reason
    assert rotation_angle_deg(loose.T_cw[:3, :3], T1[:3, :3]) > 3.0
