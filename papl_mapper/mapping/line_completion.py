"""Line track completion and merging on a bundle-adjusted map, as `track_completion` does for points.

Segment tracks end where the point flow that carries them breaks, so one physical line often comes
back as a second track: a second map line, or a track too short to be mapped. After the full BA each
map line is projected into the keyframes that do not see it, and a segment detected there is a
candidate when both its endpoints lie within `line_max_error_px` of the projection and it overlaps the
projected segment. Its whole track must then be explained by the line in every keyframe that sees it,
share no frame with the line's track, and (where both have LBD descriptors) look like it. A track
that is itself a map line is merged into the line (one line, not two); one that is not mapped is
completed into it. Tracks are renamed in `tracks.line_track` in place, as for points, and the map's
line observations follow.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from papl_mapper.frontend.descriptors import hamming_pairs
from papl_mapper.map import Lines, Map
from papl_mapper.tracks import Tracks

if TYPE_CHECKING:
    from papl_mapper.mapping.structure import AxisInputs
    from papl_mapper.mapping.track_completion import CompletionConfig

log = logging.getLogger(__name__)

NEAR = 0.05  # metres in front of the camera for a projected endpoint to count


@dataclass
class LineCompletionStats:
    """What line completion changed."""

    merged: int = 0
    """Map lines merged into another map line (two tracks of one physical line)."""
    completed: int = 0
    """Unmapped segment tracks joined to a map line."""
    observations_added: int = 0
    """Keyframe observations the map lines gained."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _project_segments(K: np.ndarray, T_wc: np.ndarray, ends_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2, 2) of the endpoints of 3D segments ends_w (M, 2, 3) seen from camera T_wc (4, 4),
    or from cameras T_wc (M, 4, 4) one per segment, and whether both lie in front (M,); a segment not
    in front gets finite placeholder pixels."""
    Xc = (ends_w - T_wc[..., None, :3, 3]) @ T_wc[..., :3, :3]  # (M, 2, 3)
    front = (Xc[..., 2] > NEAR).all(axis=1)
    z = np.where(front[:, None], Xc[..., 2], 1.0)
    return (Xc @ K.T)[..., :2] / z[..., None], front


def _image_lines(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Start, unit direction, unit normal (..., 2) and length (...) of projected segments uv (..., 2, 2)."""
    a = uv[..., 0, :]
    ab = uv[..., 1, :] - a
    length = np.linalg.norm(ab, axis=-1)
    u = ab / np.maximum(length, 1e-9)[..., None]
    return a, u, np.stack([-u[..., 1], u[..., 0]], -1), length


def segment_line_errors(K: np.ndarray, T_wc: np.ndarray, ends_w: np.ndarray, xy: np.ndarray):
    """Pixel distances (M, S, 2) of the endpoints of segments xy (S, 4) to the image lines of 3D
    segments ends_w (M, 2, 3) seen from camera T_wc, and the overlap (M, S) of each segment with the
    projected segment over the segment's own length; inf / 0 where a 3D endpoint is behind the camera."""
    uv, front = _project_segments(K, T_wc, ends_w)
    a, u, n, length = _image_lines(uv)
    p = xy.reshape(-1, 2, 2)  # (S, 2, 2)
    rx = p[None, :, :, 0] - a[:, None, None, 0]  # (M, S, 2) endpoint offsets from the image line's start
    ry = p[None, :, :, 1] - a[:, None, None, 1]
    dist = np.abs(rx * n[:, None, None, 0] + ry * n[:, None, None, 1])
    along = rx * u[:, None, None, 0] + ry * u[:, None, None, 1]
    lo, hi = np.minimum(along[..., 0], along[..., 1]), np.maximum(along[..., 0], along[..., 1])
    inside = np.clip(np.minimum(hi, length[:, None]) - np.maximum(lo, 0.0), 0.0, None)
    overlap = inside / np.maximum(hi - lo, 1e-9)
    ok = front & (length > 1.0)
    return np.where(ok[:, None, None], dist, np.inf), np.where(ok[:, None], overlap, 0.0)


def _lines_near_segments(
    K: np.ndarray, T_wc: np.ndarray, ends_w: np.ndarray, xy: np.ndarray, margin_px: float
) -> np.ndarray:
    """Rows of the 3D segments ends_w (M, 2, 3) whose image from T_wc can meet a segment of xy (S, 4)
    within `margin_px`: in front of the camera, with the bounding box of their image overlapping that
    of the segments grown by the margin. A segment within the margin of a line and overlapping its
    projection lies within the margin of the projected segment, so no line left out could match."""
    uv, front = _project_segments(K, T_wc, ends_w)
    p = xy.reshape(-1, 2)
    lo, hi = p.min(axis=0) - margin_px, p.max(axis=0) + margin_px
    meets = (uv.max(axis=1) >= lo).all(axis=1) & (uv.min(axis=1) <= hi).all(axis=1)
    return np.flatnonzero(front & meets)


