"""Essential-matrix estimation on degenerate matches (no model, never an exception); Sampson distance."""

from __future__ import annotations

import cv2
import numpy as np

from papl_mapper.geometry.se3 import skew
from papl_mapper.geometry.two_view import find_essential, sampson_px


def test_degenerate_matches_give_no_model_instead_of_an_error():
    """Exact matches of a camera that did not move (OpenCV 5.1's solver raises on them)."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 640, (200, 2))
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    for method in (cv2.RANSAC, cv2.USAC_FAST):
        E, mask = find_essential(pts, pts.copy(), K, method, 1.0)
        assert (E is None and mask is None) or (E.shape[1] == 3 and len(mask) == len(pts))


def test_a_real_motion_gives_its_essential_matrix():
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-2, 2, 100), rng.uniform(-1, 1, 100), rng.uniform(4, 8, 100)])
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    t = np.array([0.3, 0.0, 0.05])
    a = (X / X[:, 2:]) @ K.T
    b = ((X - t) / (X - t)[:, 2:]) @ K.T
    E, mask = find_essential(a[:, :2], b[:, :2], K, cv2.RANSAC, 1.0)
    assert E is not None and mask.sum() >= 95
    xa = np.column_stack([a[:, :2], np.ones(100)]) @ np.linalg.inv(K).T
    xb = np.column_stack([b[:, :2], np.ones(100)]) @ np.linalg.inv(K).T
    assert np.abs(np.einsum("ni,ij,nj->n", xb, E[:3], xa)).max() < 1e-6


def test_sampson_px_is_half_the_split_of_a_match_across_its_epipolar_line():
    """Sideways motion: epipolar lines are image rows, and a match d pixels apart across them lies
    d / sqrt(2) from the nearest consistent pair (both points move half the way)."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    E = skew(np.array([1.0, 0, 0]))  # R = I, t along x
    a = np.array([[100.0, 50], [300, 200], [500, 400]])
    d = np.array([0.0, 1.0, 3.0])
    b = a + np.column_stack([[-40.0, 10, 25], d])  # along the row anywhere, across it by d
    np.testing.assert_allclose(sampson_px(E, a, b, K), d / np.sqrt(2), atol=1e-9)
