"""Revisits: a keyframe that sees a place mapped long before is matched to the old points and the loop closed.

The keyframe's ORB descriptors are matched to those of map points whose tracks ended at least
`min_gap_frames` earlier and that the tracked pose projects near them (guided search, ratio test,
mutual best), and PnP with RANSAC on the old 3D points verifies the match geometrically.
Closing the loop spreads the drift (the Sim(3) between the tracked pose and the pose from the
old points) over the frames since the old visit, then fuses each matched track into the old one,
so later PnP, triangulation and bundle adjustment see one 3D point per place. `RevisitGate` decides
which verified revisits close a loop: a small correction at once, a large one (drift in scale) only
when consecutive keyframes find the same correction, as ORB-SLAM asks of its loop candidates, from
old points triangulated well enough to place the camera.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from papl_mapper.frontend.descriptors import match_candidates
from papl_mapper.geometry.se3 import similarity_T_cw, so3_exp, so3_log
from papl_mapper.mapping.point_store import PointStore
from papl_mapper.mapping.tracking import PnPConfig, track_pnp
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class RevisitConfig:
    """Thresholds of revisit detection and loop closure."""

    enabled: bool = True
    """Look for revisits at every frontend keyframe."""
    min_gap_frames: int = 90
    """Only map points whose tracks ended at least this many frames before count as an old visit."""
    match_ratio: float = 0.8
    """Lowe ratio of the best to the second-best ORB distance."""
    max_hamming: int = 64
    """Largest Hamming distance (of 256 bits) of a descriptor match."""
    min_inliers: int = 20
    """Fewest PnP inliers on the old points for a revisit."""
    ransac_threshold_px: float = 3.0
    """PnP inlier threshold of the verification."""
    search_radius_px: float = 40.0
    """An old point is matched only to keypoints this close to where the tracked pose projects it,
    so look-alike places elsewhere (repeated doors, windows) cannot match."""
    max_drift: float = 0.05
    """Largest distance between the tracked and the revisit camera centre, as a fraction of the path
    walked since the old visit, that one keyframe's revisit corrects by itself."""
    max_drift_deg: float = 20.0
    """Largest rotation between the tracked and the revisit pose."""
    confirm_keyframes: int = 2
    """A larger correction needs this many consecutive keyframes before it whose revisits agree with
    it: drift moves consecutive keyframes alike, a look-alike place does not (0: refuse it)."""
    agree_fraction: float = 0.15
    """Consecutive corrections agree when each moves the other's camera centre to within this
    fraction of the correction of its own revisit pose."""
    agree_deg: float = 1.5
    """... and their rotations are within this angle."""
    large_min_parallax_deg: float = 2.0
    """A larger correction also needs its old points triangulated from at least this ray angle (median;
    registration's `min_parallax_deg`): far points mapped at the starved parallax of a turn in place put
    the camera's position wrong by as much as such a correction, and always by the same amount."""


