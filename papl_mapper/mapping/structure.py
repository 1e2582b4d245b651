"""Principal axes of a whole map: the vertical, horizontal axes by mean shift, soft line weights by EM;
as pipeline stages, the map's lines triangulated, anchored to those axes and the axes updated after BA.

A batch tool sees every line at once, so axis creation runs over all structural lines until no
new axis is accepted (the paper creates one per local map); association then gives every line
its weights w_kj from the world vanishing directions it was observed with.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from papl_mapper.axes import AxesConfig, AxisState, associate, create_axes, remap_weights, update_axes
from papl_mapper.axes.association import direction_checked
from papl_mapper.geometry.triangulation import observation_planes
from papl_mapper.map import Axes, Map
from papl_mapper.mapping.assemble import assemble_map, refine_direction, set_line_states, vp_directions_w
from papl_mapper.mapping.lines import LineEstimates, LineInitConfig, triangulate_lines
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class Structure:
    """Axes (vertical first), per-line weights (M,A) and the axis book-keeping for later updates."""

    axes: Axes
    weights: np.ndarray
    state: AxisState


def hard_weights(weights: np.ndarray) -> np.ndarray:
    """One-hot rows: each associated line goes to its single best axis (the hard-association ablation)."""
    out = np.zeros_like(weights)
    has = weights.sum(axis=1) > 0
    out[np.flatnonzero(has), weights[has].argmax(axis=1)] = 1.0
    return out


def line_weights(
    obs_dirs_w: np.ndarray,
    obs_line: np.ndarray,
    n_lines: int,
    axes: np.ndarray,
    config: AxesConfig,
    hard: bool,
) -> np.ndarray:
    """EM weights (n_lines, A) from packed world vanishing directions (K,3) of line observations."""
    ok = np.isfinite(obs_dirs_w).all(axis=1)
    w = associate((obs_dirs_w[ok], obs_line[ok]), axes, config, n_lines=n_lines)
    return hard_weights(w) if hard else w


def find_structure(
    line_dirs_w: np.ndarray,
    structural: np.ndarray,
    obs_dirs_w: np.ndarray,
    obs_line: np.ndarray,
    vertical_w: np.ndarray,
    config: AxesConfig | None = None,
    hard: bool = False,
    max_axes: int = 8,
    obs_normals_w: np.ndarray | None = None,
    obs_weight: np.ndarray | None = None,
    min_support_fraction: float = 0.0,
    max_tilt_deg: float = 3.0,
) -> Structure:
    """Axes and weights for lines with directions (M,3), `structural` (M,) marking VP-classified ones.

    `obs_dirs_w` (K,3) / `obs_line` (K,) are the world vanishing directions of the lines'
    observations (NaN rows for non-structural observations). With the observations' world
    back-projection plane normals (K,3) and weights (segment lengths), each horizontal axis is
    refined over every observation classified near it, across all frames at once.
    Atlanta world: a new axis must be within `max_tilt_deg` of horizontal and supported by at
    least `min_support_fraction` of the structural lines (a whole recording has many lines, so a
    handful of misclassified ones must not found an axis).
    """
    cfg = dataclasses.replace(config or AxesConfig())
    n = len(line_dirs_w)
    cfg.min_support = max(cfg.min_support, int(np.ceil(min_support_fraction * structural.sum())))
    axes = np.asarray(vertical_w, np.float64).reshape(1, 3) / np.linalg.norm(vertical_w)
    weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    while len(axes) < max_axes:
        free = structural & (weights.sum(axis=1) == 0)
        res = create_axes(
            line_dirs_w[free],
            axes,
            int(free.sum()),
            cfg,
            # no ratio test: it guards a real-time local map against creating axes too eagerly;
            # over a whole recording the support and mean-angle tests of the candidates suffice
            n_structural=0,
        )
        tilt = np.degrees(np.arcsin(np.clip(np.abs(res.new_axes @ axes[0]), 0.0, 1.0)))
        new = res.new_axes[tilt <= max_tilt_deg]
        if len(new) == 0:
            log.debug("axis creation stops: %s", res.reason or "no horizontal candidate accepted")
            break
        axes = np.vstack([axes, new])
        weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    if obs_normals_w is not None and len(axes) > 1:
        w = np.ones(len(obs_normals_w)) if obs_weight is None else obs_weight
        ok = np.isfinite(obs_dirs_w).all(axis=1)
        for a in range(1, len(axes)):
            near = ok.copy()
            near[ok] = np.abs(obs_dirs_w[ok] @ axes[a]) > np.cos(np.radians(cfg.gate_deg / 3))
            if near.sum() >= 3:
                axes[a] = refine_direction(obs_normals_w[near], w[near], axes[a])
        weights = line_weights(obs_dirs_w, obs_line, n, axes, cfg, hard)
    angles = [
        np.degrees(np.arccos(np.clip(abs(a @ axes[0]), 0, 1))) for a in axes[1:]
    ]  # horizontal axes should be near 90 deg from the vertical
    log.info(
        "%d axes (vertical + %d horizontal, %s deg from vertical); %d of %d lines associated",
        len(axes),
        len(axes) - 1,
        ", ".join(f"{a:.1f}" for a in angles) or "-",
        int((weights.sum(axis=1) > 0).sum()),
        n,
    )
    return Structure(Axes(axes, vertical_index=0), weights, AxisState.new(len(axes), vertical_index=0))


@dataclass
class AxisInputs:
    """What the axis update after the full BA needs from line triangulation and axis creation."""

    axes_w: np.ndarray  # (A, 3) axes as created, before the BA moved them
    state: AxisState
    obs_dirs_w: np.ndarray  # (K, 3) world vanishing directions of the line observations
    obs_line: np.ndarray  # (K,) index into line_track
    line_track: np.ndarray  # (M,) sorted track ids of the triangulated lines
    obs_normals_w: np.ndarray  # (K, 3) their back-projection planes' unit normals (`direction_checked`)
    obs_length_px: np.ndarray  # (K,) their segments' lengths

    def join_lines(self, joined: dict[int, int]) -> None:
        """Line tracks merged into others (track -> the track it joined): their vanishing-direction
        observations count for the line they joined when the axis update re-associates the lines."""
        lt = self.line_track
        src = np.array([t for t in joined if t in set(lt.tolist())], np.int64)
        if len(src):
            dst = np.searchsorted(lt, [joined[int(t)] for t in src])
            remap = np.arange(len(lt))
            remap[np.searchsorted(lt, src)] = dst
            self.obs_line = remap[self.obs_line]


@dataclass
class MapLines:
    """Lines triangulated from the segments of the posed frames, and those segments' observations."""

    est: LineEstimates
    track: np.ndarray  # (K,) line track of each observation used
    xy: np.ndarray  # (K, 4) its segment, undistorted pixels
    T_wc: np.ndarray  # (K, 4, 4) pose of its frame
    vp_w: np.ndarray  # (K, 3) world vanishing direction it was classified to (NaN: none)


