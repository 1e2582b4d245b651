"""Line-map metrics, LIMAP-style: length-weighted recall and precision of 3D segments within tau.

recall(tau)    = length of ground-truth segments lying within tau of some estimated segment / GT length
precision(tau) = length of estimated segments lying within tau of some GT segment / estimated length

Both sample the measured segments at a fixed spacing (each sample stands for its share of length)
and decide coverage with the exact point-to-segment distance. Candidate segments come from a KD-tree
over points sampled along the target segments at spacing h: a segment within tau of a query has a
sample within tau + h/2, so querying that radius finds every candidate and the answer is exact.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from papl_mapper.errors import InputError

#: Queries per chunk at 8 candidates each in the exact-distance step (memory ~ chunk * 8 * 100 bytes).
_CHUNK = 131_072
#: Widest k-nearest query; queries still unsettled then take the exact ball of candidates.
_MAX_K = 2048


@dataclass
class Segments:
    """3D segments (S, 2, 3) and their axis ids (S,), -1 for non-structural."""

    endpoints: np.ndarray
    axis: np.ndarray

    def __len__(self) -> int:
        return len(self.endpoints)

    def lengths(self) -> np.ndarray:
        """(S,) segment lengths."""
        return np.linalg.norm(self.endpoints[:, 1] - self.endpoints[:, 0], axis=1)


def read_segments(path: str | os.PathLike) -> Segments:
    """Read `x1 y1 z1 x2 y2 z2 axis` rows ('#' comments); InputError naming file and line when malformed."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such segments file")
    rows, axes = [], []
    for k, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) not in (6, 7):
            raise InputError(f"{path}: line {k} has {len(parts)} values, expected 'x1 y1 z1 x2 y2 z2 axis'")
        try:
            xyz = [float(v) for v in parts[:6]]
            a = int(parts[6]) if len(parts) == 7 else -1
        except ValueError as exc:
            raise InputError(f"{path}: line {k} holds a non-number ({exc})") from exc
        if not np.isfinite(xyz).all():
            raise InputError(f"{path}: line {k} holds NaN or infinite values")
        rows.append(xyz)
        axes.append(a)
    return Segments(np.asarray(rows, np.float64).reshape(-1, 2, 3), np.asarray(axes, np.int64))


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact distances (...) from points p (..., 3) to segments [a, b] (..., 3), broadcasting."""
    ab = b - a
    ap = p - a
    den = np.einsum("...i,...i->...", ab, ab)
    t = np.clip(np.einsum("...i,...i->...", ap, ab) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


def sample_segments(endpoints: np.ndarray, spacing: float, include_ends: bool) -> tuple[np.ndarray, ...]:
    """Points along segments (S, 2, 3) no farther than `spacing` apart.

    include_ends=True: both ends and evenly spaced points in between (every point of a segment is then
    within spacing/2 of a sample). False: the midpoints of n equal pieces, each weighing length / n.
    Returns (points (Q, 3), owner segment index (Q,), weight (Q,)).
    """
    ends = np.asarray(endpoints, np.float64).reshape(-1, 2, 3)
    L = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    pieces = np.maximum(1, np.ceil(L / spacing)).astype(np.int64)
    n = pieces + 1 if include_ends else pieces
    owner = np.repeat(np.arange(len(ends)), n)
    start = np.cumsum(n) - n
    k = np.arange(len(owner)) - np.repeat(start, n)
    frac = k / np.repeat(pieces, n) if include_ends else (k + 0.5) / np.repeat(pieces, n)
    pts = ends[owner, 0] + frac[:, None] * (ends[owner, 1] - ends[owner, 0])
    weight = (L / pieces)[owner]
    return pts, owner, weight


def nearest_segment_distance(
    queries: np.ndarray,
    endpoints: np.ndarray,
    max_dist: float,
    spacing: float | None = None,
    levels: np.ndarray | None = None,
) -> np.ndarray:
    """(Q,) exact distance from each query point to the nearest segment, or inf where it exceeds max_dist.

    With `levels` (sorted thresholds <= max_dist) the search stops as soon as the answer to every
    "distance <= level?" is certain, and the value returned is a distance that answers them all
    correctly (an upper bound of the true one); this is what the coverage metrics need, and it is much
    faster where segments crowd. `spacing` is the sampling step along the target segments (default
    max_dist / 4): smaller means a larger tree but fewer candidates per query.
    """
    queries = np.asarray(queries, np.float64).reshape(-1, 3)
    ends = np.asarray(endpoints, np.float64).reshape(-1, 2, 3)
    out = np.full(len(queries), np.inf)
    if len(queries) == 0 or len(ends) == 0:
        return out
    h = spacing if spacing is not None else 0.25 * max_dist
    lv = None if levels is None else np.sort(np.asarray(levels, np.float64))
    pts, owner, _ = sample_segments(ends, h, include_ends=True)
    tree = cKDTree(pts)
    radius = max_dist + 0.5 * h
    todo = np.arange(len(queries))
    k = 8 if lv is None else 1  # levels: the nearest sample's segment settles most well-covered queries
    while len(todo):
        if k > _MAX_K:
            for r in todo:  # extremely crowded targets only: every candidate in the ball, one query at a time
                cand = np.unique(owner[tree.query_ball_point(queries[r], radius)])
                d = point_segment_distance(queries[r], ends[cand, 0], ends[cand, 1]).min()
                out[r] = d if d <= max_dist else np.inf
            break
        k = min(k, len(pts))
        saturated = []
        chunk = max(256, _CHUNK * 8 // k)  # about a million (query, candidate) pairs at a time
        for c0 in range(0, len(todo), chunk):
            rows = todo[c0 : c0 + chunk]
            dist, idx = tree.query(queries[rows], k=k, distance_upper_bound=radius)
            dist, idx = np.asarray(dist).reshape(len(rows), k), np.asarray(idx).reshape(len(rows), k)
            found = idx < len(pts)
            seg = owner[np.where(found, idx, 0)]
            d = point_segment_distance(queries[rows, None, :], ends[seg, 0], ends[seg, 1])
            d = np.where(found, d, np.inf).min(axis=1)
            d = np.minimum(out[rows], np.where(d <= max_dist, d, np.inf))
            out[rows] = d
            if k < len(pts):
                # a segment nearer than b has a sample within b + h/2; if the k-th sample is that near,
                # unseen samples could hold such a segment: look wider for these rows. b is the current
                # distance (exact mode) or the largest level below it (levels mode; none: settled)
                if lv is None:
                    b = np.minimum(d, max_dist)
                else:
                    below = np.searchsorted(lv, np.minimum(d, np.inf), side="left") - 1
                    b = np.where(below >= 0, lv[np.maximum(below, 0)], -np.inf)
                saturated.append(rows[found[:, -1] & (dist[:, -1] <= b + 0.5 * h)])
        todo = np.concatenate(saturated) if saturated else todo[:0]
        k = 8 if k == 1 else 4 * k
    return out


def covered_fraction(
    measured: np.ndarray,
    target: np.ndarray,
    taus: np.ndarray,
    spacing: float,
    labels: np.ndarray | None = None,
) -> tuple[np.ndarray, float, dict[int, np.ndarray]]:
    """Length fraction of `measured` segments within each tau of some `target` segment, their length,
    and the same fraction per label of the measured segments (when `labels` (S,) is given)."""
    taus = np.asarray(taus, np.float64)
    pts, owner, w = sample_segments(measured, spacing, include_ends=False)
    total = float(w.sum())
    if total <= 0:
        return np.full(len(taus), np.nan), 0.0, {}
    d = nearest_segment_distance(pts, target, float(taus.max()), levels=taus)
    covered = d[None, :] <= taus[:, None]  # (T, Q)
    fractions = (covered * w).sum(axis=1) / total
    per_label: dict[int, np.ndarray] = {}
    if labels is not None:
        lab = np.asarray(labels)[owner]
        for value in np.unique(lab):
            sel = lab == value
            per_label[int(value)] = (covered[:, sel] * w[sel]).sum(axis=1) / w[sel].sum()
    return fractions, total, per_label


def line_metrics(
    gt: np.ndarray, est: np.ndarray, taus: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(recall (T,), precision (T,), GT length, estimated length) for segment sets (S, 2, 3), (M, 2, 3)."""
    recall, gt_len, _ = covered_fraction(gt, est, taus, spacing)
    precision, est_len, _ = covered_fraction(est, gt, taus, spacing)
    if len(est) == 0 and gt_len > 0:
        recall = np.zeros(len(taus))
    return recall, precision, gt_len, est_len