@dataclass
class Revisit:
    """A verified revisit: frame, its pose from the old points, fused (new, old) track pairs, old frame."""

    frame: int
    T_cw: np.ndarray
    pairs: np.ndarray  # (P, 2) int64: track seen now, track of the old visit
    old_frame: int
    drift: float = float("nan")  # camera-centre correction, in map units
    scale: float = 1.0  # scale correction at the frame
    path: float = float("nan")  # keyframe path walked since the old visit, in map units
    old_parallax_deg: float = float("nan")  # median triangulation angle of the matched old points
    angle_deg: float = float("nan")  # rotation between the tracked and the revisit pose
    tracked_T_cw: np.ndarray | None = None  # the pose as tracked, before the correction
    fused: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    """(K, 2) track renamed, track it became: the pairs closing the loop fused."""

    def correction(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The world Sim(3) x -> s R x + t taking the map as tracked to the map the old points see."""
        T_wc_loop = np.linalg.inv(self.T_cw)
        R = T_wc_loop[:3, :3] @ self.tracked_T_cw[:3, :3]
        t = self.scale * T_wc_loop[:3, :3] @ self.tracked_T_cw[:3, 3] + T_wc_loop[:3, 3]
        return R, t, self.scale


_NEVER = np.iinfo(np.int64).max
"""`TrackIndex.last` of an id that is no track (fused into another): never old enough."""


@dataclass
class TrackIndex:
    """One keyframe ORB descriptor per point track and the first and last frame of every track."""

    desc_ids: np.ndarray  # (D,) sorted track ids that have a descriptor
    desc: np.ndarray  # (D, 32) uint8
    first: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(T,) first frame of each track id (-1: none)."""
    last: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """(T,) last frame of each track id (`_NEVER`: none)."""

    @classmethod
    def build(cls, tracks: Tracks) -> TrackIndex:
        """Index the descriptors (the first keyframe's per track) and spans of `tracks`."""
        tid = tracks.point_track[tracks.point_desc_row]
        ids, first_row = np.unique(tid, return_index=True)
        n = int(tracks.point_track.max()) + 1 if len(tracks.point_track) else 0
        first, last = np.full(n, _NEVER), np.full(n, -1)
        np.minimum.at(first, tracks.point_track, tracks.point_frame)
        np.maximum.at(last, tracks.point_track, tracks.point_frame)
        none = last < 0
        first[none], last[none] = -1, _NEVER
        return cls(
            ids,
            tracks.point_desc[first_row] if len(ids) else np.zeros((0, 32), np.uint8),
            first,
            last,
        )


def find_revisit(
    tracks: Tracks,
    points_w: PointStore,
    T_cw: dict[int, np.ndarray],
    frame: int,
    index: TrackIndex,
    cfg: RevisitConfig,
    seed: int = 0,
    point_angle: dict[int, float] | None = None,
) -> Revisit | None:
    """The revisit seen by keyframe `frame` (its pose `T_cw[frame]` as tracked), or None; `seed` seeds
    the verifying PnP's RANSAC; `point_angle` the map points' triangulation angles (degrees)."""
    here = tracks.point_frame[tracks.point_desc_row] == frame
    rows = tracks.point_desc_row[here]
    if len(rows) < cfg.min_inliers:
        return None
    q_ids, q_uv, q_desc = tracks.point_track[rows], tracks.point_uv[rows], tracks.point_desc[here]
    old_ids = index.desc_ids[index.last[index.desc_ids] <= frame - cfg.min_gap_frames]
    old_ids = old_ids[points_w.has(old_ids)]
    if len(old_ids) < cfg.min_inliers:
        return None
    X_old = points_w.xyz(old_ids)
    # guided search: old points are compared only with keypoints near where the tracked pose puts them
    T = T_cw[frame]
    Xc = X_old @ T[:3, :3].T + T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv_old = (Xc @ tracks.camera.K.T)[:, :2] / Xc[:, 2:3]
    r, cam = cfg.search_radius_px, tracks.camera
    near = Xc[:, 2] > 0
    with np.errstate(invalid="ignore"):  # only points that land within reach of a keypoint
        near &= (uv_old[:, 0] > -r) & (uv_old[:, 0] < cam.width + r)
        near &= (uv_old[:, 1] > -r) & (uv_old[:, 1] < cam.height + r)
    if near.sum() < cfg.min_inliers:
        return None
    old_ids, X_old, uv_old = old_ids[near], X_old[near], uv_old[near]
    old_desc = index.desc[np.searchsorted(index.desc_ids, old_ids)]
    qi, oi = _within(q_uv, uv_old, cfg.search_radius_px)
    pairs = match_candidates(q_desc, old_desc, qi, oi, cfg.max_hamming, cfg.match_ratio)
    if len(pairs) < cfg.min_inliers:
        return None
    qi, oi = pairs.T
    X = X_old[oi]
    pnp = PnPConfig(ransac_threshold_px=cfg.ransac_threshold_px, min_inliers=cfg.min_inliers, iterations=500)
    res = track_pnp(X, q_uv[qi], tracks.camera.K, None, pnp, seed=seed)
    if not res.ok:
        log.debug("frame %d: %d ORB matches to old points, not verified (%s)", frame, len(pairs), res.reason)
        return None
    qi, oi = qi[res.inliers], oi[res.inliers]
    old_frame = int(np.median(index.last[old_ids[oi]]))
    tracked = T_cw[frame]
    new_old = np.stack([q_ids[qi], old_ids[oi]], axis=1).astype(np.int64)
    rv = Revisit(
        frame,
        res.T_cw,
        new_old,
        old_frame,
        drift=float(np.linalg.norm(_centre(res.T_cw) - _centre(tracked))),
        path=_path_length(T_cw, old_frame, frame),
        angle_deg=_angle_deg(res.T_cw[:3, :3] @ tracked[:3, :3].T),
        tracked_T_cw=tracked.copy(),
    )
    if point_angle is not None:
        rv.old_parallax_deg = float(np.median([point_angle.get(int(t), 0.0) for t in old_ids[oi]]))
    rv.scale = _scale_correction(rv, points_w, tracked)
    return rv


class RevisitGate:
    """Which verified revisits close a loop, keyframe after keyframe of one registration segment.

    A correction within `max_drift` of the path since the old visit closes the loop at once. A larger
    one is drift only if it is consistent and measured from well-triangulated old points: it closes the
    loop when the revisits of the `confirm_keyframes` keyframes just before it found corrections that
    agree with it (drift moves every later keyframe alike; a look-alike place matched by chance does
    not) and its old points span `large_min_parallax_deg` (NaN, unknown, counts as too little).
    """

    def __init__(self, cfg: RevisitConfig) -> None:
        self.cfg = cfg
        self._streak: list[Revisit] = []  # large corrections at consecutive keyframes, oldest first

    def admit(self, rv: Revisit | None) -> bool:
        """Whether `rv` (the revisit found at the next keyframe, None if none was) closes a loop."""
        cfg = self.cfg
        if rv is None or rv.angle_deg > cfg.max_drift_deg:
            self._streak.clear()
            return False
        if rv.drift <= cfg.max_drift * rv.path:
            self._streak.clear()
            return True
        if not rv.old_parallax_deg >= cfg.large_min_parallax_deg:
            log.info(
                "frame %d: correction %.3f over a path of %.3f refused: its old points span %.2f deg",
                rv.frame,
                rv.drift,
                rv.path,
                rv.old_parallax_deg,
            )
            self._streak.clear()
            return False
        if self._streak and not _agree(self._streak[-1], rv, cfg):
            self._streak.clear()
        self._streak.append(rv)
        if cfg.confirm_keyframes > 0 and len(self._streak) > cfg.confirm_keyframes:
            log.info(
                "frame %d: correction %.3f over a path of %.3f (%.1f deg, scale %.3f), %d keyframes agree",
                rv.frame,
                rv.drift,
                rv.path,
                rv.angle_deg,
                rv.scale,
                len(self._streak) - 1,
            )
            self._streak.clear()
            return True
        log.info(
            "frame %d: %d matches to frame %d held: correction %.3f over a path of %.3f, %.1f deg",
            rv.frame,
            len(rv.pairs),
            rv.old_frame,
            rv.drift,
            rv.path,
            rv.angle_deg,
        )
        return False


def _agree(a: Revisit, b: Revisit, cfg: RevisitConfig) -> bool:
    """Whether two revisits' corrections agree: each puts the other's tracked camera centre where the
    other's old points do, to within `agree_fraction` of that correction, and their rotations agree."""
    ca, cb = a.correction(), b.correction()
    for (R, t, s), other in ((ca, b), (cb, a)):
        moved = s * R @ _centre(other.tracked_T_cw) + t
        if np.linalg.norm(moved - _centre(other.T_cw)) > cfg.agree_fraction * other.drift:
            return False
    return _angle_deg(ca[0] @ cb[0].T) <= cfg.agree_deg


def close_loop(
    tracks: Tracks,
    points_w: PointStore,
    T_cw: dict[int, np.ndarray],
    T_cw_frames: dict[int, np.ndarray],
    revisit: Revisit,
    index: TrackIndex,
) -> int:
    """Correct the drift since the old visit and fuse the revisit's tracks; returns the tracks fused.

    The correction at the revisit frame is the Sim(3) taking the map as tracked to the map as the
    old points see it (scale from the depths of matched points mapped on both visits); frames
    and points after the old visit get a fraction of it growing with the frame index, so the
    trajectory bends smoothly instead of jumping. Poses are changed in place; `tracks.point_track`
    is renamed in place (the later track continues the old one, as track completion's merges do).
    """
    f, f0 = revisit.frame, revisit.old_frame
    R, t, scale = revisit.correction()
    rotvec = so3_log(R)

    def part(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The share of the correction at frames g: rotations, translations and scales."""
        a = np.clip((g - f0) / max(f - f0, 1), 0.0, 1.0)
        return so3_exp(a[:, None] * rotvec), a[:, None] * t, scale**a

    for poses in (T_cw, T_cw_frames):
        later = np.array([g for g in poses if g > f0], np.int64)
        if len(later):
            moved = similarity_T_cw(np.stack([poses[int(g)] for g in later]), *part(later))
            poses.update(zip(later.tolist(), moved, strict=True))
    born = _first_keyframe(tracks, points_w, T_cw)
    tids = np.array([tid for tid, g in born.items() if g > f0], np.int64)
    if len(tids):
        Ra, ta, sa = part(np.array([born[int(tid)] for tid in tids], np.int64))
        X = points_w.xyz(tids)
        moved = sa[:, None] * np.einsum("kij,kj->ki", Ra, X) + ta
        points_w.update(zip(tids.tolist(), moved, strict=True))
    revisit.fused = _fuse(tracks, points_w, revisit.pairs, index)
    fused = len(revisit.fused)
    log.info(
        "revisit at frame %d of frame %d: %d tracks fused, drift %.3f (map units), scale %.3f, old points' "
        "parallax %.2f deg",
        f,
        f0,
        fused,
        revisit.drift,
        scale,
        revisit.old_parallax_deg,
    )
    return fused


def _fuse(tracks: Tracks, points_w: PointStore, pairs: np.ndarray, index: TrackIndex) -> np.ndarray:
    """Rename each new track to its old one (one to one) where their frames do not overlap; returns
    the (new, old) pairs renamed."""
    keep, used = [], set()
    for n, o in pairs.tolist():
        if n != o and o not in used and index.first[n] > index.last[o]:
            keep.append((n, o))
            used.add(o)
    if not keep:
        return np.zeros((0, 2), np.int64)
    new, old = np.array(keep, np.int64).T
    order = np.argsort(new)
    new, old = new[order], old[order]
    renamed = np.zeros(int(tracks.point_track.max()) + 1, bool)
    renamed[new] = True
    sel = renamed[tracks.point_track]
    tracks.point_track[sel] = old[np.searchsorted(new, tracks.point_track[sel])]
    for n in new.tolist():
        points_w.pop(n, None)
    index.last[old] = index.last[new]
    index.first[new], index.last[new] = -1, _NEVER
    return np.stack([new, old], axis=1)


def _within(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) with |a[i] - b[j]| <= radius, from a k-d tree instead of the full A x B."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ij = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius * (1 + 1e-9), output_type="ndarray")
    i, j = ij["i"].astype(np.int64), ij["j"].astype(np.int64)
    keep = np.linalg.norm(a[i] - b[j], axis=1) <= radius  # the exact test, not the tree's rounding
    return i[keep], j[keep]


def _scale_correction(revisit: Revisit, points_w: PointStore, T_cw_now: np.ndarray) -> float:
    """Median ratio of old to new depths of the matched points mapped on both visits (1 if under 8)."""
    both = [(n, o) for n, o in revisit.pairs.tolist() if n in points_w and o in points_w]
    if len(both) < 8:
        return 1.0
    new = np.array([points_w[n] for n, _ in both])
    old = np.array([points_w[o] for _, o in both])
    d_new = new @ T_cw_now[2, :3] + T_cw_now[2, 3]
    d_old = old @ revisit.T_cw[2, :3] + revisit.T_cw[2, 3]
    ok = (d_new > 0) & (d_old > 0)
    return float(np.median(d_old[ok] / d_new[ok])) if ok.sum() >= 8 else 1.0


def _first_keyframe(tracks: Tracks, points_w: PointStore, T_cw: dict[int, np.ndarray]) -> dict[int, int]:
    """The first keyframe that observes each mapped point."""
    keyframe = np.zeros(len(tracks), bool)
    keyframe[np.fromiter(T_cw, np.int64, len(T_cw))] = True
    sel = keyframe[tracks.point_frame] & points_w.has(tracks.point_track)
    uniq, inv = np.unique(tracks.point_track[sel], return_inverse=True)
    first = np.full(len(uniq), np.iinfo(np.int64).max)
    np.minimum.at(first, inv, tracks.point_frame[sel])
    return dict(zip(uniq.tolist(), first.tolist(), strict=True))


def _centre(T_cw: np.ndarray) -> np.ndarray:
    return -T_cw[:3, :3].T @ T_cw[:3, 3]


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _path_length(T_cw: dict[int, np.ndarray], f0: int, f1: int) -> float:
    """Length of the keyframe path from frame f0 to f1."""
    c = np.array([_centre(T_cw[g]) for g in sorted(T_cw) if f0 <= g <= f1])
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) if len(c) > 1 else 0.0
