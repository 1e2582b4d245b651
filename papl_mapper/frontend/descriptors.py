"""Binary descriptors (ORB, LBD; 32 bytes): describing corners, Hamming distances, mutual-nearest matching."""

from __future__ import annotations

import cv2
import numpy as np

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def describe_corners(orb: cv2.ORB, gray: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors of given corners at their own position (one size, no orientation, level 0), the
    keyframe descriptor of every point track: rows (D,) of `uv` kept (ORB leaves out corners too near
    the border) and descriptors (D, 32) uint8."""
    kps = [cv2.KeyPoint(float(x), float(y), 15.0, -1, 0, 0, i) for i, (x, y) in enumerate(uv)]
    kps, desc = orb.compute(gray, kps)
    if desc is None or not kps:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    return np.array([k.class_id for k in kps], np.int64), desc


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances (A, B) between rows of two uint8 descriptor arrays."""
    a = np.asarray(a, np.uint8)
    b = np.asarray(b, np.uint8)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), np.int64)
    return _POPCOUNT[a[:, None, :] ^ b[None, :, :]].sum(axis=2, dtype=np.int64)


def hamming_pairs(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances (P,) between rows a[ia] and b[ib]."""
    if len(ia) == 0:
        return np.zeros(0, np.int64)
    return _POPCOUNT[np.asarray(a, np.uint8)[ia] ^ np.asarray(b, np.uint8)[ib]].sum(axis=1, dtype=np.int64)


def match_descriptors(
    desc_a: np.ndarray, desc_b: np.ndarray, max_hamming: int, ratio: float, allowed: np.ndarray | None = None
) -> np.ndarray:
    """Mutual nearest neighbours passing a distance and a ratio test; (M, 2) rows (ia, ib).

    `allowed` (A, B) bool restricts the candidates (a geometric gate); only those are compared.
    """
    na, nb = len(desc_a), len(desc_b)
    if na == 0 or nb == 0:
        return np.zeros((0, 2), np.int64)
    if allowed is not None:
        ia, ib = np.nonzero(allowed)
        return match_candidates(desc_a, desc_b, ia, ib, max_hamming, ratio)
    ham = hamming(desc_a, desc_b).astype(np.float64)
    best_b = np.argmin(ham, axis=1)
    best_a = np.argmin(ham, axis=0)
    second = np.partition(ham, 1, axis=1)[:, 1] if nb > 1 else np.full(na, np.inf)
    ia = np.arange(na)
    d = ham[ia, best_b]
    ok = (d <= max_hamming) & (best_a[best_b] == ia) & (d <= ratio * second)
    return np.stack([ia[ok], best_b[ok]], axis=1).astype(np.int64)


def match_candidates(
    desc_a: np.ndarray, desc_b: np.ndarray, ia: np.ndarray, ib: np.ndarray, max_hamming: int, ratio: float
) -> np.ndarray:
    """`match_descriptors` over the candidate pairs (ia[k], ib[k]) only (unique pairs): the same
    matches as a dense `allowed` with those pairs set, at a cost linear in the candidates, not A x B.

    A row's best is its nearest candidate (the lowest ib among equals), its second the next one
    (infinite when it has one candidate); a match is also the best of its ib among that one's
    candidates (the lowest ia among equals)."""
    ia, ib = np.asarray(ia, np.int64), np.asarray(ib, np.int64)
    if len(ia) == 0:
        return np.zeros((0, 2), np.int64)
    d = hamming_pairs(desc_a, desc_b, ia, ib)
    by_a = np.lexsort((ib, d, ia))  # per ia: nearest first, ties to the lowest ib
    first_a = np.ones(len(ia), bool)
    first_a[1:] = ia[by_a][1:] != ia[by_a][:-1]
    best = by_a[first_a]  # candidate index of each row's best
    nxt = np.flatnonzero(first_a) + 1  # the row's next candidate, if it is still the same row
    has_second = nxt < len(ia)
    has_second[has_second] = ia[by_a[nxt[has_second]]] == ia[best[has_second]]
    second = np.full(len(best), np.inf)
    second[has_second] = d[by_a[nxt[has_second]]]
    by_b = np.lexsort((ia, d, ib))  # per ib: nearest first, ties to the lowest ia
    first_b = np.ones(len(ib), bool)
    first_b[1:] = ib[by_b][1:] != ib[by_b][:-1]
    best_of_b = np.full(int(ib.max()) + 1, -1, np.int64)
    best_of_b[ib[by_b[first_b]]] = ia[by_b[first_b]]
    a, b, db = ia[best], ib[best], d[best]
    ok = (db <= max_hamming) & (best_of_b[b] == a) & (db <= ratio * second)
    return np.stack([a[ok], b[ok]], axis=1).astype(np.int64)
