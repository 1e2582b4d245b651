"""Incremental keyframe registration from point tracks: initialise, PnP, triangulate, repeat.

This gives the first estimate of keyframe poses and points; line triangulation, axis
management and bundle adjustment refine it. Poses are `T_cw` (world to camera) here because
PnP and projection want them; the Map stores `T_wc`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.mapping.initialise import InitConfig, initialise_two_view
from papl_mapper.mapping.tracking import PnPConfig, track_pnp
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class IncrementalConfig:
    """Settings of incremental keyframe registration."""

    init: InitConfig = field(default_factory=InitConfig)
    """Two-view initialisation thresholds."""
    pnp: PnPConfig = field(default_factory=PnPConfig)
    """PnP tracking thresholds."""
    init_search_keyframes: int = 25
    """How many keyframes after the first one to try as the initialisation partner."""
    min_parallax_deg: float = 1.0
    """Smallest ray angle for triangulating a new point."""
    max_reprojection_px: float = 3.0
    """Largest reprojection error of a newly triangulated point in the views that made it."""


@dataclass
class Registration:
    """Registered keyframes (rows into the Tracks frames) with poses `T_cw`, and points by track id."""

    frames: list[int] = field(default_factory=list)
    T_cw: dict[int, np.ndarray] = field(default_factory=dict)
    points_w: dict[int, np.ndarray] = field(default_factory=dict)
    lost: list[int] = field(default_factory=list)
    """Keyframes that could not be registered (tracking loss)."""
    init_frames: tuple[int, int] = (-1, -1)


ProgressCallback = Callable[[int, int, str], None]


def _normalised(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def _common(tracks: Tracks, f1: int, f2: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    id1, uv1 = tracks.points_in(f1)
    id2, uv2 = tracks.points_in(f2)
    common, i1, i2 = np.intersect1d(id1, id2, assume_unique=True, return_indices=True)
    return common, uv1[i1], uv2[i2]


def triangulate_multiview(
    T_cw: np.ndarray, uv: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """DLT triangulation of one point from V views: poses (V,4,4), pixels (V,2) -> point, errors, angle."""
    P = K @ T_cw[:, :3, :]  # (V, 3, 4)
    A = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]])  # (2V, 4)
    X = np.linalg.svd(A)[2][-1]
    X = X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)
    Xc = np.einsum("vij,j->vi", T_cw[:, :3, :3], X) + T_cw[:, :3, 3]  # (V, 3)
    proj = Xc @ K.T
    err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - uv, axis=1)
    err[Xc[:, 2] <= 0] = np.inf
    centres = -np.einsum("vji,vj->vi", T_cw[:, :3, :3], T_cw[:, :3, 3])  # (V, 3)
    rays = X - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    max_angle = np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0)))
    return X, err, max_angle


def _triangulate_new(tracks: Tracks, reg: Registration, frame: int, cfg: IncrementalConfig) -> int:
    """Triangulate point tracks seen in `frame` and at least one earlier registered keyframe."""
    K = tracks.camera.K
    ids, _ = tracks.points_in(frame)
    new = ids[~np.isin(ids, np.fromiter(reg.points_w, np.int64, len(reg.points_w)))]
    if len(new) == 0:
        return 0
    registered = np.array(reg.frames)
    sel = np.isin(tracks.point_track, new) & np.isin(tracks.point_frame, registered)
    obs_track, obs_frame, obs_uv = tracks.point_track[sel], tracks.point_frame[sel], tracks.point_uv[sel]
    order = np.argsort(obs_track, kind="stable")
    obs_track, obs_frame, obs_uv = obs_track[order], obs_frame[order], obs_uv[order]
    starts = np.flatnonzero(np.r_[True, obs_track[1:] != obs_track[:-1]])
    ends = np.r_[starts[1:], len(obs_track)]
    added = 0
    for s, e in zip(starts, ends, strict=True):
        if e - s < 2:
            continue
        T = np.stack([reg.T_cw[int(f)] for f in obs_frame[s:e]])
        X, err, angle = triangulate_multiview(T, obs_uv[s:e], K)
        if np.isfinite(X).all() and angle >= cfg.min_parallax_deg and err.max() < cfg.max_reprojection_px:
            reg.points_w[int(obs_track[s])] = X
            added += 1
    return added


def _initialise(tracks: Tracks, keyframes: np.ndarray, cfg: IncrementalConfig) -> Registration | None:
    K = tracks.camera.K
    for a in range(len(keyframes)):
        for b in range(a + 1, min(len(keyframes), a + 1 + cfg.init_search_keyframes)):
            f1, f2 = int(keyframes[a]), int(keyframes[b])
            common, uv1, uv2 = _common(tracks, f1, f2)
            res = initialise_two_view(_normalised(uv1, K), _normalised(uv2, K), K[0, 0], cfg.init)
            if not res.ok:
                log.debug("init %d-%d: %s", f1, f2, res.reason)
                continue
            reg = Registration(frames=[f1, f2], init_frames=(f1, f2))
            reg.T_cw[f1] = np.eye(4)
            T2 = np.eye(4)
            T2[:3, :3], T2[:3, 3] = res.R_21, res.t_21
            reg.T_cw[f2] = T2
            for tid, X in zip(common[res.point_index], res.points_1, strict=True):
                reg.points_w[int(tid)] = X
            log.info("initialised on keyframes %d and %d: %s", f1, f2, res.reason)
            return reg
    return None


def register_keyframes(
    tracks: Tracks, config: IncrementalConfig | None = None, progress: ProgressCallback | None = None
) -> Registration:
    """Register every keyframe of `tracks` in order; unregistrable ones are listed in `lost`."""
    cfg = config or IncrementalConfig()
    tracks.validate()
    keyframes = np.flatnonzero(tracks.is_keyframe)
    reg = _initialise(tracks, keyframes, cfg)
    if reg is None:
        from papl_mapper.errors import InputError

        raise InputError(
            f"could not initialise from {len(keyframes)} keyframes: too little parallax or too few "
            "tracked points; try a recording with sideways or forward motion, or a lower --step"
        )
    K = tracks.camera.K
    start = int(np.searchsorted(keyframes, reg.init_frames[0]))
    order = [int(f) for f in keyframes[start:] if f not in reg.T_cw]
    last_T = reg.T_cw[reg.init_frames[1]]
    for i, f in enumerate(order):
        ids, uv = tracks.points_in(f)
        known = np.array([t in reg.points_w for t in ids.tolist()], bool)
        if known.sum() < cfg.pnp.min_inliers:
            reg.lost.append(f)
            continue
        X = np.stack([reg.points_w[int(t)] for t in ids[known]])
        res = track_pnp(X, uv[known], K, last_T, cfg.pnp)
        if not res.ok:
            log.info("keyframe %d not registered: %s", f, res.reason)
            reg.lost.append(f)
            continue
        reg.T_cw[f] = last_T = res.T_cw
        reg.frames.append(f)
        added = _triangulate_new(tracks, reg, f, cfg)
        log.debug("keyframe %d: %s, %d new points", f, res.reason, added)
        if progress:
            progress(i + 1, len(order), f"{len(reg.points_w)} points")
    # keyframes before the initialisation pair (if the init started late) are tracked backwards
    for f in reversed(keyframes[:start].tolist()):
        ids, uv = tracks.points_in(int(f))
        known = np.array([t in reg.points_w for t in ids.tolist()], bool)
        if known.sum() >= cfg.pnp.min_inliers:
            X = np.stack([reg.points_w[int(t)] for t in ids[known]])
            res = track_pnp(X, uv[known], K, reg.T_cw[reg.frames[0]], cfg.pnp)
            if res.ok:
                reg.T_cw[int(f)] = res.T_cw
                reg.frames.insert(0, int(f))
                continue
        reg.lost.append(int(f))
    return reg
