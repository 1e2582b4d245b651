"""Track completion, merging and retriangulation on a bundle-adjusted map, as COLMAP's mapper does.

KLT chains end when a point leaves the view or a track breaks, so one physical point often comes
back as a second track. After a global BA the poses are good enough to find it again: every map
point is projected into every keyframe that does not see it, and the tracked corner nearest to the
projection joins the point's track when (a) its ORB descriptor agrees with one of the point's, where
both have one, and (b) the map point explains every keyframe observation of the joining track
within `max_error_px`. A joining track that is itself a map point is merged (one point, not two);
one that is not yet mapped is completed into it. Tracks still unmapped are then triangulated from
the BA poses (retriangulation), filtered by reprojection error and triangulation angle. Tracks are
renamed in `tracks.point_track` in place, as loop closures do, so later stages see one id per point.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from papl_mapper.frontend.descriptors import hamming_pairs
from papl_mapper.geometry.se3 import invert, project_points
from papl_mapper.geometry.triangulation import max_reprojection_px, triangulate_points
from papl_mapper.map import Map
from papl_mapper.tracks import PointRows, Tracks

log = logging.getLogger(__name__)


@dataclass
class CompletionConfig:
    """Thresholds of track completion, merging and retriangulation after a global BA."""

    enabled: bool = True
    """Complete, merge and retriangulate point tracks after the points-only BA (then BA again)."""
    after_full_ba: bool = True
    """...and after the full BA over points and lines, then the full BA again (`--preset
    no-final-completion` turns it off: benchmarks/results/real.json and accuracy_final_completion.json)."""
    search_radius_px: float = 3.0
    """A tracked corner joins a map point only this close to where the BA pose projects the point."""
    max_error_px: float = 2.0
    """Every keyframe observation of a joining track must lie this close to the point's projection."""
    max_hamming: int = 48
    """Largest ORB distance (of 256 bits) between the joining corner and the point's descriptors."""
    min_views_without_descriptor: int = 2
    """A joining track without a descriptor at the candidate keyframe needs this many keyframe
    observations, all explained by the point (geometry alone then confirms it)."""
    retriangulate: bool = True
    """Triangulate point tracks the map does not hold yet from the BA poses."""
    min_angle_deg: float = 2.0
    """Smallest triangulation angle of a retriangulated point."""
    max_reprojection_px: float = 2.0
    """Largest reprojection error of a retriangulated point in any keyframe that sees it."""
    lines: bool = True
    """After the full BA, also merge and complete segment tracks into the map lines
    (`mapping.line_completion`)."""
    line_max_error_px: float = 1.0
    """Both endpoints of a joining segment lie this close to the line's projection, in every keyframe
    (segments are located far more precisely across than points are: 2 px let neighbouring parallel
    edges join, benchmarks/results/real.json)."""
    line_min_overlap: float = 0.5
    """A candidate segment overlaps the projected line segment over at least this fraction of itself."""
    line_max_hamming: int = 70
    """Largest LBD distance (of 256 bits) between the closest descriptors of the two tracks."""