def complete_lines(
    tracks: Tracks,
    m: Map,
    max_error_px: float,
    min_overlap: float,
    max_hamming: int,
    min_views_without_descriptor: int,
) -> tuple[LineCompletionStats, dict[int, int]]:
    """Merge and complete segment tracks into the lines of `m` (a BA result), renaming tracks in
    `tracks` and updating `m.lines` observations in place. Returns the statistics and the renames
    (segment track -> the map line's track). See the module docstring."""
    stats = LineCompletionStats()
    ln = m.lines
    if len(ln) == 0 or len(tracks.line_track) == 0:
        return stats, {}
    K = tracks.camera.K
    kf_frames = m.keyframes.ids
    is_kf = np.isin(tracks.line_frame, kf_frames)
    line_of_track = {int(t): i for i, t in enumerate(ln.ids)}
    frames_of = _frames_by_track(tracks)
    desc_of = _descriptors_by_track(tracks)
    seen = {(int(t), int(f)) for t, f in ln.obs_ids}
    n_obs = np.bincount([line_of_track[int(t)] for t in ln.obs_ids[:, 0]], minlength=len(ln))

    # candidates: (mean error, line row, segment track) from every keyframe that does not see the line
    cand: dict[tuple[int, int], float] = {}
    for r, f in enumerate(kf_frames.tolist()):
        rows = np.flatnonzero(tracks.line_frame == f)
        if len(rows) == 0:
            continue
        T_wc = m.keyframes.T_wc[r]
        near = (
            _lines_near_segments(K, T_wc, ln.endpoints_w, tracks.line_xy[rows], max_error_px)
            if min_overlap > 0  # (with no overlap asked for, a line anywhere along the image line may match)
            else np.arange(len(ln))
        )
        dist, overlap = segment_line_errors(K, T_wc, ln.endpoints_w[near], tracks.line_xy[rows])
        hit = (dist.max(axis=2) <= max_error_px) & (overlap >= min_overlap)
        for k, s in zip(*np.nonzero(hit), strict=True):
            i = near[k]
            t_line, t_seg = int(ln.ids[i]), int(tracks.line_track[rows[s]])
            if t_seg == t_line or (t_line, f) in seen:
                continue
            err = float(dist[k, s].mean())
            key = (int(i), t_seg)
            cand[key] = min(cand.get(key, np.inf), err)

    joined_into: dict[int, int] = {}  # segment track -> line track it joined
    receivers: set[int] = set()  # line tracks that took a segment track (never joined to another)
    merged_rows: set[int] = set()
    frames_now = {int(t): set(frames_of.get(int(t), ())) for t in ln.ids}
    for (i, t_seg), _ in sorted(cand.items(), key=lambda kv: kv[1]):
        t_line = int(ln.ids[i])
        if t_line in joined_into:
            continue
        if i in merged_rows or t_seg in joined_into or t_seg in receivers:
            continue
        j = line_of_track.get(t_seg)
        if j is not None and j in merged_rows:
            continue
        seg_frames = set(frames_of.get(t_seg, ()))
        if seg_frames & frames_now[t_line]:
            continue  # one track would hold two segments of a frame
        sel = (tracks.line_track == t_seg) & is_kf
        if not _explains(K, m, ln.endpoints_w[i], tracks.line_frame[sel], tracks.line_xy[sel], max_error_px):
            continue
        if not _descriptors_agree(
            desc_of, t_line, t_seg, max_hamming, int(sel.sum()), min_views_without_descriptor
        ):
            continue
        if j is None:
            survivor, joiner = t_line, t_seg
            stats.completed += 1
        else:  # the line seen from more keyframes stays (the better anchored one), the other joins it
            keep_i = (n_obs[i], -t_line) >= (n_obs[j], -t_seg)
            survivor, joiner, gone = (t_line, t_seg, j) if keep_i else (t_seg, t_line, i)
            if joiner in receivers:
                continue  # its track would be renamed after others joined it
            merged_rows.add(gone)
            stats.merged += 1
        joined_into[joiner] = survivor
        receivers.add(survivor)
        stats.observations_added += int(
            np.isin(tracks.line_frame[tracks.line_track == joiner], kf_frames).sum()
        )
        frames_now[survivor] = frames_now.get(survivor, set()) | set(frames_of.get(joiner, ()))
    if not joined_into:
        return stats, {}
    # renames resolve in one pass: a track that received others never joins another one
    old = tracks.line_track.copy()
    for t_seg, t_line in joined_into.items():
        tracks.line_track[old == t_seg] = t_line
    m.lines = _with_observations(ln, tracks, kf_frames, merged_rows, joined_into)
    return stats, joined_into


