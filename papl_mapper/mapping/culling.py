"""Redundant keyframe culling after registration, as in ORB-SLAM's local mapping.

A keyframe is redundant when at least `redundant_fraction` of the mapped points it sees are also
seen by `min_other_views` other keyframes at the same or a finer scale (here: from no farther than
`scale_factor` times its own depth; KLT tracks carry no pyramid level). Dense map-driven keyframes
make bundle adjustment slow and large; culling them keeps the map's structure while the culled
frames keep their pose as registered non-keyframe frames. Keyframes whose removal would leave a
line with too few keyframe views, or break the chain of shared points between neighbouring
keyframes, are kept, as are the first keyframe, the initial pair and the last keyframe.

benchmarks/keyframe_culling.py and memory_long.py (benchmarks/RESULTS.md) show culling halving keyframes
and the full BA's cost and memory, while the trajectory error moves both ways with the settings and the
scene, so the pipeline keeps it optional until that is understood.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.errors import ConfigError
from papl_mapper.mapping.incremental import Registration
from papl_mapper.rows import unique_rows
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class CullConfig:
    """Settings of redundant keyframe culling."""

    enabled: bool = True
    """Cull at all (False returns the registration unchanged)."""
    redundant_fraction: float = 0.9
    """A keyframe is redundant when at least this fraction of its mapped points is seen elsewhere..."""
    min_other_views: int = 3
    """...by at least this many other kept keyframes (ORB-SLAM: 3)."""
    scale_factor: float = 1.2
    """Another view counts if its depth is at most this times the keyframe's: the same or a finer
    scale, with one ORB pyramid level (1.2) of slack as in ORB-SLAM."""
    min_line_views: int = 2
    """A line track seen by k keyframes keeps at least min(k, this) of them, so lines that bundle
    adjustment refines (2 views) stay refined and no line loses its last keyframe view."""
    line_min_frames: int = 5
    """Only line tracks seen in at least this many registered frames (keyframes or not) hold keyframes:
    shorter segment tracks rarely triangulate, and most keyframes have a few of them."""
    min_shared_points: int = 30
    """The kept keyframes before and after a culled one must share at least this many mapped points,
    so the chain of poses stays constrained by common points."""
    max_gap_frames: int = 0
    """Largest frame gap between neighbouring kept keyframes (0: no limit)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.redundant_fraction <= 1.0:
            raise ConfigError(f"cull.redundant_fraction {self.redundant_fraction} must be in (0, 1]")
        if self.min_other_views < 1:
            raise ConfigError(f"cull.min_other_views {self.min_other_views} must be at least 1")
        if self.scale_factor < 1.0:
            raise ConfigError(f"cull.scale_factor {self.scale_factor} must be at least 1")
        counts = ("min_line_views", "line_min_frames", "min_shared_points", "max_gap_frames")
        bad = [f"cull.{k} {getattr(self, k)}" for k in counts if getattr(self, k) < 0]
        if bad:
            raise ConfigError(f"{', '.join(bad)}: must be 0 or more")


@dataclass
class CullStats:
    """What culling did: keyframes before and after, and why the redundant ones that stayed were kept."""

    keyframes_before: int = 0
    keyframes_after: int = 0
    culled: list[int] = field(default_factory=list)
    kept_for: dict[str, int] = field(default_factory=dict)
    """Redundant keyframes kept, by reason: protected, lines, shared_points, gap."""

    def as_dict(self) -> dict[str, object]:
        return {
            "keyframes_before": self.keyframes_before,
            "keyframes_after": self.keyframes_after,
            "culled": len(self.culled),
            "kept_for": dict(self.kept_for),
        }


@dataclass
class _Observations:
    """Keyframe observations of mapped points grouped by point: CSR rows, keyframe slot and depth."""

    kf_slot: np.ndarray  # (O,) index into the sorted keyframe list, ordered by point
    depth: np.ndarray  # (O,) depth of the point in that keyframe
    start: np.ndarray  # (P+1,) CSR offsets per point
    point_of: np.ndarray  # (O,) point index of each observation
    by_kf: list[np.ndarray]  # per keyframe slot: its observation rows (positions in the arrays above)


def _point_observations(tracks: Tracks, reg: Registration, frames: np.ndarray) -> _Observations:
    """Observations of registered points in the keyframes `frames`, in front of the camera."""
    pids = np.array(sorted(reg.points_w), np.int64)
    sel = np.isin(tracks.point_frame, frames) & np.isin(tracks.point_track, pids)
    pt = np.searchsorted(pids, tracks.point_track[sel])
    slot = np.searchsorted(frames, tracks.point_frame[sel])
    X = np.stack([reg.points_w[int(p)] for p in pids]) if len(pids) else np.zeros((0, 3))
    T = np.stack([reg.T_cw[int(f)] for f in frames])  # (N, 4, 4)
    depth = np.einsum("oj,oj->o", T[slot, 2, :3], X[pt]) + T[slot, 2, 3]
    ok = depth > 0
    pt, slot, depth = pt[ok], slot[ok], depth[ok]
    # one observation per (point, keyframe): a track seen twice in a frame counts once
    key = pt * len(frames) + slot
    _, first = np.unique(key, return_index=True)
    order = first[np.lexsort((slot[first], pt[first]))]
    pt, slot, depth = pt[order], slot[order], depth[order]
    start = np.searchsorted(pt, np.arange(len(pids) + 1))
    rows = np.argsort(slot, kind="stable")
    bounds = np.searchsorted(slot[rows], np.arange(len(frames) + 1))
    by_kf = [rows[bounds[i] : bounds[i + 1]] for i in range(len(frames))]
    return _Observations(slot, depth, start, pt, by_kf)


