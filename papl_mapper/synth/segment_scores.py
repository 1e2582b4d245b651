"""Scoring 2D segments against projected ground-truth segments (for tests and benchmarks).

A detection lies on a ground-truth segment when their directions differ by less than
`angle_deg` and both detected endpoints are within `dist_px` of the ground-truth segment.
"""

from __future__ import annotations

import numpy as np


def assign_to_gt(det: np.ndarray, gt: np.ndarray, dist_px: float = 3.0, angle_deg: float = 3.0) -> np.ndarray:
    """For each detection (D, 4) the row of the ground-truth segment (G, 4) it lies on, or -1."""
    det = np.asarray(det, np.float64).reshape(-1, 4)
    gt = np.asarray(gt, np.float64).reshape(-1, 4)
    out = np.full(len(det), -1, np.int64)
    if len(gt) == 0 or len(det) == 0:
        return out
    a, b = gt[:, :2], gt[:, 2:]
    L = np.maximum(np.linalg.norm(b - a, axis=1), 1e-9)
    ug = (b - a) / L[:, None]  # (G, 2)
    dd = det[:, 2:] - det[:, :2]
    ud = dd / np.maximum(np.linalg.norm(dd, axis=1), 1e-9)[:, None]
    cos = np.abs(ud @ ug.T)  # (D, G)
    dmax = np.zeros((len(det), len(gt)))
    for p in (det[:, :2], det[:, 2:]):
        r = p[:, None, :] - a[None]  # (D, G, 2)
        t = np.clip(np.einsum("dgk,gk->dg", r, ug), 0, L[None])
        dmax = np.maximum(dmax, np.linalg.norm(r - t[..., None] * ug[None], axis=2))
    ok = (cos >= np.cos(np.radians(angle_deg))) & (dmax <= dist_px)
    dmax = np.where(ok, dmax, np.inf)
    best = np.argmin(dmax, axis=1)
    has = np.isfinite(dmax[np.arange(len(det)), best])
    out[has] = best[has]
    return out


def covered_fraction(det: np.ndarray, gt: np.ndarray, assigned: np.ndarray) -> np.ndarray:
    """(G,) fraction of each ground-truth segment's length covered by the detections assigned to it."""
    gt = np.asarray(gt, np.float64).reshape(-1, 4)
    out = np.zeros(len(gt))
    for g in np.unique(assigned[assigned >= 0]):
        a, b = gt[g, :2], gt[g, 2:]
        L = np.linalg.norm(b - a)
        if L < 1e-9:
            continue
        u = (b - a) / L
        cover = np.zeros(int(np.ceil(L)) + 1, bool)
        for i in np.flatnonzero(assigned == g):
            t = np.sort([(det[i, :2] - a) @ u, (det[i, 2:] - a) @ u])
            lo, hi = int(np.clip(np.floor(t[0]), 0, L)), int(np.clip(np.ceil(t[1]), 0, L))
            cover[lo : hi + 1] = True
        out[g] = cover.mean()
    return out


def detection_scores(
    det: np.ndarray, gt: np.ndarray, dist_px: float = 3.0, angle_deg: float = 3.0, min_cover: float = 0.5
) -> tuple[float, float, np.ndarray]:
    """Precision (detections on GT), recall (GT segments covered >= min_cover), the assignment."""
    assigned = assign_to_gt(det, gt, dist_px, angle_deg)
    precision = float(np.mean(assigned >= 0)) if len(det) else float("nan")
    recall = float(np.mean(covered_fraction(det, gt, assigned) >= min_cover)) if len(gt) else float("nan")
    return precision, recall, assigned


def track_match_precision(frames_ids: list[np.ndarray], frames_gt: list[np.ndarray]) -> tuple[int, int]:
    """Consecutive observations of one track on the same GT segment: (good, bad) counts.

    frames_ids[f]: track ids (K,) of frame f; frames_gt[f]: the GT id of each (K,), -1 where none.
    """
    last: dict[int, int] = {}
    good = bad = 0
    for ids, gids in zip(frames_ids, frames_gt, strict=True):
        for t, g in zip(ids.tolist(), gids.tolist(), strict=True):
            if g < 0:
                continue
            if t in last:
                if last[t] == g:
                    good += 1
                else:
                    bad += 1
            last[t] = g
    return good, bad