def _frames_by_track(tracks: Tracks) -> dict[int, np.ndarray]:
    order = np.argsort(tracks.line_track, kind="stable")
    t, f = tracks.line_track[order], tracks.line_frame[order]
    cut = np.flatnonzero(np.diff(t)) + 1
    return {int(g[0]): fr for g, fr in zip(np.split(t, cut), np.split(f, cut), strict=True) if len(g)}


def _descriptors_by_track(tracks: Tracks) -> dict[int, np.ndarray]:
    if len(tracks.line_desc_row) == 0:
        return {}
    owner = tracks.line_track[tracks.line_desc_row]
    return {int(t): tracks.line_desc[owner == t] for t in np.unique(owner)}


def _explains(K, m: Map, ends_w: np.ndarray, frames: np.ndarray, xy: np.ndarray, max_error_px: float) -> bool:
    """Every keyframe observation (frames, xy) lies within max_error_px of the line's projection (the
    distances of `segment_line_errors`, all observations at once)."""
    if len(frames) == 0:
        return False
    T = m.keyframes.T_wc[np.searchsorted(m.keyframes.ids, frames)]  # (N, 4, 4), one per observation
    uv, front = _project_segments(K, T, np.broadcast_to(ends_w, (len(T), 2, 3)))
    if not front.all():
        return False
    a, _, n, length = _image_lines(uv)
    if not (length > 1.0).all():
        return False
    dist = np.abs(np.einsum("nek,nk->ne", xy.reshape(-1, 2, 2) - a[:, None], n))
    return bool(dist.max() <= max_error_px)


def _descriptors_agree(
    desc_of: dict[int, np.ndarray], t_line: int, t_seg: int, max_hamming: int, n_kf_obs: int, min_views: int
) -> bool:
    """The closest LBD descriptors of the two tracks within max_hamming; without descriptors on both
    sides the segment track needs min_views keyframe observations (geometry alone then confirms it)."""
    a, b = desc_of.get(t_line), desc_of.get(t_seg)
    if a is None or b is None or len(a) == 0 or len(b) == 0:
        return n_kf_obs >= min_views
    ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
    return int(hamming_pairs(a, b, ia.ravel(), ib.ravel()).min()) <= max_hamming


def _with_observations(
    ln: Lines, tracks: Tracks, kf_frames: np.ndarray, merged_rows: set[int], joined_into: dict[int, int]
) -> Lines:
    """The lines without the merged rows, with every keyframe observation of their (renamed) tracks."""
    keep = np.setdiff1d(np.arange(len(ln)), np.fromiter(merged_rows, np.int64, len(merged_rows)))
    ids = ln.ids[keep]
    touched = np.fromiter(set(joined_into.values()), np.int64)
    old_obs = ~np.isin(ln.obs_ids[:, 0], touched) & np.isin(ln.obs_ids[:, 0], ids)
    sel = np.isin(tracks.line_track, touched) & np.isin(tracks.line_frame, kf_frames)
    obs_ids = np.concatenate(
        [
            ln.obs_ids[old_obs],
            np.column_stack([tracks.line_track[sel], tracks.line_frame[sel]]).astype(np.int64),
        ]
    )
    obs_xy = np.concatenate([ln.obs_xy[old_obs], tracks.line_xy[sel]])
    order = np.lexsort((obs_ids[:, 1], obs_ids[:, 0]))
    return Lines(
        ids,
        ln.endpoints_w[keep],
        ln.axis_weights[keep],
        ln.state[keep],
        ln.ref_keyframe_id[keep],
        ln.inverse_depth[keep],
        obs_ids[order],
        obs_xy[order],
    )


def complete_map_lines(
    tracks: Tracks, m: Map, config: CompletionConfig, axis_inputs: AxisInputs | None = None
) -> dict[str, int]:
    """`complete_lines` with the settings of `config` as a pipeline stage: a merged line's
    vanishing-direction observations then count for the line it joined in `axis_inputs`; the
    statistics, logged."""
    done, joined = complete_lines(
        tracks,
        m,
        config.line_max_error_px,
        config.line_min_overlap,
        config.line_max_hamming,
        config.min_views_without_descriptor,
    )
    if axis_inputs is not None and joined:
        axis_inputs.join_lines(joined)
    log.info(
        "line tracks: %d merged, %d completed (%d keyframe observations)",
        done.merged,
        done.completed,
        done.observations_added,
    )
    return done.as_dict()
