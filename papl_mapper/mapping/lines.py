"""First estimates of 3D lines from segment tracks seen by registered keyframes.

Each observed segment back-projects to a plane through its camera centre; a line is where the
planes of its track meet. A structural segment also carries the vanishing direction it was
classified to, so its direction is known and only its position (2 dof) is solved: the paper's
temporary-vanishing-point stage. Endpoints come from the observed extent.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from papl_mapper.geometry.lines import endpoint_errors, plucker_from_point_dir, plucker_to_camera
from papl_mapper.geometry.triangulation import observation_planes

log = logging.getLogger(__name__)


@dataclass
class LineInitConfig:
    """Thresholds of line triangulation."""

    min_views: int = 5
    """Fewest observations of a segment track (frames or keyframes, as triangulated): lines from 2-4
    views are mostly texture edges (on the synthetic 10 s walks 5 raised precision at equal recall)."""
    min_plane_angle_deg: float = 1.0
    """Smallest angle between two observation planes: below it the depth is not observable (2 degrees
    lost ground-truth tracks of the synthetic corridor that 1 degree keeps; benchmarks/line_diagnosis.py
    counts the tracks each rule loses)."""
    max_error_px: float = 3.0
    """Largest endpoint-to-line reprojection error of an accepted line (RMS over its views)."""
    min_ray_angle_deg: float = 5.0
    """An endpoint ray closer than this to the line direction gives no extent."""
    max_length_over_depth: float = 3.0
    """Longest accepted segment, as a multiple of its midpoint's median distance to the cameras."""
    vp_direction_spread_deg: float = 3.0
    """Largest spread of a track's world vanishing directions for the direction to be trusted."""
    min_vp_fraction: float = 0.5
    """Fewest of a track's observations classified to a vanishing direction, as a fraction, for the
    track to count as structural; the map holds structural lines, texture edges are left out (on the
    synthetic corridor they are most of the line length, at low precision). 0 keeps every track. 0.7
    traded a little recall for a little precision but worsened the corridor's ATE, which 0.5 keeps at
    the points-only value."""
    max_vp_angle_deg: float = 1.0
    """A track classified in fewer views than that is structural all the same when the image angle
    between its segments and the lines to its vanishing point, averaged weighted by segment length,
    is below this (the frontend leaves some of the views of structural segments unclassified)."""


@dataclass
class LineEstimates:
    """Triangulated lines by track: endpoints (M,2,3) in the world, how each was made, errors."""

    track: np.ndarray  # (M,) int64 segment track id
    endpoints_w: np.ndarray  # (M, 2, 3)
    from_vp: np.ndarray  # (M,) bool, direction fixed by the vanishing direction
    rms_px: np.ndarray  # (M,) endpoint-to-line reprojection RMS

    @classmethod
    def empty(cls) -> LineEstimates:
        return cls(np.zeros(0, np.int64), np.zeros((0, 2, 3)), np.zeros(0, bool), np.zeros(0))


