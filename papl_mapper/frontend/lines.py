"""Line segments: detection (EDLines or LSD), fusion of collinear fragments, LBD, and tracking.

Segments are (S, 4) float arrays `x1 y1 x2 y2` in (distorted) pixels, oriented by polarity:
the brighter side is on the left of the direction p1 -> p2 (image y points down, so "left" is
the normal (dy, -dx)). Polarity makes tracking and LBD tell apart the two edges of a thin bar.

Tracking predicts each live segment in the next frame with the flow of the nearest tracked
points (inverse-distance weighted), then matches it to the new detections by angle, distance to
the predicted line and overlap, one to one in order of cost. LBD descriptors are computed on
keyframes for keyframe-to-keyframe matching and for re-finding recently lost segment tracks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from papl_mapper.frontend.descriptors import match_descriptors

log = logging.getLogger(__name__)


@dataclass
class LineConfig:
    """Settings of segment detection, fusion, tracking and LBD matching."""

    detector: Literal["edlines", "lsd"] = "edlines"
    """EDLines (cv2.ximgproc EdgeDrawing, fast) or LSD (cv2.createLineSegmentDetector)."""
    min_length_px: float = 25.0
    """Shortest segment kept (after fusion), in pixels of the processed image."""
    max_segments: int = 250
    """Keep at most this many segments per frame, the longest."""
    ed_gradient_threshold: int = 30
    """EdgeDrawing gradient threshold (lower finds weaker edges)."""
    ed_sigma: float = 1.0
    """EdgeDrawing Gaussian smoothing."""
    ed_line_fit_error_px: float = 1.0
    """EdgeDrawing largest line-fit error."""
    fuse: bool = True
    """Merge collinear fragments into one segment."""
    fuse_angle_deg: float = 2.0
    """Largest angle between fragments that are merged."""
    fuse_distance_px: float = 1.5
    """Largest distance of a fragment's endpoints to the other fragment's line."""
    fuse_gap_px: float = 20.0
    """Largest gap along the line between merged fragments."""
    match_angle_deg: float = 5.0
    """Tracking gate: angle between the predicted and the detected segment."""
    match_distance_px: float = 4.0
    """Tracking gate: mean distance of the detected endpoints to the predicted line."""
    min_overlap: float = 0.3
    """Tracking gate: overlap along the line over the shorter segment's length."""
    max_missed_frames: int = 4
    """A segment track survives this many frames without a detection (carried by the point flow)."""
    flow_neighbours: int = 6
    """Tracked points used to predict a segment's motion."""
    own_motion: bool = True
    """Segment tracks the point-flow prediction finds no detection for are matched again where their
    own last motion carries them: on blank walls the few tracked points lie far from the lines and
    predict them wrongly, while the lines themselves move smoothly."""
    lbd_max_hamming: int = 70
    """Largest Hamming distance (of 256 bits) of an LBD match."""
    lbd_ratio: float = 0.85
    """Lowe ratio of the best to the second-best LBD distance."""
    reassociate: bool = True
    """Give new segment tracks the id of a recently lost track with a matching LBD descriptor."""
    reassociate_radius_px: float = 30.0
    """A lost segment is re-found only if its midpoint is this close to where it was last seen."""
    lost_memory_frames: int = 60
    """How long (frames) a lost segment track can be re-found."""


