"""The vectorised frontend kernels against direct (slow, obvious) implementations of the same formulas."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.frontend import vanishing
from papl_mapper.frontend.lines import LineConfig, match_predicted
from papl_mapper.frontend.vanishing import VPConfig, segment_vp_angles_deg

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
ANGLE_TOL_DEG = 1e-8


def _random_segments(rng: np.random.Generator, n: int) -> np.ndarray:
    p = rng.uniform([0, 0], [640, 480], (n, 2))
    a = rng.uniform(0, 2 * np.pi, n)
    length = rng.uniform(5, 200, n)
    return np.hstack([p, p + length[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)])


def _angles_direct(segs: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Angle between each segment and the image line from its midpoint to each vanishing point."""
    out = np.zeros((len(segs), len(dirs)))
    for i, (x1, y1, x2, y2) in enumerate(segs):
        u = np.array([x2 - x1, y2 - y1])
        m = np.array([x1 + x2, y1 + y2]) / 2
        for j, d in enumerate(dirs):
            vp = K @ d
            w = vp[:2] - vp[2] * m  # towards the VP (finite or at infinity), up to scale and sign
            if np.linalg.norm(w) < 1e-9:
                out[i, j] = 90.0  # the VP is the midpoint: no direction
                continue
            c = abs(u @ w) / (np.linalg.norm(u) * np.linalg.norm(w))
            out[i, j] = np.degrees(np.arccos(min(1.0, c)))
    return out


def test_segment_vp_angles_match_the_direct_formula():
    rng = np.random.default_rng(0)
    segs = _random_segments(rng, 40)
    dirs = rng.normal(size=(25, 3))
    dirs[0] = [0.0, 1.0, 0.0]  # a vanishing point at infinity
    dirs[1] = np.linalg.inv(K) @ [*((segs[3, :2] + segs[3, 2:]) / 2), 1.0]  # VP on a segment's midpoint
    fast = segment_vp_angles_deg(segs, K, dirs)
    direct = _angles_direct(segs, dirs)
    assert fast[3, 1] == 90.0 and direct[3, 1] == 90.0  # no direction from the midpoint to the VP
    np.testing.assert_allclose(fast, direct, atol=ANGLE_TOL_DEG)


def test_support_only_where_within_the_angle_and_as_the_formula():
    rng = np.random.default_rng(1)
    segs = _random_segments(rng, 60)
    theta = np.radians(np.arange(0, 360, 1.0))
    dirs = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], axis=1)  # horizontals
    cfg = VPConfig()
    s = vanishing._prepare(segs, K, cfg)
    sup = vanishing._support(s, K, dirs, s.valid, cfg)
    ang = _angles_direct(segs[s.valid], dirs)
    expected = np.clip(1 - (ang / cfg.support_angle_deg) ** 2, 0, None) * s.length[s.valid, None]
    np.testing.assert_allclose(sup, expected, atol=1e-6)
    assert (sup > 0).any()


def test_cross_and_perpendicular():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(7, 5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(vanishing._cross(a, b), np.cross(a, b), atol=1e-12)
    v = rng.normal(size=(50, 3))
    v[0] = [0, 0, 1]
    p = vanishing._perpendicular(v)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(p * v, axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(vanishing._perpendicular(v[3]), p[3], atol=1e-12)


def _match_direct(pred: np.ndarray, det: np.ndarray, cfg: LineConfig) -> list[tuple[int, int]]:
    """The tracking gates pair by pair, then greedy one-to-one by cost."""
    cands = []
    for i, p in enumerate(pred):
        lp = np.linalg.norm(p[2:] - p[:2])
        u = (p[2:] - p[:2]) / lp
        n = np.array([-u[1], u[0]])
        for j, d in enumerate(det):
            ld = np.linalg.norm(d[2:] - d[:2])
            cos = u @ (d[2:] - d[:2]) / ld
            dist = (abs((d[:2] - p[:2]) @ n) + abs((d[2:] - p[:2]) @ n)) / 2
            t = sorted([(d[:2] - p[:2]) @ u, (d[2:] - p[:2]) @ u])
            overlap = (np.clip(t[1], 0, lp) - np.clip(t[0], 0, lp)) / min(lp, ld)
            if (
                cos >= np.cos(np.radians(cfg.match_angle_deg))
                and dist <= cfg.match_distance_px
                and overlap >= cfg.min_overlap
            ):
                angle = np.degrees(np.arccos(min(1.0, cos)))
                cands.append((dist + 0.5 * angle + 2.0 * (1 - min(overlap, 1.0)), i, j))
    used_p, used_d, out = set(), set(), []
    for _, i, j in sorted(cands):
        if i not in used_p and j not in used_d:
            used_p.add(i)
            used_d.add(j)
            out.append((i, j))
    return sorted(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_match_predicted_equals_pairwise_gates(seed):
    rng = np.random.default_rng(seed)
    det = _random_segments(rng, 80)
    det[:20, 2:] = det[:20, :2] + (det[:20, 2:] - det[:20, :2]) * 0.3  # some short ones
    moved = det[:50] + rng.normal(0, 2.0, (50, 4))  # predictions near half of the detections
    pred = np.vstack([moved, _random_segments(rng, 30)])
    cfg = LineConfig()
    fast = sorted(map(tuple, match_predicted(pred, det, cfg).tolist()))
    assert fast == _match_direct(pred, det, cfg)
    assert len(fast) > 20