def line_through_planes(
    planes: np.ndarray, centres_w: np.ndarray, direction: np.ndarray | None = None, iterations: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Line (point, unit direction) where planes (n,4) seen from centres (n,3) meet, in the least squares.

    The algebraic plane distance is a metric distance; dividing it by the line's depth in each view
    makes it proportional to the reprojection error, so the fit is reweighted by 1/depth a few
    times. With a known `direction` the planes should contain it (see `planes_through_direction`).
    """
    normals = planes[:, :3]
    offsets = -np.einsum("ni,ni->n", normals, centres_w)
    w = np.ones(len(planes))
    for _ in range(iterations):
        d = direction if direction is not None else np.linalg.svd(normals * w[:, None])[2][-1]
        basis = np.linalg.svd(d[None, :])[2][1:]  # (2, 3) orthonormal complement of d
        coeff = np.linalg.lstsq((normals @ basis.T) * w[:, None], -offsets * w, rcond=None)[0]
        p = coeff @ basis
        depth = np.linalg.norm(p - centres_w, axis=1)
        w = 1.0 / np.maximum(depth, 1e-3 * depth.max() + 1e-12)
    return p, d


def planes_through_direction(T_wc: np.ndarray, xy: np.ndarray, K: np.ndarray, d_w: np.ndarray) -> np.ndarray:
    """Back-projection planes (n,4) constrained to contain the world direction d_w.

    Each image line is replaced by the line through the segment's midpoint and the vanishing
    point of d_w, the usual vanishing-point-constrained segment; its plane then contains d_w.
    """
    d_c = np.einsum("nji,j->ni", T_wc[:, :3, :3], d_w)  # R_cw d_w
    vp = d_c @ K.T  # (n, 3), homogeneous, possibly at infinity
    mid = np.column_stack([0.5 * (xy[:, :2] + xy[:, 2:]), np.ones(len(xy))])
    n_c = np.cross(vp, mid) @ K
    n_w = np.einsum("nij,nj->ni", T_wc[:, :3, :3], n_c)
    n_w /= np.linalg.norm(n_w, axis=1, keepdims=True)
    offset = -np.einsum("ni,ni->n", n_w, T_wc[:, :3, 3])
    return np.column_stack([n_w, offset])


def _plane_angle_deg(normals: np.ndarray) -> float:
    """Largest angle between any two of the (unsigned) plane normals."""
    c = np.abs(normals @ normals.T)
    return float(np.degrees(np.arccos(np.clip(c.min(), 0.0, 1.0))))


def reprojection_rms(
    p: np.ndarray, d: np.ndarray, T_wc: np.ndarray, xy: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """Per-view RMS distance (px) of the observed endpoints to the projected infinite line."""
    L_c = plucker_to_camera(plucker_from_point_dir(p, d), T_wc)
    return np.sqrt(np.mean(endpoint_errors(K, L_c, xy) ** 2, axis=1))


def endpoint_extent(
    p: np.ndarray, d: np.ndarray, T_wc: np.ndarray, xy: np.ndarray, K: np.ndarray, min_ray_angle_deg: float
) -> np.ndarray | None:
    """Endpoints (2,3): the union of the observed extents along the line, None if none is usable."""
    Kinv = np.linalg.inv(K)
    rays = np.concatenate([xy[:, :2], xy[:, 2:]])  # (2n, 2)
    rays_c = np.column_stack([rays, np.ones(len(rays))]) @ Kinv.T
    R = np.concatenate([T_wc[:, :3, :3], T_wc[:, :3, :3]])
    c = np.concatenate([T_wc[:, :3, 3], T_wc[:, :3, 3]])
    r = np.einsum("nij,nj->ni", R, rays_c)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    # closest point on the line p + s d to the ray c + u r
    w0 = p - c
    b = r @ d
    denom = 1.0 - b**2
    ok = denom > np.sin(np.radians(min_ray_angle_deg)) ** 2
    if not ok.any():
        return None
    w0r = np.einsum("ni,ni->n", w0, r)
    s = (b * w0r - (w0 @ d)) / np.where(ok, denom, 1.0)
    u = w0r + b * s  # ray parameter: the closest point must be in front of the camera
    ok &= u > 0
    if not ok.any():
        return None
    s = s[ok]
    return np.stack([p + s.min() * d, p + s.max() * d])


def triangulate_lines(
    track: np.ndarray,
    T_wc: np.ndarray,
    xy: np.ndarray,
    vp_dir_w: np.ndarray,
    K: np.ndarray,
    config: LineInitConfig | None = None,
    seed: int = 0,
    what: str = "line tracks",
) -> LineEstimates:
    """Lines from observations grouped by track: poses (n,4,4), segments (n,4), VP directions (n,3).

    `vp_dir_w` holds the world vanishing direction each observation was classified to, NaN for
    non-structural ones; a track whose directions agree uses their mean as its direction. `seed`
    draws the sample of directions the scene's dominant ones are searched in; `what` names the
    tracks in the log.
    """
    cfg = config or LineInitConfig()
    # the world directions most observations were classified to: candidates for weakly classified tracks
    common = dominant_directions(vp_dir_w, seed=seed) if cfg.min_vp_fraction > 0 else np.zeros((0, 3))
    order = np.argsort(track, kind="stable")
    track, T_wc, xy, vp_dir_w = track[order], T_wc[order], xy[order], vp_dir_w[order]
    starts = np.flatnonzero(np.r_[True, track[1:] != track[:-1]]) if len(track) else np.zeros(0, int)
    ends = np.r_[starts[1:], len(track)] if len(track) else np.zeros(0, int)
    planes = observation_planes(T_wc, K, xy) if len(track) else np.zeros((0, 4))
    out_t, out_e, out_vp, out_rms = [], [], [], []
    reasons: dict[str, int] = {}
    for s, e in zip(starts, ends, strict=True):
        why = ""
        if e - s < cfg.min_views:
            why = "too few views"
        elif _plane_angle_deg(planes[s:e, :3]) < cfg.min_plane_angle_deg:
            why = "too little parallax"
        if why:
            reasons[why] = reasons.get(why, 0) + 1
            continue
        d, from_vp = _track_direction(vp_dir_w[s:e], cfg)
        if cfg.min_vp_fraction > 0 and np.isfinite(vp_dir_w[s:e, 0]).mean() < cfg.min_vp_fraction:
            d = _aligned_direction(
                T_wc[s:e], xy[s:e], K, common if d is None else np.vstack([d, common]), cfg
            )
            if d is None:
                reasons["not structural"] = reasons.get("not structural", 0) + 1
                continue
            from_vp = True
        track_planes = planes[s:e] if d is None else planes_through_direction(T_wc[s:e], xy[s:e], K, d)
        p, d = line_through_planes(track_planes, T_wc[s:e, :3, 3], d)
        rms = reprojection_rms(p, d, T_wc[s:e], xy[s:e], K)
        if not np.isfinite(rms).all() or np.sqrt(np.mean(rms**2)) > cfg.max_error_px:
            reasons["reprojection error"] = reasons.get("reprojection error", 0) + 1
            continue
        ends_w = endpoint_extent(p, d, T_wc[s:e], xy[s:e], K, cfg.min_ray_angle_deg)
        if ends_w is None or np.linalg.norm(ends_w[1] - ends_w[0]) <= 0:
            reasons["no extent"] = reasons.get("no extent", 0) + 1
            continue
        depth = np.median(np.linalg.norm(ends_w.mean(axis=0) - T_wc[s:e, :3, 3], axis=1))
        if np.linalg.norm(ends_w[1] - ends_w[0]) > cfg.max_length_over_depth * depth:
            reasons["implausibly long"] = reasons.get("implausibly long", 0) + 1
            continue
        out_t.append(track[s])
        out_e.append(ends_w)
        out_vp.append(from_vp)
        out_rms.append(float(np.sqrt(np.mean(rms**2))))
    if reasons:
        log.info("%s dropped: %s", what, ", ".join(f"{v} {k}" for k, v in sorted(reasons.items())))
    return LineEstimates(
        np.array(out_t, np.int64),
        np.array(out_e, np.float64).reshape(-1, 2, 3),
        np.array(out_vp, bool),
        np.array(out_rms, np.float64),
    )


def vp_image_angle_deg(T_wc: np.ndarray, xy: np.ndarray, K: np.ndarray, d_w: np.ndarray) -> np.ndarray:
    """(n,) image angle (deg) between each segment and the line from its midpoint to the vanishing
    point of the world direction d_w: what the frontend thresholds to classify a segment."""
    vp = np.einsum("nji,j->ni", T_wc[:, :3, :3], d_w) @ K.T  # (n, 3), homogeneous, maybe at infinity
    mid = np.column_stack([0.5 * (xy[:, :2] + xy[:, 2:]), np.ones(len(xy))])
    to_vp = vp[:, :2] - mid[:, :2] * vp[:, 2:3]  # direction from the midpoint towards the VP
    seg = xy[:, 2:] - xy[:, :2]
    cos = np.abs(np.einsum("ni,ni->n", to_vp, seg)) / np.maximum(
        np.linalg.norm(to_vp, axis=1) * np.linalg.norm(seg, axis=1), 1e-300
    )
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def _aligned_direction(
    T_wc: np.ndarray, xy: np.ndarray, K: np.ndarray, candidates: np.ndarray, cfg: LineInitConfig
) -> np.ndarray | None:
    """The candidate world direction whose vanishing points a track's segments line up with best, if
    their image angle (averaged weighted by segment length: long segments give the surer angles) is
    within `max_vp_angle_deg`; None when none is. This decides whether a weakly classified track is
    structural: on the synthetic walks it keeps nearly all of the ground-truth tracks' length and drops
    most of the texture tracks' (more than a median angle does)."""
    if len(candidates) == 0:
        return None
    w = np.maximum(np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1), 1e-9)
    angle = np.array([np.average(vp_image_angle_deg(T_wc, xy, K, c), weights=w) for c in candidates])
    best = int(np.argmin(angle))
    return candidates[best] if angle[best] <= cfg.max_vp_angle_deg else None