@dataclass
class CompletionStats:
    """What completion changed: tracks merged or completed into map points, points triangulated."""

    merged: int = 0
    """Map points merged into another map point (two tracks of one physical point)."""
    completed: int = 0
    """Unmapped tracks joined to a map point."""
    observations_added: int = 0
    """Keyframe observations the map points gained by merging and completing."""
    retriangulated: int = 0
    """Unmapped tracks triangulated from the BA poses."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def complete_tracks(
    tracks: Tracks, m: Map, config: CompletionConfig | None = None
) -> tuple[dict[int, np.ndarray], CompletionStats]:
    """Points of `m` (by track id) after merging, completion and retriangulation; renames tracks in place.

    The keyframe poses of `m` are taken as they are (a BA has run); the returned points are its
    points minus the merged ones plus the retriangulated ones, for `assemble_map` and another BA.
    """
    cfg = config or CompletionConfig()
    stats = CompletionStats()
    points_w = {int(i): x for i, x in zip(m.points.ids, m.points.xyz, strict=True)}
    if not cfg.enabled or len(m.keyframes) == 0:
        return points_w, stats
    kf_ids = m.keyframes.ids.astype(np.int64)
    T_wc = {int(k): T for k, T in zip(kf_ids, m.keyframes.T_wc, strict=True)}
    in_kf = np.isin(tracks.point_frame, kf_ids)
    rows_index = PointRows(tracks)
    desc_of_row = np.full(len(tracks.point_track), -1, np.int64)
    desc_of_row[tracks.point_desc_row] = np.arange(len(tracks.point_desc_row))
    pairs = _candidates(tracks, m, T_wc, cfg)
    members: dict[int, list[int]] = {}  # a map point's original track ids (itself and those it took in)
    owner: dict[int, int] = {}  # original track id -> the map point it was renamed to
    frames_of: dict[int, set[int]] = {}

    def group(t: int) -> np.ndarray:
        return np.array(members.get(t, [t]), np.int64)

    def frames(t: int) -> set[int]:
        if t not in frames_of:
            frames_of[t] = set(tracks.point_frame[rows_index.rows(group(t))].tolist())
        return frames_of[t]

    K = tracks.camera.K
    near = _projects_near(tracks, rows_index, in_kf, T_wc, points_w, pairs, cfg.max_error_px)
    for i, (p, b) in enumerate(pairs):
        if p in owner or b in owner or p not in points_w:
            continue
        if b not in members and not near[i]:  # screened in one pass while b is a track of its own
            continue
        if frames(b) & frames(p):  # one track twice in a frame: two different corners, not one point
            continue
        all_rows = rows_index.rows(group(b))
        rows = all_rows[in_kf[all_rows]]
        if b in members:  # grown since the screen: its test again, over all its pieces
            if len(rows) == 0:
                continue
            uv, z = project_points(K, np.stack([T_wc[int(f)] for f in tracks.point_frame[rows]]), points_w[p])
            if (z <= 0).any() or np.linalg.norm(uv - tracks.point_uv[rows], axis=1).max() > cfg.max_error_px:
                continue
        if not _descriptors_agree(tracks, rows_index, desc_of_row, group(p), group(b), len(rows), cfg):
            continue
        tracks.point_track[all_rows] = p
        members[p] = [*group(p).tolist(), *group(b).tolist()]
        frames_of[p] = frames(p) | frames(b)
        for t in group(b).tolist():
            owner[t] = p
        stats.observations_added += len(rows)
        if b in points_w:
            del points_w[b]
            stats.merged += 1
        else:
            stats.completed += 1
    if cfg.retriangulate:
        stats.retriangulated = _retriangulate(tracks, T_wc, in_kf, points_w, cfg)
    return points_w, stats


def _projects_near(
    tracks: Tracks,
    rows_index: PointRows,
    in_kf: np.ndarray,
    T_wc: dict[int, np.ndarray],
    points_w: dict[int, np.ndarray],
    pairs: list[tuple[int, int]],
    max_error_px: float,
) -> np.ndarray:
    """(len(pairs),) whether map point p projects in front of, and within `max_error_px` of, every
    keyframe observation of track b (which has at least one): the geometric test of a join for every
    pair at once; the completion loop repeats it only for a track that has grown since."""
    if not pairs:
        return np.zeros(0, bool)
    p_ids = [p for p, _ in pairs]
    X = np.array([points_w.get(p, np.zeros(3)) for p in p_ids])
    rows, which = rows_index.rows_by_id(np.array([b for _, b in pairs], np.int64))
    keep = in_kf[rows]
    rows, which = rows[keep], which[keep]
    frames = tracks.point_frame[rows]
    kf = np.unique(frames)
    T = np.stack([T_wc[int(f)] for f in kf]) if len(kf) else np.zeros((0, 4, 4))
    uv, z = project_points(tracks.camera.K, T[np.searchsorted(kf, frames)], X[which])
    bad = (z <= 0) | (np.linalg.norm(uv - tracks.point_uv[rows], axis=1) > max_error_px)
    near = np.bincount(which, minlength=len(pairs)) > 0
    near &= np.bincount(which, weights=bad, minlength=len(pairs)) == 0
    return near


def _candidates(
    tracks: Tracks, m: Map, T_wc: dict[int, np.ndarray], cfg: CompletionConfig
) -> list[tuple[int, int]]:
    """(map point, other track) pairs where the track's corner lies near the point's projection in a
    keyframe that does not see the point, nearest first; each pair once, a mapped other track only
    when it is the younger one."""
    K, cam = tracks.camera.K, tracks.camera
    pid, X = m.points.ids.astype(np.int64), m.points.xyz
    mapped = set(pid.tolist())
    found: dict[tuple[int, int], float] = {}
    for f, T in T_wc.items():
        ids, uv_k = tracks.points_in(f)
        if len(ids) == 0 or len(pid) == 0:
            continue
        uv, z = project_points(K, T, X)
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        vis &= ~np.isin(pid, ids)
        if not vis.any():
            continue
        dist, j = cKDTree(uv_k).query(uv[vis], distance_upper_bound=cfg.search_radius_px)
        hit = np.isfinite(dist)
        for p, t, d in zip(pid[vis][hit].tolist(), ids[j[hit]].tolist(), dist[hit].tolist(), strict=True):
            # two map points merge into the older track (the lower id), so ids stay stable
            if p != t and not (t < p and t in mapped) and found.get((p, t), np.inf) > d:
                found[(p, t)] = d
    return sorted(found, key=found.__getitem__)


def _descriptors_agree(
    tracks: Tracks,
    rows_index: PointRows,
    desc_of_row: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    b_views: int,
    cfg: CompletionConfig,
) -> bool:
    """ORB check of a join of track groups `a` and `b`: their closest pair of descriptors within
    `max_hamming`; where either has none, enough keyframe views explained by the point stand in."""
    da = desc_of_row[rows_index.rows(a)]
    db = desc_of_row[rows_index.rows(b)]
    da, db = da[da >= 0], db[db >= 0]
    if len(da) == 0 or len(db) == 0:
        return b_views >= cfg.min_views_without_descriptor
    ia, ib = np.repeat(da, len(db)), np.tile(db, len(da))
    return int(hamming_pairs(tracks.point_desc, tracks.point_desc, ia, ib).min()) <= cfg.max_hamming


def _retriangulate(
    tracks: Tracks,
    T_wc: dict[int, np.ndarray],
    in_kf: np.ndarray,
    points_w: dict[int, np.ndarray],
    cfg: CompletionConfig,
) -> int:
    """Triangulate the unmapped tracks seen by two or more keyframes; adds them to `points_w`."""
    mapped = np.fromiter(points_w, np.int64, len(points_w))
    sel = np.flatnonzero(in_kf & ~np.isin(tracks.point_track, mapped))
    if len(sel) == 0:
        return 0
    uniq, index = np.unique(tracks.point_track[sel], return_inverse=True)
    T = np.stack([T_wc[int(f)] for f in tracks.point_frame[sel]])
    K, uv = tracks.camera.K, tracks.point_uv[sel]
    X, ok = triangulate_points(index, T, K, uv, len(uniq), cfg.min_angle_deg)
    ok &= max_reprojection_px(index, invert(T), K, uv, X) <= cfg.max_reprojection_px
    for i in np.flatnonzero(ok).tolist():
        points_w[int(uniq[i])] = X[i]
    return int(ok.sum())


def complete_map(tracks: Tracks, m: Map, config: CompletionConfig | None = None) -> CompletionStats:
    """`complete_tracks` on the BA poses of `m`, its points replaced in place (keyframes and lines kept)
    for the BA that follows; the statistics, logged."""
    from papl_mapper.mapping.assemble import assemble_map
    from papl_mapper.mapping.lines import LineEstimates

    points_w, done = complete_tracks(tracks, m, config)
    poses = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    m.points = assemble_map(tracks, poses, points_w, LineEstimates.empty()).points
    log.info(
        "tracks: %d merged, %d completed (%d keyframe observations), %d retriangulated",
        done.merged,
        done.completed,
        done.observations_added,
        done.retriangulated,
    )
    return done
