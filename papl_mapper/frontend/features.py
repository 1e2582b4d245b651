"""Wide-baseline point features: SIFT keypoints on keyframes, matched across keyframes that KLT does not link.

KLT follows corners from frame to frame and breaks at a jump: a dropped or corrupt frame, a cut, a
large `--step`, a folder of photos taken a step apart. The frames on both sides of a break are
keyframes, and the keyframes near a weak link (a break, or few KLT tracks shared) get SIFT keypoints
of their own, so they repeat under the rotation and scale change of a wide baseline. Keyframe pairs
that a weak link separates are matched (every pair in a photo set: covisible keyframes far apart in
the recording make long tracks): RootSIFT ratio test, closest match per keypoint, essential-matrix
USAC. Verified matches are chained into tracks by union-find, never two observations of one track in
one frame, and these tracks join the KLT point observations with ids of their own, so registration
(PnP, triangulation, revisits) carries on across the break.

SIFT, not ORB: its keypoints are localised to a fraction of a pixel in scale space where ORB's sit on
the integer grid of a pyramid level (inliers fit their epipolar geometry several times closer), and it
verifies more matches between neighbouring real images, at about ten times ORB's detection time
(benchmarks/results/features.json); the real photo set maps more accurately with it. Each keypoint
also gets the 32-byte ORB descriptor that KLT corners get on keyframes (`describe_corners`), so track
completion and revisits compare one kind of descriptor across both kinds of track.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from papl_mapper.frontend.descriptors import describe_corners
from papl_mapper.geometry.two_view import find_essential

log = logging.getLogger(__name__)


@dataclass
class FeatureConfig:
    """Settings of the wide-baseline features and their matching."""

    enabled: bool = True
    """Detect SIFT keypoints on keyframes and match them across weak KLT links."""
    max_features: int = 2000
    """Most SIFT keypoints per keyframe (the strongest)."""
    contrast_threshold: float = 0.004
    """SIFT's contrast threshold (OpenCV's default is 0.04). Low: low-contrast walls still give
    keypoints (at the default, a nearly blank corridor wall gives a tenth of ORB's FAST corners at
    threshold 5), and the `max_features` cap keeps the strongest where there are many."""
    break_survival: float = 0.5
    """A frame that keeps fewer than this fraction of the previous frame's KLT tracks is a break: it
    and the frame before it become keyframes."""
    weak_link_tracks: int = 80
    """Consecutive keyframes sharing fewer KLT tracks than this are a weak link, matched by features."""
    window: int = 8
    """Keyframe pairs at most this many keyframes apart, with a weak link between them, are matched."""
    exhaustive_below: int = 40
    """With at most this many keyframes next to weak links (a photo set), all their pairs are matched."""
    ratio: float = 0.8
    """Lowe ratio of the best to the second-best descriptor distance."""
    ransac_threshold_px: float = 2.0
    """Essential-matrix inlier threshold of the verification (pixels)."""
    min_inliers: int = 25
    """Fewest verified matches for a keyframe pair to contribute."""
    min_inlier_ratio: float = 0.25
    """...and at least this fraction of its matches (COLMAP's two-view default): a pair of look-alike
    views gathers many matches of which a few fit some geometry by chance."""


@dataclass
class KeyframeFeatures:
    """SIFT keypoints of the keyframes: frame row, undistorted pixels, RootSIFT descriptor (for matching,
    kept as 255ths: a quarter of the memory of floats for keyframes held until the end) and ORB
    descriptor (for the tracks) per keypoint."""

    frame: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)
    sift: list[np.ndarray] = field(default_factory=list)
    desc: list[np.ndarray] = field(default_factory=list)

    def add(self, row: int, uv: np.ndarray, sift: np.ndarray, desc: np.ndarray) -> None:
        self.frame.append(np.full(len(uv), row, np.int64))
        self.uv.append(np.asarray(uv, np.float64).reshape(-1, 2))
        self.sift.append(np.round(np.asarray(sift, np.float32).reshape(-1, 128) * 255).astype(np.uint8))
        self.desc.append(np.asarray(desc, np.uint8).reshape(-1, 32))


class SiftDetector:
    """SIFT keypoints of one gray image with RootSIFT descriptors, and the ORB descriptor of each.

    `detect` may run in several threads at once (OpenCV's SIFT barely uses a second core by itself):
    each thread gets its own OpenCV detectors."""

    def __init__(self, config: FeatureConfig):
        self._config = config
        self._local = threading.local()

    def _detectors(self) -> tuple[cv2.SIFT, cv2.ORB]:
        d = getattr(self._local, "detectors", None)
        if d is None:
            cfg = self._config
            d = self._local.detectors = (
                cv2.SIFT_create(cfg.max_features, 3, cfg.contrast_threshold, 10, 1.6),
                cv2.ORB_create(edgeThreshold=15, patchSize=15),
            )
        return d

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoint pixels (N, 2), RootSIFT descriptors (N, 128) float32 (unit length) and ORB
        descriptors (N, 32) uint8; keypoints too near the border for ORB are left out."""
        sift_detector, orb = self._detectors()
        kps, sift = sift_detector.detectAndCompute(gray, None)
        if sift is None or not kps:
            return np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros((0, 32), np.uint8)
        uv = np.array([k.pt for k in kps], np.float64)
        rows, desc = describe_corners(orb, gray, uv)
        return uv[rows], root_sift(sift[rows]), desc


def root_sift(sift: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic and Zisserman): L1-normalised, square-rooted, so that the dot product of
    two descriptors is the Hellinger kernel, which matches better than SIFT's Euclidean distance."""
    d = np.asarray(sift, np.float32)
    d = d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d)


@dataclass
class FeatureTracks:
    """Point observations of the feature tracks, in the layout of `Tracks`' point arrays."""

    frame: np.ndarray  # (K,) int64 frame rows
    track: np.ndarray  # (K,) int64 track ids (from `first_id`)
    uv: np.ndarray  # (K, 2) undistorted pixels
    desc: np.ndarray  # (K, 32) uint8, the descriptor of each observation
    pairs_verified: int = 0
    geometry: list[tuple[int, int, np.ndarray]] = field(default_factory=list)
    """(frame row a, frame row b, essential matrix E with x_b^T E x_a = 0) of each verified pair."""


def _unit(q: np.ndarray) -> np.ndarray:
    """Unit-length float rows of quantised descriptors."""
    d = q.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def match_pair(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Matches of unit descriptors passing Lowe's ratio test, one per keypoint of b (the closest):
    (M, 2) rows (ia, ib) and their distances (M,)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    sim = desc_a @ desc_b.T  # cosine of unit vectors: squared distance 2 - 2 sim
    ia = np.arange(len(desc_a))
    ib = np.argmax(sim, axis=1)
    best = sim[ia, ib]
    sim[ia, ib] = -np.inf
    d1 = np.maximum(2.0 - 2.0 * best, 0.0)
    d2 = np.maximum(2.0 - 2.0 * sim.max(axis=1), 0.0)
    ok = d1 <= ratio**2 * d2
    m = np.column_stack([ia[ok], ib[ok], np.sqrt(d1[ok])])
    m = m[np.lexsort((m[:, 2], m[:, 1]))]  # by keypoint of b, closest first
    first = np.ones(len(m), bool)
    first[1:] = m[1:, 1] != m[:-1, 1]
    m = m[first]
    return m[:, :2].astype(np.int64), m[:, 2]


def verify_pair(
    uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, threshold_px: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray | None]:
    """Inlier mask of matched undistorted pixels under an essential matrix (OpenCV's USAC), and the
    matrix (None where none was found).

    The essential matrix, not the fundamental: with the camera known it has 5 degrees of freedom
    instead of 7, so look-alike textures (repeated tiles, doors) fit it far less often. USAC rather
    than plain RANSAC: far faster on wide-baseline pairs with few inliers. Under a pure
    rotation the matrix is degenerate, but its inliers still agree with the rotation, which is all
    that chaining tracks needs.
    """
    if len(uv_a) < 8:
        return np.zeros(len(uv_a), bool), None
    cv2.setRNGSeed(seed)
    E, mask = find_essential(uv_a, uv_b, K, cv2.USAC_FAST, threshold_px)
    if E is None or mask is None or E.shape[0] < 3:
        return np.zeros(len(uv_a), bool), None
    return mask.ravel().astype(bool), E[:3]  # the first of several stacked solutions, the mask's


def candidate_pairs(keyframes: np.ndarray, weak: np.ndarray, cfg: FeatureConfig) -> list[tuple[int, int]]:
    """Keyframe index pairs (i, j), i < j, to match: a weak link lies between them.

    `weak[i]` says whether keyframes i and i+1 share too few KLT tracks. Pairs up to `window`
    keyframes apart; every pair when the keyframes next to weak links are at most `exhaustive_below` (a
    photo set), KLT-linked or not: matching covisible keyframes far apart makes the long tracks.
    """
    n = len(keyframes)
    if n < 2 or not weak.any():
        return []
    breaks = np.concatenate([[0], np.cumsum(weak)])  # weak links before each keyframe
    near = np.zeros(n, bool)
    near[:-1] |= weak
    near[1:] |= weak
    exhaustive = near.sum() <= cfg.exhaustive_below
    pairs = []
    for i in range(n):
        for j in range(i + 1, n if exhaustive else min(n, i + cfg.window + 1)):
            if exhaustive or breaks[j] > breaks[i]:
                pairs.append((i, j))
    return pairs


def weak_links(
    point_frame: np.ndarray,
    point_track: np.ndarray,
    keyframes: np.ndarray,
    min_shared: int,
    breaks: np.ndarray | None = None,
) -> np.ndarray:
    """(len(keyframes) - 1,) True where consecutive keyframes share fewer than `min_shared` tracks, or
    where a break (a frame that kept too few of the previous frame's KLT tracks: `breaks`, frame rows)
    lies between them: the tracks across a jump are few and short even when they pass the count.

    `point_frame` is in frame order (as the frontend writes it), so each frame's rows are one slice.
    """
    weak = np.zeros(max(0, len(keyframes) - 1), bool)
    bounds = np.searchsorted(point_frame, np.stack([keyframes, keyframes + 1]))
    prev = None
    for i, (lo, hi) in enumerate(bounds.T.tolist()):
        ids = point_track[lo:hi]
        if prev is not None:
            weak[i - 1] = len(np.intersect1d(prev, ids)) < min_shared
        prev = ids
    if breaks is not None and len(breaks) and len(weak):
        # the link before keyframe i+1 holds the breaks at frames keyframes[i] + 1 .. keyframes[i+1]
        after = np.searchsorted(keyframes, np.asarray(breaks), side="left") - 1
        after = after[(after >= 0) & (after < len(weak))]
        weak[after] = True
    return weak


def chain_tracks(
    node_frame: np.ndarray | list[set[int]], edges: np.ndarray, edge_cost: np.ndarray
) -> np.ndarray:
    """Union-find of matched nodes into tracks, best matches first, never two nodes of one frame.

    A node is a keypoint (`node_frame` holds its frame) or a track of its own (its set of frames).
    Returns a component label per node, -1 for nodes left alone.
    """
    n = len(node_frame)
    parent = np.arange(n)
    frames: dict[int, set[int]] = {}

    def frames_of(a: int) -> set[int]:
        f = node_frame[a]
        return set(f) if isinstance(f, set) else {int(f)}

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = int(parent[a])
        return a

    for e in np.argsort(edge_cost, kind="stable").tolist():
        a, b = root(int(edges[e, 0])), root(int(edges[e, 1]))
        if a == b:
            continue
        fa = frames.get(a) or frames_of(a)
        fb = frames.get(b) or frames_of(b)
        if fa & fb:
            continue  # would see one track twice in a frame: a wrong match somewhere
        if len(fa) < len(fb):
            a, b, fa, fb = b, a, fb, fa
        parent[b] = a
        fa |= fb
        frames[a] = fa
        frames.pop(b, None)
    roots = np.array([root(i) for i in range(n)])
    label = np.full(n, -1, np.int64)
    uniq, inv, counts = np.unique(roots, return_inverse=True, return_counts=True)
    multi = counts[inv] >= 2
    _, label[multi] = np.unique(inv[multi], return_inverse=True)
    return label


def feature_tracks(
    feats: KeyframeFeatures,
    K: np.ndarray,
    point_frame: np.ndarray,
    point_track: np.ndarray,
    first_id: int,
    cfg: FeatureConfig,
    workers: int = 1,
    seed: int = 0,
    breaks: np.ndarray | None = None,
) -> FeatureTracks:
    """Match the keyframes' SIFT keypoints across weak KLT links (`weak_links`; `breaks`: frame rows
    of the breaks) and chain them into tracks; `workers` threads match the keyframe pairs; `seed` seeds
    the verification's RANSAC."""
    empty = FeatureTracks(
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
    )
    if not feats.frame:
        return empty
    node_frame = np.concatenate(feats.frame)
    node_uv = np.concatenate(feats.uv)
    node_sift = np.concatenate(feats.sift)
    node_desc = np.concatenate(feats.desc)
    keyframes = np.unique(node_frame)
    starts = np.searchsorted(node_frame, keyframes) if np.all(np.diff(node_frame) >= 0) else None
    if starts is None:  # keypoints were added out of frame order
        order = np.argsort(node_frame, kind="stable")
        node_frame, node_uv = node_frame[order], node_uv[order]
        node_sift, node_desc = node_sift[order], node_desc[order]
        starts = np.searchsorted(node_frame, keyframes)
    ends = np.append(starts[1:], len(node_frame))
    weak = weak_links(point_frame, point_track, keyframes, cfg.weak_link_tracks, breaks)
    pairs = candidate_pairs(keyframes, weak, cfg)

    used = sorted({k for pair in pairs for k in pair})
    unit = {k: _unit(node_sift[starts[k] : ends[k]]) for k in used}  # once per keyframe, not per pair

    def link(pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, tuple[int, int, np.ndarray]] | None:
        """Verified matches of one keyframe pair as node rows (M, 2), their distances and the pair's
        geometry (frame rows and essential matrix), or None."""
        sa, sb = (slice(starts[k], ends[k]) for k in pair)
        m, dist = match_pair(unit[pair[0]], unit[pair[1]], cfg.ratio)
        if len(m) < cfg.min_inliers:
            return None
        ok, E = verify_pair(node_uv[sa][m[:, 0]], node_uv[sb][m[:, 1]], K, cfg.ransac_threshold_px, seed)
        if E is None or ok.sum() < max(cfg.min_inliers, cfg.min_inlier_ratio * len(m)):
            return None
        geometry = (int(keyframes[pair[0]]), int(keyframes[pair[1]]), E)
        return np.column_stack([m[ok, 0] + sa.start, m[ok, 1] + sb.start]), dist[ok], geometry

    # BLAS and OpenCV release the GIL: pairs are matched in parallel, the results kept in pair order;
    # one BLAS thread per worker, as the workers already fill the cores (with BLAS's own threads on top,
    # the descriptor products took half as long again)
    blas = threadpool_limits(limits=1, user_api="blas") if workers > 1 else contextlib.nullcontext()
    with blas, ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="features") as pool:
        links = [r for r in pool.map(link, pairs) if r is not None]
    verified = len(links)
    edges, costs = [e for e, _, _ in links], [c for _, c, _ in links]
    if not edges:
        log.debug("features: %d keyframe pairs matched, none verified", len(pairs))
        return empty
    label = chain_tracks(node_frame, np.concatenate(edges), np.concatenate(costs))
    keep = label >= 0
    log.debug(
        "features: %d of %d keyframe pairs verified, %d tracks over %d keyframes",
        verified,
        len(pairs),
        label.max() + 1,
        len(keyframes),
    )
    return FeatureTracks(
        frame=node_frame[keep],
        track=label[keep] + first_id,
        uv=node_uv[keep],
        desc=node_desc[keep],
        pairs_verified=verified,
        geometry=[g for _, _, g in links],
    )
