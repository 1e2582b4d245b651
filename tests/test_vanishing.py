"""Vanishing directions on synthetic segments projected from known 3D directions."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.errors import GeometryError, InputError
from papl_mapper.frontend.vanishing import (
    VPConfig,
    classify_segments,
    estimate_frame,
    estimate_vertical,
    segment_vp_angles_deg,
    update_vertical,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
NOISE_PX = 0.5
MAX_ERR_NOISELESS_DEG = 0.05  # SVD refinement on exact segments
MAX_ERR_NOISY_DEG = 0.5  # 0.5 px endpoint noise, 20% outlier segments
MAX_ERR_UNREFINED_DEG = 1.5  # the 1-degree proposal grid without refinement (plus the vertical's error)
MIN_LABEL_ACCURACY = 0.9


def _h(deg):
    a = np.radians(deg)
    return np.array([np.cos(a), np.sin(a), 0.0])


def _camera(yaw_deg, pitch_deg, roll_deg):
    """R_cw of a camera looking along yaw, tilted by pitch and roll (world +Z up)."""
    f, r = _h(yaw_deg), _h(yaw_deg - 90.0)
    R_wc = np.column_stack([r, np.cross(f, r), f])  # x right, y down, z forward
    p, q = np.radians(pitch_deg), np.radians(roll_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    Rz = np.array([[np.cos(q), -np.sin(q), 0], [np.sin(q), np.cos(q), 0], [0, 0, 1]])
    return (R_wc @ Rx @ Rz).T


def _segments(R_cw, dirs_w, counts, noise_px, n_outliers, rng):
    """Projected segments of 3D lines with the given world directions, plus random outlier segments."""
    segs, labels = [], []
    for k, (d_w, n) in enumerate(zip(dirs_w, counts, strict=True)):
        d = R_cw @ d_w
        got = 0
        for _ in range(200 * n):
            if got == n:
                break
            P = np.array([rng.uniform(-6, 6), rng.uniform(-4, 4), rng.uniform(4, 14)])
            Q = P + rng.uniform(1.0, 3.0) * d
            if min(P[2], Q[2]) < 0.5:
                continue
            p, q = (K @ P)[:2] / P[2], (K @ Q)[:2] / Q[2]
            inside = all(0 <= x[0] < W and 0 <= x[1] < H for x in (p, q))
            if inside and np.linalg.norm(p - q) >= 30:
                segs.append(np.r_[p, q])
                labels.append(k)
                got += 1
    for _ in range(n_outliers):
        p = rng.uniform([0, 0], [W, H])
        a = rng.uniform(0, np.pi)
        q = np.clip(p + rng.uniform(30, 150) * np.array([np.cos(a), np.sin(a)]), 0, [W - 1, H - 1])
        segs.append(np.r_[p, q])
        labels.append(-1)
    segs = np.array(segs) + rng.normal(scale=noise_px, size=(len(segs), 4))
    return segs, np.array(labels)


def _errors(true_c, est_c):
    """Per true direction, the unsigned angle to the nearest estimated direction (degrees)."""
    c = np.abs(np.asarray(true_c) @ np.asarray(est_c).T)
    return np.degrees(np.arccos(np.clip(c, 0, 1))).min(axis=1)


MANHATTAN = [np.array([0.0, 0.0, 1.0]), _h(20.0), _h(110.0)]
ATLANTA = [np.array([0.0, 0.0, 1.0]), _h(20.0), _h(65.0), _h(140.0)]  # horizontals not orthogonal


@pytest.mark.parametrize(
    "noise_px,n_out,tol", [(0.0, 0, MAX_ERR_NOISELESS_DEG), (NOISE_PX, 30, MAX_ERR_NOISY_DEG)]
)
def test_manhattan_scene_with_vertical_prior(noise_px, n_out, tol):
    rng = np.random.default_rng(10)
    R_cw = _camera(40.0, 8.0, 4.0)
    segs, truth = _segments(R_cw, MANHATTAN, [40, 50, 40], noise_px, n_out, rng)
    true_c = np.array([R_cw @ d for d in MANHATTAN])
    v = estimate_vertical([segs], K)
    assert v @ true_c[0] > 0  # points up (world +Z)
    assert _errors(true_c[:1], v[None])[0] < tol
    res = estimate_frame(segs, K, v)
    assert res.vertical_index == 0 and res.method == "vertical-prior-atlanta"
    assert len(res.dirs_c) == 3
    np.testing.assert_allclose(np.linalg.norm(res.dirs_c, axis=1), 1.0)
    assert _errors(true_c, res.dirs_c).max() < tol
    assert _errors(true_c[:1], res.dirs_c[:1])[0] < tol
    # labels: map each estimated direction to its true index
    match = np.argmin(np.degrees(np.arccos(np.clip(np.abs(res.dirs_c @ true_c.T), 0, 1))), axis=1)
    pred = np.where(res.labels >= 0, match[res.labels], -1)
    structural = truth >= 0
    assert np.mean(pred[structural] == truth[structural]) > MIN_LABEL_ACCURACY
    np.testing.assert_array_equal(res.inlier_counts, np.bincount(res.labels[res.labels >= 0], minlength=3))


@pytest.mark.parametrize(
    "noise_px,n_out,tol", [(0.0, 0, MAX_ERR_NOISELESS_DEG), (NOISE_PX, 20, MAX_ERR_NOISY_DEG)]
)
def test_atlanta_three_horizontals_best_two(noise_px, n_out, tol):
    rng = np.random.default_rng(11)
    R_cw = _camera(-30.0, -6.0, -3.0)
    segs, _ = _segments(R_cw, ATLANTA, [40, 60, 45, 12], noise_px, n_out, rng)
    true_c = np.array([R_cw @ d for d in ATLANTA])
    res = estimate_frame(segs, K, true_c[0])
    assert len(res.dirs_c) == 3
    # the two best-supported horizontals (60 and 45 segments, 45 degrees apart), not the weak third
    assert _errors(true_c[[0, 1, 2]], res.dirs_c).max() < tol
    assert _errors(true_c[[3]], res.dirs_c[1:])[0] > 10.0


def test_manhattan_mode_pairs_orthogonal_horizontals():
    rng = np.random.default_rng(12)
    R_cw = _camera(10.0, 5.0, 0.0)
    segs, _ = _segments(R_cw, ATLANTA, [40, 60, 45, 12], NOISE_PX, 0, rng)
    true_c = np.array([R_cw @ d for d in ATLANTA])
    cfg = VPConfig(manhattan_only=True, refine_svd=False)
    res = estimate_frame(segs, K, true_c[0], cfg)
    assert res.method == "vertical-prior-manhattan"
    # the second horizontal is the first rotated by 90 degrees about the vertical, whatever the data
    assert abs(res.dirs_c[1] @ res.dirs_c[2]) < 1e-9
    # the pair is anchored on a true horizontal (support is length-weighted: here the long 65-degree
    # segments win over the foreshortened 20-degree ones)
    assert _errors(true_c[1:], res.dirs_c[1:]).min() < MAX_ERR_UNREFINED_DEG


def test_svd_refinement_beats_the_proposal_grid():
    rng = np.random.default_rng(13)
    R_cw = _camera(73.3, 7.7, 2.2)  # directions off the 1-degree grid
    segs, _ = _segments(R_cw, MANHATTAN, [40, 50, 40], 0.0, 0, rng)
    true_c = np.array([R_cw @ d for d in MANHATTAN])
    coarse = estimate_frame(segs, K, true_c[0], VPConfig(refine_svd=False))
    fine = estimate_frame(segs, K, true_c[0], VPConfig(refine_svd=True))
    e_coarse, e_fine = _errors(true_c, coarse.dirs_c), _errors(true_c, fine.dirs_c)
    assert e_coarse.max() < MAX_ERR_UNREFINED_DEG
    assert e_fine.max() < MAX_ERR_NOISELESS_DEG
    assert e_coarse[1:].max() > 5 * e_fine[1:].max()


@pytest.mark.parametrize("noise_px,tol", [(0.0, MAX_ERR_NOISELESS_DEG), (NOISE_PX, MAX_ERR_NOISY_DEG)])
def test_two_line_search_without_prior(noise_px, tol):
    rng = np.random.default_rng(14)
    R_cw = _camera(-55.0, 12.0, -5.0)
    segs, _ = _segments(R_cw, MANHATTAN, [40, 50, 40], noise_px, 25, rng)
    true_c = np.array([R_cw @ d for d in MANHATTAN])
    res = estimate_frame(segs, K, None)
    assert res.method == "two-line-manhattan" and res.vertical_index == 0
    assert _errors(true_c[:1], res.dirs_c[:1])[0] < tol
    assert _errors(true_c, res.dirs_c).max() < tol
    # use_vertical_prior=False ignores a (wrong) prior: the ablation switch
    wrong = np.array([1.0, 0.0, 0.0])
    res2 = estimate_frame(segs, K, wrong, VPConfig(use_vertical_prior=False))
    np.testing.assert_allclose(res2.dirs_c, res.dirs_c)


def test_vertical_from_several_frames_and_tracking():
    rng = np.random.default_rng(15)
    frames, verticals = [], []
    for yaw in (0.0, 2.0, 4.0):
        R_cw = _camera(yaw, 6.0, 3.0)  # yaw about the world vertical keeps the camera-frame vertical
        frames.append(_segments(R_cw, MANHATTAN, [30, 30, 30], NOISE_PX, 10, rng)[0])
        verticals.append(R_cw @ MANHATTAN[0])
    v = estimate_vertical(frames, K)
    assert _errors(verticals[:1], v[None])[0] < MAX_ERR_NOISY_DEG
    # tracking: a rotation carries the vertical, a measurement within the gate pulls it
    R = _camera(0.0, 10.0, 3.0) @ _camera(0.0, 6.0, 3.0).T  # x_cur = R x_prev
    pred = update_vertical(verticals[0], None, R)
    np.testing.assert_allclose(pred, R @ verticals[0], atol=1e-12)
    meas = _camera(0.0, 11.0, 3.0) @ MANHATTAN[0]  # one degree off the prediction
    pulled = update_vertical(verticals[0], -meas, R, VPConfig(track_gain=0.5))  # sign of meas is free
    assert 0.4 < _errors(pulled[None], pred[None])[0] < 0.6
    far = _camera(0.0, 30.0, 3.0) @ MANHATTAN[0]  # outside the gate: ignored
    np.testing.assert_allclose(update_vertical(verticals[0], far, R), pred, atol=1e-12)
    assert pred[1] < 0  # up is -y in the image


def test_classification_and_angles():
    dirs = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # VPs at infinity: image y and x axes
    segs = np.array([[100, 100, 100, 200], [50, 50, 150, 50], [0, 0, 100, 100], [10, 10, 100, 13.0]])
    ang = segment_vp_angles_deg(segs, K, dirs)
    np.testing.assert_allclose(ang[:3], [[0, 90], [90, 0], [45, 45]], atol=1e-9)
    labels = classify_segments(segs, K, dirs)
    assert labels.tolist() == [0, 1, -1, 1]
    assert classify_segments(segs, K, dirs, VPConfig(inlier_angle_deg=1.0)).tolist() == [0, 1, -1, -1]


def test_bad_input():
    with pytest.raises(InputError):
        estimate_frame(np.zeros((5, 3)), K)
    with pytest.raises(InputError):
        estimate_frame(np.zeros((5, 4)), np.zeros((3, 3)))
    with pytest.raises(GeometryError):
        estimate_frame(np.array([[0, 0, 100, 0.0]]), K)  # one segment
    with pytest.raises(GeometryError):
        estimate_frame(np.array([[0, 0, 100, 0.0], [0, 10, 100, 10.0]]), K, np.zeros(3))
    # a NaN segment is labelled non-structural and does not disturb the others
    rng = np.random.default_rng(17)
    R_cw = _camera(40.0, 8.0, 4.0)
    segs, _ = _segments(R_cw, MANHATTAN, [30, 30, 30], NOISE_PX, 0, rng)
    bad = np.vstack([segs, [np.nan, 1.0, 2.0, 3.0], [5.0, 5.0, 5.0, 5.0]])  # NaN and zero length
    res = estimate_frame(bad, K, R_cw @ MANHATTAN[0])
    clean = estimate_frame(segs, K, R_cw @ MANHATTAN[0])
    assert res.labels[-2:].tolist() == [-1, -1]
    np.testing.assert_array_equal(res.labels[:-2], clean.labels)
    np.testing.assert_allclose(res.dirs_c, clean.dirs_c, atol=1e-12)
    # horizontal-only texture: no vertical direction to find
    rng = np.random.default_rng(16)
    segs, _ = _segments(_camera(0, 0, 0), [_h(0.0), _h(90.0)], [30, 30], 0.2, 0, rng)
    with pytest.raises(GeometryError, match="near-vertical"):
        estimate_vertical([segs], K)


def test_orthogonal_preference_takes_a_weaker_orthogonal_partner():
    dirs = [np.array([0.0, 0.0, 1.0]), _h(20.0), _h(110.0), _h(65.0)]  # 110 is orthogonal to 20
    rng = np.random.default_rng(0)
    R_cw = _camera(-30.0, -6.0, -3.0)
    segs, _ = _segments(R_cw, dirs, [40, 60, 30, 45], NOISE_PX, 10, rng)
    true_c = np.array([R_cw @ d for d in dirs])
    pure = estimate_frame(segs, K, true_c[0])  # Atlanta: the better-supported 65-degree direction
    assert _errors(true_c[[0, 1, 3]], pure.dirs_c).max() < MAX_ERR_NOISY_DEG
    pref = estimate_frame(segs, K, true_c[0], VPConfig(orthogonal_preference=0.5))
    assert _errors(true_c[[0, 1, 2]], pref.dirs_c).max() < MAX_ERR_NOISY_DEG


def test_sequence_with_vertical_tracking():
    """A turning, nodding camera: vertical from the first frames, then predicted by the relative
    rotation and updated by each frame's refined vertical; every frame's directions stay accurate."""
    rng = np.random.default_rng(18)
    poses = [_camera(4.0 * i, 6.0 + (3.0 * np.sin(i) if i >= 3 else 0.0), 2.0) for i in range(10)]
    frames = [_segments(R, MANHATTAN, [40, 50, 40], NOISE_PX, 15, rng)[0] for R in poses]
    cfg = VPConfig()
    v = estimate_vertical(frames[:3], K, cfg)
    errs, vert_errs = [], []
    for i, (R_cw, segs) in enumerate(zip(poses, frames, strict=True)):
        if i > 0:
            v = update_vertical(v, None, R_cw @ poses[i - 1].T, cfg)  # predict with x_cur = R x_prev
        res = estimate_frame(segs, K, v, cfg)
        v = update_vertical(v, res.vertical_c, None, cfg)
        true_c = np.array([R_cw @ d for d in MANHATTAN])
        errs.extend(_errors(true_c, res.dirs_c))
        vert_errs.append(_errors(true_c[:1], v[None])[0])
    assert np.median(errs) < MAX_ERR_NOISY_DEG / 2
    assert np.max(errs) < MAX_ERR_NOISY_DEG * 2
    assert np.max(vert_errs) < MAX_ERR_NOISY_DEG


def _tracker_frames(rng):
    """A turning, nodding camera (pure rotation) seeing 200 far points and the scene's segments; the
    first two frames show no vertical segment. Returns (R_cw per frame, tracker inputs per frame)."""
    pts = rng.uniform([-20, -15, 30], [20, 15, 60], size=(200, 3))  # world points in front (yaw 0)
    poses, frames = [], []
    for i in range(10):
        R_cw = _camera(3.0 * i, 6.0 + 2.0 * np.sin(i), 2.0)
        dirs, counts = (MANHATTAN[1:], [40, 40]) if i < 2 else (MANHATTAN, [40, 40, 40])
        segs = _segments(R_cw, dirs, counts, NOISE_PX, 10, rng)[0]
        R0 = _camera(0.0, 6.0, 2.0)
        x = (K @ (R_cw @ R0.T @ pts.T)).T  # the points rotate with the camera about its centre
        poses.append(R_cw)
        frames.append((segs, np.arange(200), x[:, :2] / x[:, 2:], i % 3 == 0))
    return poses, frames


@pytest.mark.parametrize("init_frames", [30, 5])
def test_vanishing_tracker_vertical_from_a_later_frame(init_frames):
    """Frames 0-1 show no vertical: the tracker's vertical comes from the earliest frame of the largest
    agreeing group (frame 2), rotated back along the point tracks, and every frame from 2 on reports
    the true vertical; a recording shorter than init_frames and one that starts the tracking midway
    give the same result (the first frames' own verticals are found as they arrive)."""
    from papl_mapper.frontend.vp_tracking import VanishingTracker, VPTrackingConfig

    poses, frames = _tracker_frames(np.random.default_rng(21))
    tracker = VanishingTracker(K, VPTrackingConfig(VPConfig(), init_frames=init_frames))
    for segs, ids, uv, kf in frames:
        tracker.add(segs, ids, uv, kf)
    labels, dirs, vertical_vp = tracker.result()
    assert tracker.vertical_source == "initialised"
    for f in range(2, 10):
        true_v = poses[f] @ MANHATTAN[0]
        assert vertical_vp[f] >= 0
        assert _errors(true_v[None], dirs[f, vertical_vp[f]][None])[0] < MAX_ERR_NOISY_DEG
    reference = VanishingTracker(K, VPTrackingConfig(VPConfig(), init_frames=30))
    for segs, ids, uv, kf in frames:
        reference.add(segs, ids, uv, kf)
    _, dirs_ref, vertical_ref = reference.result()
    np.testing.assert_array_equal(vertical_vp, vertical_ref)
    np.testing.assert_allclose(dirs, dirs_ref, atol=1e-12)


def test_vanishing_tracker_starts_once_the_vote_is_settled():
    """Eight frames in, six of them agree on the vertical (frames 0-1 show none) and the four still to
    come before init_frames = 12 could not outvote them: the tracker starts there, not after frame 12,
    and ends with the same vertical and directions as one that waited for all the frames; frames that
    disagree keep it waiting."""
    from papl_mapper.frontend.vp_tracking import VanishingTracker, VPTrackingConfig

    _, frames = _tracker_frames(np.random.default_rng(21))
    early = VanishingTracker(K, VPTrackingConfig(VPConfig(), init_frames=12))
    reference = VanishingTracker(K, VPTrackingConfig(VPConfig(), init_frames=30))
    for f, (segs, ids, uv, kf) in enumerate(frames):
        early.add(segs, ids, uv, kf)
        reference.add(segs, ids, uv, kf)
        assert early._started == (f >= 7)
    assert not reference._started
    _, dirs, vertical_vp = early.result()
    _, dirs_ref, vertical_ref = reference.result()
    np.testing.assert_array_equal(vertical_vp, vertical_ref)
    np.testing.assert_allclose(dirs, dirs_ref, atol=1e-12)
    split = VanishingTracker(K, VPTrackingConfig(VPConfig(), init_frames=12))
    split._found = [(f, MANHATTAN[0]) for f in range(4)] + [(f, MANHATTAN[1]) for f in range(4, 8)]
    split._pending = [None] * 8
    assert not split._vote_decided()