def dominant_directions(
    dirs: np.ndarray,
    gate_deg: float = 2.0,
    min_share: float = 0.02,
    max_count: int = 8,
    sample: int = 2000,
    seed: int = 0,
) -> np.ndarray:
    """(k, 3) unit directions that at least `min_share` of the finite rows of `dirs` (n, 3) lie within
    `gate_deg` of (sign-invariant), densest first: the scene's axes as the observations saw them
    (searched among `sample` rows drawn with `seed`)."""
    D = dirs[np.isfinite(dirs).all(axis=1)]
    if len(D) == 0:
        return np.zeros((0, 3))
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    seeds = D[np.random.default_rng(seed).choice(len(D), min(len(D), sample), replace=False)]
    cos_gate = np.cos(np.radians(gate_deg))
    near = (np.abs(seeds @ seeds.T) > cos_gate).astype(np.float32)  # (s, s); counts below are exact
    alive, alive_s = np.ones(len(D), bool), np.ones(len(seeds), bool)
    out: list[np.ndarray] = []
    while len(out) < max_count and alive_s.any():
        counts = (near @ alive_s.astype(np.float32)) * alive_s
        c = seeds[int(np.argmax(counts))]
        for _ in range(3):  # re-centre on the members
            members = alive & (np.abs(D @ c) > cos_gate)
            if not members.any():
                break
            m = (D[members] * np.sign(D[members] @ c)[:, None]).sum(axis=0)
            c = m / np.linalg.norm(m)
        members = alive & (np.abs(D @ c) > cos_gate)
        if members.sum() < max(1, min_share * len(D)):
            break
        out.append(c)
        alive &= ~members
        alive_s &= np.abs(seeds @ c) <= cos_gate
    return np.array(out).reshape(-1, 3)


def _track_direction(dirs: np.ndarray, cfg: LineInitConfig) -> tuple[np.ndarray | None, bool]:
    """The mean of a track's world vanishing directions when they agree (sign-invariant)."""
    dirs = dirs[np.isfinite(dirs).all(axis=1)]
    if len(dirs) == 0:
        return None, False
    dirs = dirs * np.sign(dirs @ dirs[0])[:, None]
    mean = dirs.mean(axis=0)
    mean /= np.linalg.norm(mean)
    spread = np.degrees(np.arccos(np.clip(np.abs(dirs @ mean).min(), -1.0, 1.0)))
    if spread > cfg.vp_direction_spread_deg:
        return None, False
    return mean, True
