"""Segment tracks joined across wide baselines: LBD matches in the epipolar band of verified keyframe pairs.

Segments are tracked from frame to frame by the point flow, so a break (a photo set, dropped frames,
a cut) ends every segment track, and a line seen in photos a step apart becomes a track per photo,
too short to triangulate. Where the wide-baseline point features verified a keyframe pair, its
essential matrix tells where a segment of one keyframe can lie in the other: between the epipolar
lines of its endpoints. Segments of the pair whose LBD descriptors match (mutual best, ratio test)
and overlap that band are one line; their tracks are joined by union-find, best matches first, never
two segments of one frame in one track.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from papl_mapper.frontend.descriptors import hamming_pairs, match_descriptors
from papl_mapper.frontend.features import chain_tracks
from papl_mapper.frontend.lines import LineConfig

log = logging.getLogger(__name__)


@dataclass
class LineLinkConfig:
    """Settings of joining segment tracks across verified keyframe pairs."""

    enabled: bool = True
    """Join segment tracks across the keyframe pairs that the wide-baseline features verified."""
    min_overlap: float = 0.5
    """Least overlap of a segment with the other segment's epipolar band, over the shorter of the two."""
    min_epipolar_angle_deg: float = 5.0
    """Least angle between a segment and the epipolar lines across it: a segment running along them
    (through the epipole) is not located by them, so it is not matched."""


def epipolar_overlap(
    F: np.ndarray, segs_a: np.ndarray, segs_b: np.ndarray, min_angle_deg: float
) -> np.ndarray:
    """(A, B) overlap of each segment b with the band between the epipolar lines (F p, F q) of the
    endpoints of each segment a, over the shorter of the band and b along b's line; 0 where b runs
    within `min_angle_deg` of either epipolar line. F maps pixels of a to lines of b (x_b^T F x_a = 0)."""
    ends_a = np.concatenate([segs_a[:, :2], segs_a[:, 2:]]).reshape(2, -1, 2)
    lines = np.stack([np.column_stack([e, np.ones(len(e))]) @ F.T for e in ends_a])  # (2, A, 3)
    q1 = np.column_stack([segs_b[:, :2], np.ones(len(segs_b))])  # (B, 3)
    d = np.column_stack([segs_b[:, 2:] - segs_b[:, :2], np.zeros(len(segs_b))])  # (B, 3)
    den = lines @ d.T  # (2, A, B): l . d
    norm = np.linalg.norm(lines[..., :2], axis=-1)[..., None] * np.linalg.norm(d[:, :2], axis=1)[None, None]
    steep = np.abs(den) >= np.sin(np.radians(min_angle_deg)) * np.maximum(norm, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(lines @ q1.T) / den  # (2, A, B): where b's line meets each epipolar line, in b's lengths
    lo, hi = np.minimum(t[0], t[1]), np.maximum(t[0], t[1])
    inter = np.clip(np.minimum(hi, 1.0) - np.maximum(lo, 0.0), 0.0, None)
    shorter = np.minimum(hi - lo, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(steep.all(axis=0) & (shorter > 0), inter / shorter, 0.0)
    return np.nan_to_num(out)


def link_line_tracks(
    line_frame: np.ndarray,
    line_track: np.ndarray,
    line_xy: np.ndarray,
    desc_row: np.ndarray,
    desc: np.ndarray,
    geometry: list[tuple[int, int, np.ndarray]],
    K: np.ndarray,
    cfg: LineLinkConfig,
    lbd: LineConfig,
) -> tuple[np.ndarray, int]:
    """Segment track ids (Kl,) with the tracks matched across the verified pairs joined (each group
    takes its oldest id), and the number of tracks joined into others.

    `desc_row`/`desc` are the keyframes' LBD descriptors and the segment rows they describe;
    `geometry` holds (frame row a, frame row b, essential matrix) per verified keyframe pair; LBD
    matches take the thresholds of segment re-association (`lbd`).
    """
    if not cfg.enabled or not geometry or len(desc_row) == 0:
        return line_track, 0
    K_inv = np.linalg.inv(K)
    described = np.zeros(len(line_frame), bool)
    described[desc_row] = True
    desc_of = np.zeros((len(line_frame), desc.shape[1]), np.uint8)
    desc_of[desc_row] = desc
    frames = np.unique(line_frame[desc_row])
    rows_of = {int(f): np.flatnonzero(described & (line_frame == f)) for f in frames}
    edges, costs = [], []
    for fa, fb, E in geometry:
        ra, rb = rows_of.get(fa), rows_of.get(fb)
        if ra is None or rb is None or len(ra) < 2 or len(rb) < 2:
            continue
        F = K_inv.T @ E @ K_inv
        allowed = epipolar_overlap(F, line_xy[ra], line_xy[rb], cfg.min_epipolar_angle_deg) >= cfg.min_overlap
        m = match_descriptors(desc_of[ra], desc_of[rb], lbd.lbd_max_hamming, lbd.lbd_ratio, allowed)
        if len(m):
            edges.append(np.column_stack([ra[m[:, 0]], rb[m[:, 1]]]))
            costs.append(hamming_pairs(desc_of, desc_of, ra[m[:, 0]], rb[m[:, 1]]))
    if not edges:
        return line_track, 0
    rows = np.concatenate(edges)
    ids, pair_track = np.unique(line_track[rows], return_inverse=True)
    pair_track = pair_track.reshape(rows.shape)
    order = np.argsort(line_track, kind="stable")
    sorted_track = line_track[order]
    lo, hi = np.searchsorted(sorted_track, ids), np.searchsorted(sorted_track, ids, side="right")
    track_frames = [set(line_frame[order[a:b]].tolist()) for a, b in zip(lo, hi, strict=True)]
    label = chain_tracks(track_frames, pair_track, np.concatenate(costs))
    rename = ids.copy()
    for g in np.unique(label[label >= 0]):
        members = ids[label == g]
        rename[label == g] = members.min()
    joined = int(np.sum(rename != ids))
    out = line_track.copy()
    pos = np.searchsorted(ids, line_track)
    hit = (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == line_track)
    out[hit] = rename[pos[hit]]
    log.debug("line links: %d segment tracks joined over %d keyframe pairs", joined, len(geometry))
    return out, joined
