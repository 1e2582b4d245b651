"""The wide-baseline features: weak links, which pairs are matched, track chaining, SIFT matching."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.features import (
    FeatureConfig,
    SiftDetector,
    candidate_pairs,
    chain_tracks,
    match_pair,
    root_sift,
    weak_links,
)


def test_weak_links_count_the_tracks_consecutive_keyframes_share():
    # frames 0, 1, 2 (rows in frame order): 0 and 1 share tracks 1-3, 1 and 2 share only track 3
    frame = np.array([0, 0, 0, 1, 1, 1, 2, 2])
    track = np.array([1, 2, 3, 1, 2, 3, 3, 9])
    assert weak_links(frame, track, np.array([0, 1, 2]), 2).tolist() == [False, True]
    assert weak_links(frame, track, np.array([0, 2]), 2).tolist() == [True]


def test_a_break_between_keyframes_makes_their_link_weak_whatever_they_share():
    """KLT across a jump (dropped frames, a fast car) keeps enough tracks to pass the count, but few and
    short ones: the features must be matched there too, as they were detected there."""
    frame = np.repeat(np.arange(6), 3)
    track = np.tile([1, 2, 3], 6)  # every frame shares all three tracks
    keyframes = np.array([0, 2, 5])
    assert weak_links(frame, track, keyframes, 2).tolist() == [False, False]
    assert weak_links(frame, track, keyframes, 2, breaks=np.array([4])).tolist() == [False, True]
    assert weak_links(frame, track, keyframes, 2, breaks=np.array([2])).tolist() == [True, False]
    assert weak_links(frame, track, keyframes, 2, breaks=np.array([5, 1])).tolist() == [True, True]
    assert weak_links(frame, track, keyframes, 2, breaks=np.array([0])).tolist() == [False, False]


def test_only_pairs_across_a_weak_link_within_the_window_are_matched():
    cfg = FeatureConfig(window=2, exhaustive_below=0)
    weak = np.array([False, False, True, False, False])  # keyframes 0..5, the link 2-3 is weak
    pairs = candidate_pairs(np.arange(6), weak, cfg)
    assert sorted(pairs) == [(1, 3), (2, 3), (2, 4)]
    assert candidate_pairs(np.arange(6), np.zeros(5, bool), cfg) == []
    # a photo set (every link weak, few keyframes): every pair
    assert len(candidate_pairs(np.arange(6), np.ones(5, bool), FeatureConfig())) == 15


def test_chaining_never_puts_two_observations_of_a_track_in_one_frame():
    node_frame = np.array([0, 0, 1, 1, 2])
    # good chain 0-2-4 (cost 1), 1-3 (cost 1); a worse edge 3-4 would join 1-3 with 0-2-4, which
    # holds frame 1 already (node 2): refused; so would 0-1 (same frame)
    edges = np.array([[0, 2], [2, 4], [1, 3], [3, 4], [0, 1]])
    cost = np.array([1.0, 1.0, 1.0, 5.0, 9.0])
    label = chain_tracks(node_frame, edges, cost)
    assert label[0] == label[2] == label[4] and label[1] == label[3] and label[0] != label[1]
    for t in set(label.tolist()):
        frames = node_frame[label == t]
        assert len(frames) == len(set(frames.tolist()))
    assert (chain_tracks(np.array([0, 1, 2]), np.zeros((0, 2), np.int64), np.zeros(0)) == -1).all()


def _textured_image(rng: np.random.Generator, size: tuple[int, int] = (480, 640)) -> np.ndarray:
    """Blobs of every scale: blurred noise at three scales, contrast stretched."""
    img = np.zeros(size, np.float32)
    for sigma in (1.5, 4.0, 10.0):
        img += cv2.GaussianBlur(rng.standard_normal(size).astype(np.float32), (0, 0), sigma) * sigma
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


@pytest.mark.parametrize("noise", [0.0, 4.0])
def test_sift_matches_follow_a_known_rotation_and_zoom(noise):
    """Keypoints of an image and of the image turned 25 deg and zoomed 1.3x, matched: the matches
    agree with the known homography to a fraction of a pixel, also with image noise."""
    rng = np.random.default_rng(3)
    a = _textured_image(rng)
    H = cv2.getRotationMatrix2D((320.0, 240.0), 25.0, 1.3)
    b = cv2.warpAffine(a, H, (640, 480), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    if noise:
        a = np.clip(a + rng.normal(0, noise, a.shape), 0, 255).astype(np.uint8)
        b = np.clip(b + rng.normal(0, noise, b.shape), 0, 255).astype(np.uint8)
    det = SiftDetector(FeatureConfig())
    uv_a, sift_a, orb_a = det.detect(a)
    uv_b, sift_b, orb_b = det.detect(b)
    assert len(uv_a) == len(sift_a) == len(orb_a) > 300 and orb_a.shape[1] == 32
    assert np.allclose(np.linalg.norm(sift_a, axis=1), 1.0, atol=1e-4)
    m, dist = match_pair(sift_a, sift_b, 0.8)
    assert len(m) > 500 and len(np.unique(m[:, 1])) == len(m)  # one match per keypoint of b
    pred = uv_a[m[:, 0]] @ H[:, :2].T + H[:, 2]
    err = np.linalg.norm(pred - uv_b[m[:, 1]], axis=1)
    assert np.mean(err < 1.5) > 0.97
    assert np.median(err[err < 1.5]) < 0.35  # sub-pixel keypoints
    # the ratio test: matching against an unrelated image finds almost nothing that passes
    other = _textured_image(np.random.default_rng(11))
    _, sift_o, _ = det.detect(other)
    assert len(match_pair(sift_a, sift_o, 0.8)[0]) < 0.05 * len(m)
    # the frontend detects in two threads at once: each thread's own detectors, the same keypoints
    with ThreadPoolExecutor(max_workers=2) as pool:
        both = list(pool.map(det.detect, [a, b, other, a]))
    serial = [(uv_a, sift_a, orb_a), (uv_b, sift_b, orb_b), det.detect(other), (uv_a, sift_a, orb_a)]
    for got, want in zip(both, serial, strict=True):
        for x, y in zip(got, want, strict=True):
            np.testing.assert_array_equal(x, y)


def test_root_sift_dot_product_is_the_hellinger_kernel():
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 255, (2, 128)).astype(np.float32)
    rx, ry = root_sift(np.stack([x, y]))
    assert np.isclose(rx @ ry, np.sum(np.sqrt(x / x.sum() * y / y.sum())), rtol=1e-5)
