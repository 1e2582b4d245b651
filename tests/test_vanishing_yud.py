"""Vanishing directions on real images: a few York Urban training images (skipped when absent)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from papl_mapper.frontend.vanishing import VPConfig, classify_segments, estimate_frame, estimate_vertical

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "yud_train"
IMAGES = ["P1020177", "P1020819", "P1020831", "P1020833"]  # the first four GT files, sorted
MAX_MEDIAN_ERR_DETECTED_DEG = 1.5  # issue 4 goal, on detected segments
MAX_MEDIAN_ERR_GT_SEGMENTS_DEG = 0.6  # labelled segments lie 0.42 deg (median) from their VP
MIN_LABEL_ACCURACY = 0.9

pytestmark = pytest.mark.skipif(
    not (DATA / "camera.json").is_file(), reason=f"YUD data not found at {DATA} (../shared/data/yud_train)"
)


def _load(name):
    K = np.array(json.loads((DATA / "camera.json").read_text())["K"])
    g = json.loads((DATA / "gt" / f"{name}.json").read_text())
    lines = np.loadtxt(DATA / "gt" / f"{name}_lines.txt", ndmin=2)
    gray = cv2.imread(str(DATA / g["image"]), cv2.IMREAD_GRAYSCALE)
    return K, np.array(g["vp_directions_camera"]), gray, lines[:, :4], lines[:, 4].astype(int) - 1


def _match(gt, est):
    """Best sign-invariant assignment: per GT direction its error (90 if unmatched), est -> GT index."""
    ang = np.degrees(np.arccos(np.clip(np.abs(gt @ est.T), 0, 1)))
    best = (np.full(3, 90.0), np.full(len(est), -1))
    for perm in itertools.permutations(range(len(est)), min(3, len(est))):
        err = np.full(3, 90.0)
        err[: len(perm)] = ang[np.arange(len(perm)), perm]
        if err.sum() < best[0].sum():
            assign = np.full(len(est), -1)
            assign[list(perm)] = np.arange(len(perm))
            best = (err, assign)
    return best


def _detect(gray, kind):
    if kind == "lsd":
        return cv2.createLineSegmentDetector().detect(gray)[0].reshape(-1, 4).astype(float)
    ed = cv2.ximgproc.createEdgeDrawing()
    p = cv2.ximgproc.EdgeDrawing.Params()
    p.MinLineLength = 20
    ed.setParams(p)
    ed.detectEdges(gray)
    return ed.detectLines().reshape(-1, 4).astype(float)


@pytest.mark.parametrize("kind", ["lsd", "edlines"])
def test_detected_segments(kind):
    errs = []
    for name in IMAGES:
        K, gt, gray, _, _ = _load(name)
        segs = _detect(gray, kind)
        v = estimate_vertical([segs], K)  # the vertical prior from the same image, as a first frame
        res = estimate_frame(segs, K, v)
        assert res.vertical_index == 0 and v[1] < 0  # YUD is shot upright: up is -y
        errs.append(_match(gt, res.dirs_c)[0])
    assert np.median(errs) < MAX_MEDIAN_ERR_DETECTED_DEG, np.round(errs, 2)


@pytest.mark.parametrize("use_prior", [True, False])
def test_labelled_segments(use_prior):
    errs, acc = [], []
    for name in IMAGES:
        K, gt, _, segs, labels = _load(name)
        v = estimate_vertical([segs], K) if use_prior else None
        res = estimate_frame(segs, K, v, VPConfig())
        err, assign = _match(gt, res.dirs_c)
        errs.append(err)
        pred = classify_segments(segs, K, res.dirs_c)
        pred = np.where(pred >= 0, assign[np.maximum(pred, 0)], -1)
        acc.append(np.mean(pred == labels))
    assert np.median(errs) < MAX_MEDIAN_ERR_GT_SEGMENTS_DEG, np.round(errs, 2)
    assert np.mean(acc) > MIN_LABEL_ACCURACY, acc