def _redundant_fraction(obs: _Observations, k: int, alive: np.ndarray, cfg: CullConfig) -> float:
    """Fraction of keyframe slot k's mapped points seen by enough other kept keyframes at its scale."""
    rows = obs.by_kf[k]
    if len(rows) == 0:
        return 1.0
    p = obs.point_of[rows]
    s, e = obs.start[p], obs.start[p + 1]
    n = e - s
    owner = np.repeat(np.arange(len(rows)), n)
    other = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + np.repeat(s, n)
    good = (
        alive[obs.kf_slot[other]]
        & (obs.kf_slot[other] != k)
        & (obs.depth[other] <= cfg.scale_factor * np.repeat(obs.depth[rows], n))
    )
    views = np.bincount(owner[good], minlength=len(rows))
    return float(np.mean(views >= cfg.min_other_views))


def _line_views(
    tracks: Tracks, frames: np.ndarray, registered: np.ndarray, min_frames: int
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Line tracks seen in the keyframes and in `min_frames` registered frames: ids, keyframe views per
    track, and each keyframe slot's rows into them."""
    seen = tracks.line_track[np.isin(tracks.line_frame, registered)]
    ids, n = np.unique(seen, return_counts=True)
    sel = np.isin(tracks.line_frame, frames) & np.isin(tracks.line_track, ids[n >= min_frames])
    slot = np.searchsorted(frames, tracks.line_frame[sel])
    ids, row = np.unique(tracks.line_track[sel], return_inverse=True)
    pairs = unique_rows(np.column_stack([row, slot])) if len(row) else np.zeros((0, 2), np.int64)
    views = np.bincount(pairs[:, 0], minlength=len(ids))
    order = np.argsort(pairs[:, 1], kind="stable")
    bounds = np.searchsorted(pairs[order, 1], np.arange(len(frames) + 1))
    per_kf = [pairs[order[bounds[i] : bounds[i + 1]], 0] for i in range(len(frames))]
    return ids, views, per_kf


def cull_keyframes(
    tracks: Tracks, reg: Registration, config: CullConfig | None = None, stats: CullStats | None = None
) -> Registration:
    """A copy of `reg` without its redundant keyframes; their poses move to `T_cw_frames`.

    Keyframes are visited in time order and culled greedily, so each decision counts only the
    keyframes still kept. Points stay as they are (bundle adjustment drops a point left with fewer
    than two keyframe views). `stats`, if given, is filled in.
    """
    cfg = config or CullConfig()
    stats = stats if stats is not None else CullStats()
    frames = np.array(sorted(reg.frames), np.int64)
    stats.keyframes_before = stats.keyframes_after = len(frames)
    out = dataclasses.replace(  # a copy that keeps every field, with the containers culling changes
        reg,
        frames=list(frames.tolist()),
        T_cw=dict(reg.T_cw),
        points_w=reg.points_w.copy(),
        point_angle=dict(reg.point_angle),
        T_cw_frames=dict(reg.T_cw_frames),
        lost=list(reg.lost),
    )
    if not cfg.enabled or len(frames) < 3:
        return out
    obs = _point_observations(tracks, reg, frames)
    registered = np.array(sorted(reg.poses()), np.int64)
    _, line_views, line_rows = _line_views(tracks, frames, registered, cfg.line_min_frames)
    line_floor = np.minimum(line_views, cfg.min_line_views)
    kf_points = [obs.point_of[r] for r in obs.by_kf]  # sorted: rows are ordered by point
    protected = {int(frames[0]), int(frames[-1]), *map(int, reg.init_frames)}
    alive = np.ones(len(frames), bool)
    kept_for: dict[str, int] = {}
    prev = 0  # the last kept slot before k
    for k in range(1, len(frames) - 1):
        if _redundant_fraction(obs, k, alive, cfg) < cfg.redundant_fraction:
            prev = k
            continue
        nxt = k + 1  # slots after k are all still alive: culling goes in time order
        reason = ""
        if int(frames[k]) in protected:
            reason = "protected"
        elif (line_views[line_rows[k]] - 1 < line_floor[line_rows[k]]).any():
            reason = "lines"
        elif cfg.max_gap_frames and frames[nxt] - frames[prev] > cfg.max_gap_frames:
            reason = "gap"
        elif len(np.intersect1d(kf_points[prev], kf_points[nxt], assume_unique=True)) < cfg.min_shared_points:
            reason = "shared_points"
        if reason:
            kept_for[reason] = kept_for.get(reason, 0) + 1
            prev = k
            continue
        alive[k] = False
        line_views[line_rows[k]] -= 1
    culled = frames[~alive]
    for f in culled.tolist():
        out.T_cw_frames[f] = out.T_cw.pop(f)
    out.frames = frames[alive].tolist()
    stats.keyframes_after = len(out.frames)
    stats.culled = culled.tolist()
    stats.kept_for = kept_for
    log.info(
        "keyframe culling: %d of %d keyframes redundant and culled (redundant but kept: %s)",
        len(culled),
        len(frames),
        ", ".join(f"{v} for {k}" for k, v in sorted(kept_for.items())) or "none",
    )
    return out


__all__ = ["CullConfig", "CullStats", "cull_keyframes"]