def triangulate_map_lines(
    tracks: Tracks, T_by_frame: dict[int, np.ndarray], config: LineInitConfig, seed: int = 0
) -> MapLines:
    """Lines from the segments of the frames posed in `T_by_frame` (T_wc by frame; more views than the
    keyframes alone give longer baselines), structural ones along their vanishing direction."""
    sel = np.isin(tracks.line_frame, list(T_by_frame))
    frames, labels = tracks.line_frame[sel], tracks.line_vp[sel]
    T_obs = np.stack([T_by_frame[int(f)] for f in frames]) if sel.any() else np.zeros((0, 4, 4))
    vp_w = vp_directions_w(tracks, frames, labels, T_obs)
    track, xy = tracks.line_track[sel], tracks.line_xy[sel]
    est = triangulate_lines(track, T_obs, xy, vp_w, tracks.camera.K, config, seed)
    log.info("%d lines triangulated, %d from vanishing directions", len(est.track), int(est.from_vp.sum()))
    return MapLines(est, track, xy, T_obs, vp_w)


def structured_map(
    tracks: Tracks,
    m: Map,
    lines: MapLines,
    upright: bool,
    config: AxesConfig,
    anchored: bool,
    line_sigma_px: float,
    line_config: LineInitConfig,
) -> tuple[Map, AxisInputs | None]:
    """The map for the full BA: the keyframes and points of `m` with `lines`, anchored to the principal
    axes found among them (soft or hard association as configured), and what the axis update after
    the BA needs. A line whose segments' planes reject every axis it was associated with was placed
    along a direction its views deny: it is triangulated afresh from those planes, and left out when
    they cannot place it (`line_config`'s limits). Without axes (`anchored` False: every line
    orthonormal, or a map that could not be turned upright) the lines stay free and the second value
    is None."""
    poses = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    points = {int(i): x for i, x in zip(m.points.ids, m.points.xyz, strict=True)}
    est = lines.est
    if not anchored or not upright:
        out = assemble_map(tracks, poses, points, est)
        out.metadata = dict(m.metadata)
        return out, None
    obs_line = np.searchsorted(est.track, lines.track)
    known = np.isin(lines.track, est.track)
    obs_dirs, obs_line = lines.vp_w[known], obs_line[known]
    d = est.endpoints_w[:, 1] - est.endpoints_w[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    xy = lines.xy[known]
    normals = observation_planes(lines.T_wc[known], tracks.camera.K, xy)[:, :3]
    length = np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1)
    structure = find_structure(
        d,
        est.from_vp,
        obs_dirs,
        obs_line,
        np.array([0.0, 0.0, 1.0]),
        config,
        hard=config.association == "hard",
        obs_normals_w=normals,
        obs_weight=length,
        min_support_fraction=config.min_support_fraction,
    )
    associated = int((structure.weights.sum(axis=1) > 0).sum())
    weights, unfit = direction_checked(
        normals, length, obs_line, structure.weights, structure.axes.directions, config, line_sigma_px
    )
    if unfit.any():
        est, keep = freed_lines(est, unfit, lines, tracks.camera.K, line_config)
        log.info(
            "%d of %d associated lines unanchored, %d of them left out: their segments' planes reject "
            "every axis they were associated with (axes.direction_alpha)",
            unfit.sum(),
            associated,
            (~keep).sum(),
        )
        weights = weights[keep]
        seen, obs_line = _renumbered(obs_line, np.where(keep, np.cumsum(keep) - 1, -1))
        obs_dirs, normals, length = obs_dirs[seen], normals[seen], length[seen]
    out = assemble_map(tracks, poses, points, est, structure.axes, weights)
    out.metadata = dict(m.metadata)
    inputs = AxisInputs(
        structure.axes.directions, structure.state, obs_dirs, obs_line, est.track, normals, length
    )
    return out, inputs


