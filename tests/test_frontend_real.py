"""Frontend steps on real images (York Urban, ../shared/data/yud_train) and the rotation estimate.

Real images have no motion ground truth, so motion is applied by a known image warp: a shift for
point and segment tracking, and the homography K R K^-1 of a known rotation for the rotation.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.descriptors import hamming, hamming_pairs, match_candidates, match_descriptors
from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.lines import LBD, LineConfig, LineTracker, SegmentDetector, match_keyframe_lines
from papl_mapper.frontend.motion import relative_rotation, rotation_from_bearings
from papl_mapper.frontend.points import PointConfig, PointTracker
from papl_mapper.synth.segment_scores import detection_scores

YUD_NAMES = ("P1020177", "P1020819", "P1020831", "P1020839")
MIN_YUD_RECALL = 0.4  # hand-labelled segments at least half covered (3 px, 3 deg); measured about 0.5
SHIFT = np.array([3.3, -2.1])
MAX_SHIFT_ERR_PX = 0.3  # median
MIN_MATCH_PRECISION = 0.95
VERTICAL_TRANSPORT_TOL_DEG = {0.0: 0.05, 1.0: 0.1}  # noise px -> carried vertical error (no rotation: 0.68)
ROT_TOL_DEG = {0.0: 0.05, 1.0: 0.5}  # noise px -> largest rotation error (RANSAC E, no refinement)


def _yud(shared_data, name):
    root = shared_data / "yud_train"
    paths = sorted((root / "images").glob(f"{name}.*"))
    if not paths:
        pytest.skip(f"{name} not in {root}")
    img = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE)
    labels = np.loadtxt(root / "gt" / f"{name}_lines.txt")[:, :4]
    return img, labels


def _shift(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    M = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
    return cv2.warpAffine(
        img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )


@pytest.mark.parametrize("detector", ["edlines", "lsd"])
def test_yud_segment_recall_against_hand_labels(shared_data, detector):
    det = SegmentDetector(LineConfig(detector=detector))
    recalls = []
    for name in YUD_NAMES:
        img, labels = _yud(shared_data, name)
        _, r, _ = detection_scores(det.detect(img), labels)
        recalls.append(r)
    assert np.mean(recalls) >= MIN_YUD_RECALL


@pytest.mark.parametrize("name", YUD_NAMES[:2])
def test_yud_shift_is_tracked_by_points_segments_and_lbd(shared_data, name):
    img, _ = _yud(shared_data, name)
    moved = _shift(img, SHIFT)
    h, w = img.shape
    pts = PointTracker(PointConfig(), FlowConfig(), w, h)
    pts.step(img, None)
    before = dict(zip(pts.ids.tolist(), pts.uv.tolist(), strict=True))
    pts.step(moved, img)
    d = np.array(
        [
            np.array(u) - before[i]
            for i, u in zip(pts.ids.tolist(), pts.uv.tolist(), strict=True)
            if i in before
        ]
    )
    assert len(d) > 100
    assert np.median(np.linalg.norm(d - SHIFT, axis=1)) < MAX_SHIFT_ERR_PX

    cfg = LineConfig()
    det = SegmentDetector(cfg)
    lt = LineTracker(cfg)
    s0 = det.detect(img)
    ids0 = lt.step(s0, None, None)
    s1 = det.detect(moved)
    ids1 = lt.step(s1, pts.flow_from, pts.flow_to)
    common, i0, i1 = np.intersect1d(ids0, ids1, return_indices=True)
    assert len(common) > 0.5 * min(len(s0), len(s1))
    # a tracked segment lies on the shifted line of its predecessor
    p0 = s0[i0]
    n = np.stack([-(p0[:, 3] - p0[:, 1]), p0[:, 2] - p0[:, 0]], 1)
    n /= np.linalg.norm(n, axis=1)[:, None]
    mid1 = (s1[i1, :2] + s1[i1, 2:]) / 2
    off = np.abs(np.sum((mid1 - SHIFT - p0[:, :2]) * n, axis=1))
    assert np.mean(off < 1.5) >= MIN_MATCH_PRECISION

    lbd = LBD()
    r0, d0 = lbd.compute(img, s0)
    r1, d1 = lbd.compute(moved, s1)
    m = match_keyframe_lines(s0[r0], d0, s1[r1], d1, cfg)
    assert len(m) > 0.3 * min(len(r0), len(r1))
    a, b = s0[r0][m[:, 0]], s1[r1][m[:, 1]]
    na = np.stack([-(a[:, 3] - a[:, 1]), a[:, 2] - a[:, 0]], 1)
    na /= np.linalg.norm(na, axis=1)[:, None]
    offb = np.abs(np.sum(((b[:, :2] + b[:, 2:]) / 2 - SHIFT - a[:, :2]) * na, axis=1))
    assert np.mean(offb < 1.5) >= MIN_MATCH_PRECISION


def test_hamming_matches_bit_count():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    ref = np.array([[np.unpackbits(x ^ y).sum() for y in b] for x in a])
    np.testing.assert_array_equal(hamming(a, b), ref)
    ia, ib = np.array([0, 3, 6]), np.array([4, 0, 2])
    np.testing.assert_array_equal(hamming_pairs(a, b, ia, ib), ref[ia, ib])


def _dense_gated_matches(a, b, max_hamming, ratio, allowed):
    """The gated matcher written over the whole (A, B) table: the definition the sparse one keeps."""
    ham = np.where(allowed, hamming(a, b), np.inf)
    best_b, best_a = np.argmin(ham, axis=1), np.argmin(ham, axis=0)
    second = np.sort(ham, axis=1)[:, 1] if len(b) > 1 else np.full(len(a), np.inf)
    ia = np.arange(len(a))
    d = ham[ia, best_b]
    ok = np.isfinite(d) & (d <= max_hamming) & (best_a[best_b] == ia) & (d <= ratio * second)
    return np.stack([ia[ok], best_b[ok]], axis=1)


def test_matching_over_candidate_pairs_equals_the_gated_table():
    rng = np.random.default_rng(3)
    found = 0
    for _ in range(400):
        na, nb = rng.integers(1, 25, 2)
        bits = rng.integers(1, 9)  # few distinct descriptors: many ties, which must break alike
        a = rng.integers(0, 2**bits, (na, 32)).astype(np.uint8)
        b = rng.integers(0, 2**bits, (nb, 32)).astype(np.uint8)
        allowed = rng.random((na, nb)) < rng.random()
        ia, ib = np.nonzero(allowed)
        shuffle = rng.permutation(len(ia))  # the candidates' order does not matter
        for max_hamming, ratio in ((64, 0.8), (256, 1.0), (12, 0.9)):
            want = _dense_gated_matches(a, b, max_hamming, ratio, allowed)
            got = match_candidates(a, b, ia[shuffle], ib[shuffle], max_hamming, ratio)
            np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(match_descriptors(a, b, max_hamming, ratio, allowed), want)
            found += len(want)
    assert found > 1000  # the cases hold matches, not only refusals


def _rot(axis, deg):
    v = np.asarray(axis, float)
    return cv2.Rodrigues(v / np.linalg.norm(v) * np.radians(deg))[0]


@pytest.mark.parametrize("noise", [0.0, 1.0])
@pytest.mark.parametrize("translation", [0.0, 0.05])
def test_relative_rotation_known_answer(noise, translation):
    """Points 2-6 m away seen from two poses: x_b = R x_a + t; the estimate recovers R."""
    rng = np.random.default_rng(1)
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-2, 2, 300), rng.uniform(-1.5, 1.5, 300), rng.uniform(2, 6, 300)])
    R = _rot([0.2, 1.0, 0.1], 3.0)
    t = np.array([translation, 0.0, translation / 2])
    Xb = X @ R.T + t
    ua = (X @ K.T)[:, :2] / X[:, 2:3] + rng.normal(0, noise, (300, 2))
    ub = (Xb @ K.T)[:, :2] / Xb[:, 2:3] + rng.normal(0, noise, (300, 2))
    ub[:20] += rng.uniform(-30, 30, (20, 2))  # outliers
    est = relative_rotation(ua, ub, K)
    assert est is not None
    err = np.degrees(np.arccos(np.clip((np.trace(est.T @ R) - 1) / 2, -1, 1)))
    assert err < ROT_TOL_DEG[noise]


def test_relative_rotation_refuses_too_few_points():
    K = np.eye(3)
    assert relative_rotation(np.zeros((5, 2)), np.ones((5, 2)), K) is None


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_rotation_from_bearings_carries_the_vertical(noise):
    """Rotation-only fit under walking-like translation: the transported vertical stays accurate."""
    rng = np.random.default_rng(2)
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-2, 2, 300), rng.uniform(-1.5, 1.5, 300), rng.uniform(2, 6, 300)])
    R = _rot([0.3, 1.0, -0.2], 2.0)
    t = np.array([0.01, 0.0, 0.03])  # a frame of walking: forward and a little sideways, no vertical
    Xb = X @ R.T + t
    ua = (X @ K.T)[:, :2] / X[:, 2:3] + rng.normal(0, noise, (300, 2))
    ub = (Xb @ K.T)[:, :2] / Xb[:, 2:3] + rng.normal(0, noise, (300, 2))
    ub[:20] += rng.uniform(-30, 30, (20, 2))
    est = rotation_from_bearings(ua, ub, K)
    up = np.array([0.0, -1.0, 0.0])
    err = np.degrees(np.arccos(np.clip(abs((est @ up) @ (R @ up)), -1, 1)))
    assert err < VERTICAL_TRANSPORT_TOL_DEG[noise]