class SegmentDetector:
    """EDLines or LSD on gray images, followed by length filtering, fusion and polarity orientation."""

    def __init__(self, config: LineConfig):
        self.config = config
        if config.detector == "edlines":
            self._ed = cv2.ximgproc.createEdgeDrawing()
            params = cv2.ximgproc.EdgeDrawing.Params()
            params.GradientThresholdValue = int(config.ed_gradient_threshold)
            params.Sigma = float(config.ed_sigma)
            params.LineFitErrorThreshold = float(config.ed_line_fit_error_px)
            params.MinLineLength = max(5, int(config.min_length_px // 2))
            self._ed.setParams(params)
        else:
            self._lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)

    def raw(self, gray: np.ndarray) -> np.ndarray:
        """Segments of the detector as is, (S, 4) float64."""
        if self.config.detector == "edlines":
            self._ed.detectEdges(gray)
            lines = self._ed.detectLines()
        else:
            lines = self._lsd.detect(gray)[0]
        if lines is None:
            return np.zeros((0, 4))
        return np.asarray(lines, np.float64).reshape(-1, 4)

    def detect(self, gray: np.ndarray) -> np.ndarray:
        """Fused, oriented segments longer than min_length_px, longest first, (S, 4) float64."""
        cfg = self.config
        segs = self.raw(gray)
        if cfg.fuse and len(segs) > 1:
            segs = fuse_collinear(segs, cfg.fuse_angle_deg, cfg.fuse_distance_px, cfg.fuse_gap_px)
        length = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
        keep = length >= cfg.min_length_px
        segs, length = segs[keep], length[keep]
        segs = segs[np.argsort(-length, kind="stable")[: cfg.max_segments]]
        return orient_by_polarity(segs, gray)


def fuse_collinear(segs: np.ndarray, angle_deg: float, dist_px: float, gap_px: float) -> np.ndarray:
    """Merge groups of nearly collinear fragments (angle, line distance and gap gates; transitive).

    Candidate pairs have endpoints within gap_px + dist_px of each other: detector fragments of
    one edge follow each other along it. Overlapping duplicates (LSD double responses) are kept.
    """
    segs = np.asarray(segs, np.float64).reshape(-1, 4)
    n = len(segs)
    if n < 2:
        return segs
    p1, p2 = segs[:, :2], segs[:, 2:]
    d = p2 - p1
    length = np.linalg.norm(d, axis=1)
    u = d / np.maximum(length, 1e-9)[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    # candidates: fragments with endpoints within the gap (EDLines chains do not overlap), similar angle
    ends = np.vstack([p1, p2])
    pairs = cKDTree(ends).query_pairs(gap_px + dist_px, output_type="ndarray") % n
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    if len(pairs) == 0:
        return segs
    key = np.unique(
        np.minimum(pairs[:, 0], pairs[:, 1]).astype(np.int64) * n + np.maximum(pairs[:, 0], pairs[:, 1])
    )
    ii, jj = key // n, key % n
    similar = np.abs(np.sum(u[ii] * u[jj], axis=1)) >= np.cos(np.radians(angle_deg))
    ii, jj = ii[similar], jj[similar]
    if len(ii) == 0:
        return segs
    # distance of j's endpoints to line i and of i's endpoints to line j
    dj1 = np.abs(np.sum((p1[jj] - p1[ii]) * nrm[ii], axis=1))
    dj2 = np.abs(np.sum((p2[jj] - p1[ii]) * nrm[ii], axis=1))
    di1 = np.abs(np.sum((p1[ii] - p1[jj]) * nrm[jj], axis=1))
    di2 = np.abs(np.sum((p2[ii] - p1[jj]) * nrm[jj], axis=1))
    close = np.maximum.reduce([dj1, dj2, di1, di2]) <= dist_px
    # gap between the intervals along i's direction
    tj1 = np.sum((p1[jj] - p1[ii]) * u[ii], axis=1)
    tj2 = np.sum((p2[jj] - p1[ii]) * u[ii], axis=1)
    lo, hi = np.minimum(tj1, tj2), np.maximum(tj1, tj2)
    gap = np.maximum(lo - length[ii], -hi)
    ok = close & (gap <= gap_px)
    if not ok.any():
        return segs
    _, label = connected_components(coo_matrix((np.ones(int(ok.sum())), (ii[ok], jj[ok])), shape=(n, n)))
    size = np.bincount(label)
    single = size[label] == 1
    multi = np.flatnonzero(~single)
    g = label[multi]
    # per group: length-weighted direction (signs aligned to the longest member) and centre
    longest = np.full(len(size), -1)
    order = multi[np.argsort(length[multi], kind="stable")]
    longest[label[order]] = order  # the last write per group is its longest member
    sign = np.where(np.sum(u[multi] * u[longest[g]], axis=1) < 0, -1.0, 1.0)
    dsum = np.zeros((len(size), 2))
    np.add.at(dsum, g, u[multi] * (sign * length[multi])[:, None])
    wsum = np.bincount(g, weights=length[multi], minlength=len(size))
    csum = np.zeros((len(size), 2))
    np.add.at(csum, g, ((p1[multi] + p2[multi]) / 2) * length[multi][:, None])
    groups = np.flatnonzero(size > 1)
    direction = dsum[groups] / np.linalg.norm(dsum[groups], axis=1)[:, None]
    centre = csum[groups] / wsum[groups][:, None]
    slot = np.full(len(size), -1)
    slot[groups] = np.arange(len(groups))
    k = slot[g]
    t1 = np.sum((p1[multi] - centre[k]) * direction[k], axis=1)
    t2 = np.sum((p2[multi] - centre[k]) * direction[k], axis=1)
    tmin = np.full(len(groups), np.inf)
    tmax = np.full(len(groups), -np.inf)
    np.minimum.at(tmin, k, np.minimum(t1, t2))
    np.maximum.at(tmax, k, np.maximum(t1, t2))
    merged = np.hstack([centre + tmin[:, None] * direction, centre + tmax[:, None] * direction])
    return np.vstack([segs[single], merged])


def orient_by_polarity(segs: np.ndarray, gray: np.ndarray, offset_px: float = 2.0) -> np.ndarray:
    """Swap endpoints so that the brighter side lies on the left normal (dy, -dx) of p1 -> p2."""
    segs = np.asarray(segs, np.float64).reshape(-1, 4).copy()
    if len(segs) == 0:
        return segs
    h, w = gray.shape[:2]
    t = np.linspace(0.2, 0.8, 5)
    p1, p2 = segs[:, None, :2], segs[:, None, 2:]
    pts = p1 + (p2 - p1) * t[None, :, None]  # (S, 5, 2)
    d = segs[:, 2:] - segs[:, :2]
    n = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    left = pts + offset_px * n[:, None, :]
    right = pts - offset_px * n[:, None, :]

    def sample(q: np.ndarray) -> np.ndarray:
        x = np.clip(np.rint(q[..., 0]).astype(np.intp), 0, w - 1)
        y = np.clip(np.rint(q[..., 1]).astype(np.intp), 0, h - 1)
        return gray[y, x].astype(np.float64)

    contrast = (sample(left) - sample(right)).sum(axis=1)
    flip = contrast < 0
    segs[flip] = segs[flip][:, [2, 3, 0, 1]]
    return segs


# -- LBD --------------------------------------------------------------------------------------


class LBD:
    """LBD binary descriptors (cv2.line_descriptor) of given segments, (D, 32) uint8."""

    def __init__(self) -> None:
        self._bd = cv2.line_descriptor.BinaryDescriptor_createBinaryDescriptor()
        self._bd.setNumOfOctaves(1)

    def compute(self, gray: np.ndarray, segs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors of the segments it could describe: rows (D,) into segs and (D, 32) uint8."""
        segs = np.asarray(segs, np.float64).reshape(-1, 4)
        if len(segs) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        kls = []
        for i, (x1, y1, x2, y2) in enumerate(segs.tolist()):
            kl = cv2.line_descriptor.KeyLine()
            kl.startPointX, kl.startPointY, kl.endPointX, kl.endPointY = x1, y1, x2, y2
            kl.sPointInOctaveX, kl.sPointInOctaveY, kl.ePointInOctaveX, kl.ePointInOctaveY = x1, y1, x2, y2
            length = float(np.hypot(x2 - x1, y2 - y1))
            kl.lineLength = length
            kl.numOfPixels = max(1, int(length))
            kl.angle = float(np.arctan2(y2 - y1, x2 - x1))
            kl.class_id = i
            kl.octave = 0
            kl.pt = ((x1 + x2) / 2, (y1 + y2) / 2)
            kl.size = length
            kl.response = length / max(gray.shape)
            kls.append(kl)
        kls, desc = self._bd.compute(gray, kls)
        if desc is None or not kls:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        return np.array([k.class_id for k in kls], np.int64), np.asarray(desc, np.uint8)


def match_keyframe_lines(
    segs_a: np.ndarray,
    desc_a: np.ndarray,
    segs_b: np.ndarray,
    desc_b: np.ndarray,
    config: LineConfig,
    max_angle_deg: float = 30.0,
) -> np.ndarray:
    """Match segments of two keyframes by LBD (mutual, ratio) with a loose polarity-aware angle gate.

    Returns (M, 2) row pairs into (segs_a, segs_b).
    """
    da = segs_a[:, 2:] - segs_a[:, :2]
    db = segs_b[:, 2:] - segs_b[:, :2]
    ua = da / np.maximum(np.linalg.norm(da, axis=1), 1e-9)[:, None]
    ub = db / np.maximum(np.linalg.norm(db, axis=1), 1e-9)[:, None]
    allowed = ua @ ub.T >= np.cos(np.radians(max_angle_deg))
    return match_descriptors(desc_a, desc_b, config.lbd_max_hamming, config.lbd_ratio, allowed)


# -- tracking ---------------------------------------------------------------------------------


def predict_segments(segs: np.ndarray, flow_from: np.ndarray, flow_to: np.ndarray, k: int) -> np.ndarray:
    """Move segments (S, 4) by the inverse-distance-weighted flow of the k nearest tracked points.

    With fewer than 2 tracked points the segments stay where they are (zero-motion prediction).
    """
    segs = np.asarray(segs, np.float64).reshape(-1, 4)
    if len(segs) == 0 or len(flow_from) < 2:
        return segs.copy()
    k = min(k, len(flow_from))
    tree = cKDTree(flow_from)
    q = np.vstack([segs[:, :2], segs[:, 2:], (segs[:, :2] + segs[:, 2:]) / 2])  # (3S, 2)
    dist, idx = tree.query(q, k=k)
    dist = dist.reshape(len(q), k)
    idx = idx.reshape(len(q), k)
    w = 1.0 / (dist + 5.0)
    flow = flow_to - flow_from
    f = np.sum(flow[idx] * w[..., None], axis=1) / w.sum(axis=1)[:, None]
    s = len(segs)
    # endpoints move with their own flow, plus the midpoint's as a regulariser
    f1 = 0.5 * f[:s] + 0.5 * f[2 * s :]
    f2 = 0.5 * f[s : 2 * s] + 0.5 * f[2 * s :]
    return np.hstack([segs[:, :2] + f1, segs[:, 2:] + f2])


def match_predicted(pred: np.ndarray, det: np.ndarray, config: LineConfig) -> np.ndarray:
    """One-to-one matches (M, 2) of predicted segments to detections by the tracking gates.

    The distance and overlap gates are evaluated only on the pairs that pass the angle gate and whose
    midpoints are close enough to overlap (a few percent of all pairs), not on the full (P, D) grid.
    """
    if len(pred) == 0 or len(det) == 0:
        return np.zeros((0, 2), np.int64)
    dp = pred[:, 2:] - pred[:, :2]
    lp = np.maximum(np.linalg.norm(dp, axis=1), 1e-9)
    up = dp / lp[:, None]
    dd = det[:, 2:] - det[:, :2]
    ld = np.maximum(np.linalg.norm(dd, axis=1), 1e-9)
    ud = dd / ld[:, None]
    cos = up @ ud.T  # (P, D), polarity-aware
    # overlapping segments have midpoints within half their summed lengths (plus the line distance)
    mid_p = (pred[:, :2] + pred[:, 2:]) / 2
    mid_d = (det[:, :2] + det[:, 2:]) / 2
    reach = 0.5 * (lp[:, None] + ld[None, :]) + config.match_distance_px
    gap2 = np.square(mid_p[:, None, 0] - mid_d[None, :, 0]) + np.square(mid_p[:, None, 1] - mid_d[None, :, 1])
    pi, di = np.nonzero((cos >= np.cos(np.radians(config.match_angle_deg))) & (gap2 <= reach * reach))
    if len(pi) == 0:
        return np.zeros((0, 2), np.int64)
    c = cos[pi, di]
    p1, u, n = pred[pi, :2], up[pi], np.stack([-up[pi, 1], up[pi, 0]], axis=1)
    r1 = det[di, :2] - p1  # (C, 2) detected endpoints relative to the predicted start
    r2 = det[di, 2:] - p1
    # mean distance of the detected endpoints to the predicted line
    dist = 0.5 * (np.abs(np.sum(r1 * n, axis=1)) + np.abs(np.sum(r2 * n, axis=1)))
    t1 = np.sum(r1 * u, axis=1)
    t2 = np.sum(r2 * u, axis=1)
    lo = np.clip(np.minimum(t1, t2), 0, lp[pi])
    hi = np.clip(np.maximum(t1, t2), 0, lp[pi])
    overlap = (hi - lo) / np.minimum(lp[pi], ld[di])
    ok = (dist <= config.match_distance_px) & (overlap >= config.min_overlap)
    if not ok.any():
        return np.zeros((0, 2), np.int64)
    pi, di = pi[ok], di[ok]
    angle = np.degrees(np.arccos(np.clip(c[ok], -1, 1)))
    cost = dist[ok] + 0.5 * angle + 2.0 * (1.0 - np.minimum(overlap[ok], 1.0))
    order = np.argsort(cost, kind="stable")
    used_p, used_d, out = set(), set(), []
    for a, b in zip(pi[order].tolist(), di[order].tolist(), strict=True):
        if a in used_p or b in used_d:
            continue
        used_p.add(a)
        used_d.add(b)
        out.append((a, b))
    return np.array(out, np.int64).reshape(-1, 2)


class LineTracker:
    """Stateful segment tracker of one recording: `step` once per frame, `keyframe` on keyframes."""

    def __init__(self, config: LineConfig):
        self.config = config
        self.ids = np.zeros(0, np.int64)
        self.segs = np.zeros((0, 4))
        self.next_id = 0
        self.frame = -1
        self.born: dict[int, int] = {}
        self.aliases: dict[int, int] = {}
        self._kf: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # live id -> (segment, LBD) at last keyframe
        self._lost_ids = np.zeros(0, np.int64)
        self._lost_segs = np.zeros((0, 4))
        self._lost_desc = np.zeros((0, 32), np.uint8)
        self._lost_at = np.zeros(0, np.int64)
        # tracks not detected in the last frame(s), carried by the flow for max_missed_frames
        self._coast_ids = np.zeros(0, np.int64)
        self._coast_segs = np.zeros((0, 4))
        self._coast_miss = np.zeros(0, np.int64)
        self._motion = (np.zeros(0, np.int64), np.zeros((0, 2)))  # live ids, their last image motion

    def step(self, det: np.ndarray, flow_from: np.ndarray | None, flow_to: np.ndarray | None) -> np.ndarray:
        """Assign track ids to this frame's detections (S, 4); returns the ids (S,) int64.

        flow_from/flow_to: (N, 2) positions of point tracks in the previous and this frame;
        None after a break in tracking (all segment tracks end).
        """
        self.frame += 1
        det = np.asarray(det, np.float64).reshape(-1, 4)
        ids = np.full(len(det), -1, np.int64)
        cand_ids = np.concatenate([self.ids, self._coast_ids])
        if flow_from is not None and len(cand_ids):
            cand_segs = np.vstack([self.segs, self._coast_segs])
            cand_miss = np.concatenate([np.zeros(len(self.ids), np.int64), self._coast_miss])
            pred = predict_segments(cand_segs, flow_from, flow_to, self.config.flow_neighbours)
            m = match_predicted(pred, det, self.config)
            if self.config.own_motion and len(self._motion[0]):
                m = np.vstack([m, self._match_own_motion(cand_segs, cand_ids, det, m)])
            ids[m[:, 1]] = cand_ids[m[:, 0]]
            missed = np.ones(len(cand_ids), bool)
            missed[m[:, 0]] = False
            miss = cand_miss + 1
            coast = missed & (miss <= self.config.max_missed_frames)
            self._coast_ids, self._coast_segs, self._coast_miss = cand_ids[coast], pred[coast], miss[coast]
            lost = cand_ids[missed & ~coast]
        else:
            lost = cand_ids
            self._coast_ids, self._coast_segs = np.zeros(0, np.int64), np.zeros((0, 4))
            self._coast_miss = np.zeros(0, np.int64)
        self._forget(lost)
        new = ids < 0
        ids[new] = np.arange(self.next_id, self.next_id + new.sum())
        for i in ids[new].tolist():
            self.born[i] = self.frame
        self.next_id += int(new.sum())
        self._motion = self._track_motion(ids, det)
        self.ids, self.segs = ids, det
        return ids.copy()

    def _track_motion(self, ids: np.ndarray, det: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sorted ids (N,) of the segment tracks detected in this frame and the previous one, and their image
        motion (N, 2) between the two: the mean of the endpoints' (the tracking gates are about the line's
        position, not its extent)."""
        common, now, prev = np.intersect1d(ids, self.ids, assume_unique=True, return_indices=True)
        d = det[now] - self.segs[prev]
        return common, 0.5 * (d[:, :2] + d[:, 2:])

    def _match_own_motion(
        self, cand_segs: np.ndarray, cand_ids: np.ndarray, det: np.ndarray, matched: np.ndarray
    ) -> np.ndarray:
        """Matches (M, 2) of the candidates the flow left unmatched, moved by their own last motion, to
        the detections still free."""
        moved_ids, motion = self._motion
        free_c = np.isin(cand_ids, moved_ids)
        free_c[matched[:, 0]] = False
        free_d = np.ones(len(det), bool)
        free_d[matched[:, 1]] = False
        rows_c, rows_d = np.flatnonzero(free_c), np.flatnonzero(free_d)
        if len(rows_c) == 0 or len(rows_d) == 0:
            return np.zeros((0, 2), np.int64)
        shift = motion[np.searchsorted(moved_ids, cand_ids[rows_c])]
        pred = cand_segs[rows_c] + np.hstack([shift, shift])
        m = match_predicted(pred, det[rows_d], self.config)
        return np.column_stack([rows_c[m[:, 0]], rows_d[m[:, 1]]]).reshape(-1, 2)

    def _forget(self, lost: np.ndarray) -> None:
        for i in lost.tolist():
            self.born.pop(i, None)
        if not self.config.reassociate:
            return
        keep = [i for i in lost.tolist() if i in self._kf]
        if not keep:
            return
        self._lost_ids = np.concatenate([self._lost_ids, np.array(keep, np.int64)])
        self._lost_segs = np.vstack([self._lost_segs, np.array([self._kf[i][0] for i in keep])])
        self._lost_desc = np.vstack([self._lost_desc, np.array([self._kf.pop(i)[1] for i in keep])])
        self._lost_at = np.concatenate([self._lost_at, np.full(len(keep), self.frame)])

    def keyframe(
        self, gray: np.ndarray, lbd: LBD, scale_xy: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """LBD of the live segments; re-associates young tracks with lost ones. Returns ids, (D, 32).

        scale_xy: size of `gray` over the size of the frame the segments were detected in (LBD on
        a downscaled image is cheaper); None when they are the same.
        """
        segs = self.segs
        if scale_xy is not None and np.any(np.asarray(scale_xy) != 1.0):
            sx, sy = scale_xy
            segs = (segs + 0.5) * np.array([sx, sy, sx, sy]) - 0.5
        rows, desc = lbd.compute(gray, segs)
        if self.config.reassociate and len(rows):
            self._reassociate(rows, desc)
        ids = self.ids[rows]
        self._kf = {i: (self.segs[r], d) for i, r, d in zip(ids.tolist(), rows.tolist(), desc, strict=True)}
        self.born.clear()
        keep = self.frame - self._lost_at <= self.config.lost_memory_frames
        self._lost_ids, self._lost_segs = self._lost_ids[keep], self._lost_segs[keep]
        self._lost_desc, self._lost_at = self._lost_desc[keep], self._lost_at[keep]
        return ids, desc

    def _reassociate(self, rows: np.ndarray, desc: np.ndarray) -> None:
        cfg = self.config
        young = np.array([int(self.ids[r]) in self.born for r in rows], bool)
        if not young.any() or len(self._lost_ids) == 0:
            return
        yr = np.flatnonzero(young)
        segs_y = self.segs[rows[yr]]
        mid_y = (segs_y[:, :2] + segs_y[:, 2:]) / 2
        mid_l = (self._lost_segs[:, :2] + self._lost_segs[:, 2:]) / 2
        born = np.array([self.born[int(self.ids[rows[y]])] for y in yr])
        near = np.linalg.norm(mid_y[:, None] - mid_l[None], axis=2) <= cfg.reassociate_radius_px
        dy = segs_y[:, 2:] - segs_y[:, :2]
        dl = self._lost_segs[:, 2:] - self._lost_segs[:, :2]
        cos = (dy @ dl.T) / np.maximum(np.outer(np.linalg.norm(dy, axis=1), np.linalg.norm(dl, axis=1)), 1e-9)
        allowed = near & (cos >= np.cos(np.radians(10.0))) & (born[:, None] >= self._lost_at[None, :])
        m = match_descriptors(desc[yr], self._lost_desc, cfg.lbd_max_hamming, cfg.lbd_ratio, allowed)
        if len(m) == 0:
            return
        for y, l in m.tolist():
            row = rows[yr[y]]
            self.aliases[int(self.ids[row])] = int(self._lost_ids[l])
            self.ids[row] = self._lost_ids[l]
        keep = np.ones(len(self._lost_ids), bool)
        keep[m[:, 1]] = False
        self._lost_ids, self._lost_segs = self._lost_ids[keep], self._lost_segs[keep]
        self._lost_desc, self._lost_at = self._lost_desc[keep], self._lost_at[keep]
        log.debug("re-associated %d segment tracks", len(m))

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Map track ids through the re-association aliases to their oldest id."""
        out = ids.copy()
        for young, old in self.aliases.items():
            while old in self.aliases:
                old = self.aliases[old]
            out[ids == young] = old
        return out