def freed_lines(
    est: LineEstimates, unfit: np.ndarray, lines: MapLines, K: np.ndarray, config: LineInitConfig
) -> tuple[LineEstimates, np.ndarray]:
    """`est` with its `unfit` (M,) lines triangulated from their planes alone (they were placed along
    the vanishing direction their planes reject), and which lines remain (M,): those the planes
    cannot place are left out."""
    sel = np.isin(lines.track, est.track[unfit])
    fresh = triangulate_lines(
        lines.track[sel],
        lines.T_wc[sel],
        lines.xy[sel],
        np.full((int(sel.sum()), 3), np.nan),
        K,
        dataclasses.replace(config, min_vp_fraction=0.0),
        what="lines off their axis",
    )
    i = np.searchsorted(est.track, fresh.track)
    endpoints, from_vp, rms = est.endpoints_w.copy(), est.from_vp.copy(), est.rms_px.copy()
    endpoints[i], from_vp[i], rms[i] = fresh.endpoints_w, False, fresh.rms_px
    keep = ~unfit
    keep[i] = True
    return LineEstimates(est.track[keep], endpoints[keep], from_vp[keep], rms[keep]), keep


def _renumbered(obs_line: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which observations (K,) belong to a line that has a row (`row` (M,) per line, -1 where it has
    none), and those observations' lines as rows."""
    seen = row[obs_line] >= 0
    return seen, row[obs_line[seen]]


def update_structure(
    m: Map, inputs: AxisInputs, config: AxesConfig, line_sigma_px: float
) -> tuple[bool, list[str]]:
    """After a full BA: adopt, merge or delete the axes of `m` as they moved, and re-associate its lines
    (in place; without the axes their segments' planes reject, as when the map was structured).
    Returns whether the axes changed (then the BA is worth running again) and what was done."""
    upd = update_axes(inputs.axes_w, m.axes.directions, inputs.state, config)
    w = remap_weights(m.lines.axis_weights, upd.index_map, len(upd.axes))
    messages = upd.messages()
    m.axes = upd.to_map_axes()
    fresh = line_weights(
        inputs.obs_dirs_w,
        inputs.obs_line,
        len(inputs.line_track),
        m.axes.directions,
        config,
        config.association == "hard",
    )
    order = np.searchsorted(inputs.line_track, m.lines.ids)
    weights = np.where(fresh[order].sum(1, keepdims=True) > 0, fresh[order], w)
    row = np.full(len(inputs.line_track), -1)
    row[order] = np.arange(len(order))
    seen, obs_line = _renumbered(inputs.obs_line, row)  # observations of lines still in the map
    m.lines.axis_weights, _ = direction_checked(
        inputs.obs_normals_w[seen],
        inputs.obs_length_px[seen],
        obs_line,
        weights,
        m.axes.directions,
        config,
        line_sigma_px,
    )
    set_line_states(m)
    return bool(upd.adopted or upd.deleted or upd.merged), messages
