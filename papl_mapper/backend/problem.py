"""Select what a bundle adjustment optimises, from a Map, and drop degenerate pieces with logged reasons.

numpy only: the gtsam graph is built from this in `factors.py`. Nothing here changes the Map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from papl_mapper import geometry as geo
from papl_mapper.backend.config import BAConfig, min_parallax_deg
from papl_mapper.errors import GeometryError
from papl_mapper.geometry.lines import line_parallax_deg
from papl_mapper.geometry.triangulation import clear_of_camera
from papl_mapper.map import LineState, Map
from papl_mapper.rows import unique_rows

log = logging.getLogger(__name__)

KIND_ANCHORED = "anchored"
KIND_TVP = "temporary_vp"
KIND_ORTHO = "orthonormal"


@dataclass
class LineGroup:
    """Lines of one representation, with their observations grouped by line (CSR layout)."""

    rows: np.ndarray  # (n,) rows into Map.lines
    obs_start: np.ndarray  # (n + 1,) observations of line i are obs_*[obs_start[i]:obs_start[i + 1]]
    obs_kf: np.ndarray  # (k,) keyframe rows
    obs_xy: np.ndarray  # (k, 4) pixels
    ref_kf: np.ndarray  # (n,) keyframe rows (-1 for orthonormal lines)
    bearing: np.ndarray  # (n, 3) anchor bearing in the reference keyframe (x, y, 1)
    inv_depth: np.ndarray  # (n,) 1 / z of the anchor in the reference keyframe
    L0: np.ndarray  # (n, 6) initial Pluecker line, |v| = 1
    weights: np.ndarray  # (n, A) axis weights in the graph (anchored), zeros otherwise
    offset_dir: np.ndarray  # (n, 3) sideways anchor direction q (z = 0; BAConfig.anchor_offset), else zeros
    obs_bearing: np.ndarray  # (n, 3) bearing of the observed segment midpoint in the reference keyframe
    frame_origin: np.ndarray  # (n, 3) orthonormal lines: origin of the frame their (U, W) live in, else zeros
    frame_scale: np.ndarray  # (n,) orthonormal lines: that frame's unit (geometry.line_frame), else ones

    @classmethod
    def empty(cls, n_axes: int) -> LineGroup:
        z = np.zeros(0, np.int64)
        return cls(
            z,
            np.zeros(1, np.int64),
            z,
            np.zeros((0, 4)),
            z,
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 6)),
            np.zeros((0, n_axes)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
        )

    def __len__(self) -> int:
        return len(self.rows)


@dataclass
class Problem:
    """Everything the factor graph needs, as rows into the Map's arrays."""

    kf_in: np.ndarray  # (N,) bool: keyframe has a variable
    kf_fixed: np.ndarray  # (N,) bool: held at its value (subset of kf_in)
    gauge: tuple[int, int] | None  # keyframe rows (fixed first, scale to second) for a free gauge
    pt_rows: np.ndarray  # (P',) rows into Map.points
    pt_obs_pt: np.ndarray  # (K,) index into pt_rows
    pt_obs_kf: np.ndarray  # (K,) keyframe rows
    pt_obs_uv: np.ndarray  # (K, 2)
    lines: dict[str, LineGroup]
    axis_var: np.ndarray  # (A,) bool: axis direction optimised
    axis_used: np.ndarray  # (A,) bool: some line anchors to it
    dropped: dict[str, int] = field(default_factory=dict)


def _rows_of(ids: np.ndarray, query: np.ndarray) -> np.ndarray:
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], query)
    return order[np.clip(pos, 0, max(len(ids) - 1, 0))]


def _drop(dropped: dict[str, int], key: str, count: int, reason: str) -> None:
    if count:
        dropped[key] = dropped.get(key, 0) + int(count)
        log.info("BA: left out %d %s: %s", count, key.replace("_", " "), reason)


def _distinct_views(owner: np.ndarray, kf: np.ndarray, n: int) -> np.ndarray:
    if len(owner) == 0:
        return np.zeros(n, np.int64)
    pairs = unique_rows(np.stack([owner, kf], 1))
    return np.bincount(pairs[:, 0], minlength=n)


def uses_offset(config: BAConfig, kind: str) -> bool:
    """Whether lines of this kind carry the sideways anchor offset (r, s) instead of the paper's r."""
    return config.anchor_offset and (kind == KIND_ANCHORED or (kind == KIND_TVP and config.tvp_offset))


def build_problem(m: Map, config: BAConfig, window: np.ndarray | None = None) -> Problem:
    """Choose variables and observations. `window` (keyframe rows) restricts BA to a local window:
    landmarks seen there are optimised, other keyframes seeing them are held fixed."""
    m.validate()
    N = len(m.keyframes)
    if N == 0:
        raise GeometryError("map has no keyframes: nothing to adjust")
    K = m.camera.K
    T = m.keyframes.T_wc
    dropped: dict[str, int] = {}
    in_window = np.ones(N, bool) if window is None else np.isin(np.arange(N), window)

    # ---- points -------------------------------------------------------------------------------
    P = len(m.points)
    p_obs = m.points.obs_ids
    p_row = _rows_of(m.points.ids, p_obs[:, 0]) if len(p_obs) else np.zeros(0, np.int64)
    p_kf = _rows_of(m.keyframes.ids, p_obs[:, 1]) if len(p_obs) else np.zeros(0, np.int64)
    p_uv = m.points.obs_uv
    if len(p_obs):
        _, z = geo.project_points(K, T[p_kf], m.points.xyz[p_row])
        front = clear_of_camera(p_row, m.points.xyz, T[p_kf, :3, 3], z)
        _drop(dropped, "point_observations", (~front).sum(), "point behind the camera or on its centre")
        p_row, p_kf, p_uv = p_row[front], p_kf[front], p_uv[front]
    pt_keep = _distinct_views(p_row, p_kf, P) >= config.min_views
    _drop(dropped, "points", (~pt_keep).sum(), f"seen from fewer than {config.min_views} keyframes")
    if window is not None:
        seen = np.zeros(P, bool)
        seen[p_row[in_window[p_kf]]] = True
        pt_keep &= seen
    sel = pt_keep[p_row]
    p_row, p_kf, p_uv = p_row[sel], p_kf[sel], p_uv[sel]
    pt_rows = np.flatnonzero(pt_keep)
    pt_index = np.full(P, -1, np.int64)
    pt_index[pt_rows] = np.arange(len(pt_rows))

    # ---- lines ---------------------------------------------------------------------------------
    lines, axis_used = _build_lines(m, config, in_window if window is not None else None, dropped)

    # ---- keyframes -----------------------------------------------------------------------------
    used = np.zeros(N, bool)
    used[p_kf] = True
    for grp in lines.values():
        used[grp.obs_kf] = True
    lonely = in_window & ~used
    _drop(dropped, "keyframes", lonely.sum(), "see no point or line of the adjustment (kept as they are)")
    kf_in = used
    kf_fixed = kf_in & ~in_window
    if not config.optimize_poses:
        kf_fixed = kf_in.copy()
    gauge = None
    if not kf_fixed.any():
        gauge = _choose_gauge(T, np.flatnonzero(kf_in))
    elif config.optimize_poses and window is not None and kf_fixed.sum() == 1:
        log.debug("BA: local window has one fixed keyframe; scale is held by a prior on a second one")
        first = int(np.flatnonzero(kf_fixed)[0])
        others = np.flatnonzero(kf_in & ~kf_fixed)
        if len(others):
            gauge = (
                first,
                int(others[np.argmax(np.linalg.norm(T[others, :3, 3] - T[first, :3, 3], axis=1))]),
            )

    # ---- axes ----------------------------------------------------------------------------------
    A = len(m.axes)
    n_per_axis = (lines[KIND_ANCHORED].weights > 0).sum(axis=0) if A else np.zeros(0, np.int64)
    few = axis_used & (n_per_axis < config.min_lines_per_axis)
    if few.any():
        log.debug(
            "BA: holding axes %s fixed: they anchor fewer than %d lines",
            np.flatnonzero(few).tolist(),
            config.min_lines_per_axis,
        )
        dropped["axes_held_fixed"] = int(few.sum())
    axis_var = axis_used & ~few & config.optimize_axes & (config.structural_lines == "anchored")

    return Problem(
        kf_in=kf_in,
        kf_fixed=kf_fixed,
        gauge=gauge,
        pt_rows=pt_rows,
        pt_obs_pt=pt_index[p_row],
        pt_obs_kf=p_kf,
        pt_obs_uv=p_uv,
        lines=lines,
        axis_var=axis_var,
        axis_used=axis_used,
        dropped=dropped,
    )


def _choose_gauge(T: np.ndarray, rows: np.ndarray) -> tuple[int, int] | None:
    """First keyframe fixed; scale from the distance to the next one that moved (else the farthest)."""
    if len(rows) < 2:
        return None
    first = int(rows[0])
    d = np.linalg.norm(T[rows, :3, 3] - T[first, :3, 3], axis=1)
    if d.max() <= 1e-9:
        raise GeometryError(
            "all keyframes share one camera centre: a monocular map needs translation to fix its scale"
        )
    moved = np.flatnonzero(d > 1e-3 * d.max())
    return first, int(rows[moved[0]])


def _build_lines(
    m: Map, config: BAConfig, in_window: np.ndarray | None, dropped: dict[str, int]
) -> tuple[dict[str, LineGroup], np.ndarray]:
    lines = m.lines
    M = len(lines)
    A = len(m.axes)
    K = m.camera.K
    T = m.keyframes.T_wc
    empty = {k: LineGroup.empty(A) for k in (KIND_ANCHORED, KIND_TVP, KIND_ORTHO)}
    if M == 0:
        return empty, np.zeros(A, bool)
    obs = lines.obs_ids
    o_row = _rows_of(lines.ids, obs[:, 0]) if len(obs) else np.zeros(0, np.int64)
    o_kf = _rows_of(m.keyframes.ids, obs[:, 1]) if len(obs) else np.zeros(0, np.int64)
    o_xy = lines.obs_xy

    # representation per line
    w = np.where(lines.axis_weights >= config.min_axis_weight, lines.axis_weights, 0.0)
    state = lines.state.astype(np.int64)
    anchored = state == LineState.ANCHORED
    no_axis = anchored & (w.sum(axis=1) <= 0)
    _drop(
        dropped,
        "anchored_lines_without_axis",
        no_axis.sum(),
        "no axis weight >= min_axis_weight; optimised as orthonormal lines",
    )
    kind = np.where(anchored & ~no_axis, 2, np.where(state == LineState.TEMPORARY_VP, 1, 0))
    w[kind != 2] = 0.0

    # initial geometry: direction (axis of largest weight for anchored lines) through the midpoint
    ends = lines.endpoints_w
    mid = ends.mean(axis=1)
    seg = ends[:, 1] - ends[:, 0]
    seglen = np.linalg.norm(seg, axis=1)
    d = seg / np.maximum(seglen, 1e-300)[:, None]
    if A:
        best = np.argmax(w, axis=1)
        d = np.where((kind == 2)[:, None], m.axes.directions[best], d)
    bad_len = (kind != 2) & (seglen <= 1e-12)
    L0 = geo.plucker_from_point_dir(mid, d)

    # observations: zero-length segments and lines along the viewing ray
    keep = np.ones(len(obs), bool)
    short = np.linalg.norm(o_xy[:, 2:] - o_xy[:, :2], axis=1) < config.min_segment_px
    _drop(dropped, "line_observations_short", short.sum(), f"segment shorter than {config.min_segment_px} px")
    keep &= ~short
    if len(obs):
        L_c = geo.plucker_to_camera(L0[o_row], T[o_kf])
        mid_c = geo.transform(geo.invert(T[o_kf]), mid[o_row])
        sin = np.linalg.norm(L_c[:, :3], axis=1) / np.maximum(
            np.linalg.norm(mid_c, axis=1) * np.linalg.norm(L_c[:, 3:], axis=1), 1e-300
        )
        along = sin < np.sin(np.radians(config.min_ray_angle_deg))
        behind = mid_c[:, 2] <= 1e-9
        _drop(
            dropped,
            "line_observations_along_ray",
            (along & keep).sum(),
            "3D line nearly parallel to the viewing ray (projects to a point)",
        )
        _drop(dropped, "line_observations_behind", (behind & ~along & keep).sum(), "line behind the camera")
        keep &= ~along & ~behind
    o_row, o_kf, o_xy = o_row[keep], o_kf[keep], o_xy[keep]

    views = _distinct_views(o_row, o_kf, M)
    line_keep = (views >= config.min_views) & ~bad_len
    _drop(dropped, "lines_zero_length", bad_len.sum(), "zero-length segment has no direction")
    _drop(
        dropped,
        "lines",
        ((views < config.min_views) & ~bad_len).sum(),
        f"seen from fewer than {config.min_views} keyframes",
    )
    need = min_parallax_deg(config, kind == 0)
    if (need > 0).any() and len(o_row):
        # as points need a triangulation angle: lines whose observing centres span too small an angle about
        # their start geometry have no observable depth (e.g. walked along); each representation judges its
        # own start line (anchored: the axis direction through the midpoint)
        par = line_parallax_deg(geo.normalize_plucker(L0), o_row, T[o_kf, :3, 3], M)
        flat = line_keep & (par < need)
        _drop(
            dropped,
            "lines_low_parallax",
            flat.sum(),
            "observing cameras span too small an angle about the line (depth unobservable; "
            "BAConfig.min_line_parallax_deg, min_orthonormal_parallax_deg)",
        )
        line_keep &= ~flat
    if in_window is not None:
        seen = np.zeros(M, bool)
        seen[o_row[in_window[o_kf]]] = True
        line_keep &= seen

    # reference keyframe: the stored one if it observes the line (kept observation, line not along the
    # midpoint ray, met in front), else the first observing keyframe that qualifies. The bearing is the
    # observed segment midpoint there, the inverse depth that of the ray's point closest to the line.
    needs_ref = kind >= 1
    stored = np.full(M, -1, np.int64)
    has_ref = lines.ref_keyframe_id >= 0
    stored[has_ref] = _rows_of(m.keyframes.ids, lines.ref_keyframe_id[has_ref])
    # The anchor's ray goes through the observed segment midpoint in the reference keyframe (the paper) or,
    # with anchor_bearing "estimate", through the foot of that midpoint on the current line's image (its ray
    # meets the current line). Lines with the sideways offset can leave that ray (q: across the segment).
    anchor_xy = o_xy
    offset_line = np.array([uses_offset(config, KIND_TVP), uses_offset(config, KIND_ANCHORED)])[
        np.clip(kind - 1, 0, 1)
    ] & (kind >= 1)
    seg_px = np.cross(
        np.concatenate([o_xy[:, :2], np.ones((len(o_xy), 1))], 1),
        np.concatenate([o_xy[:, 2:], np.ones((len(o_xy), 1))], 1),
    )
    if config.anchor_bearing == "estimate" and len(o_xy):
        seg_px = geo.project_line(K, geo.plucker_to_camera(L0[o_row], T[o_kf]))
        mid = (o_xy[:, :2] + o_xy[:, 2:]) / 2.0
        s2 = np.maximum(np.sum(seg_px[:, :2] ** 2, 1), 1e-300)
        foot = mid - ((np.sum(seg_px[:, :2] * mid, 1) + seg_px[:, 2]) / s2)[:, None] * seg_px[:, :2]
        anchor_xy = np.concatenate([foot, foot], 1)
    q_all = np.where(offset_line[o_row, None], geo.anchor_offset_direction(seg_px, K), 0.0)
    b_all, r_all, sin_all = geo.anchor_from_observation(anchor_xy, K, T[o_kf], L0[o_row])
    b_obs, _, _ = geo.anchor_from_observation(o_xy, K, T[o_kf], L0[o_row]) if len(o_xy) else (b_all, 0, 0)
    cand = needs_ref[o_row] & np.isfinite(r_all) & (r_all > 0)
    cand &= sin_all > np.sin(np.radians(config.min_ray_angle_deg))
    prefer = (o_kf == stored[o_row]).astype(np.int64)
    # best candidate per line: qualifying first, then the stored keyframe, then the earliest observation
    order = np.lexsort((np.arange(len(o_row)), -prefer, ~cand, o_row))
    first = np.ones(len(order), bool)
    first[1:] = o_row[order][1:] != o_row[order][:-1]
    pick = order[first]
    pick = pick[cand[pick]]
    ref = np.full(M, -1, np.int64)
    bearing = np.zeros((M, 3))
    q = np.zeros((M, 3))
    obs_bearing = np.zeros((M, 3))
    inv = np.full(M, np.nan)
    ref[o_row[pick]] = o_kf[pick]
    bearing[o_row[pick]] = b_all[pick]
    q[o_row[pick]] = q_all[pick]
    obs_bearing[o_row[pick]] = b_obs[pick]
    inv[o_row[pick]] = r_all[pick]
    no_ref = needs_ref & (ref < 0) & line_keep
    _drop(
        dropped,
        "lines_no_reference",
        no_ref.sum(),
        "no observing keyframe whose midpoint ray meets the line in front of the camera",
    )
    line_keep &= ~no_ref

    groups = {}
    for code, name in ((2, KIND_ANCHORED), (1, KIND_TVP), (0, KIND_ORTHO)):
        rows = np.flatnonzero(line_keep & (kind == code))
        sel = np.isin(o_row, rows)
        r_sel, kf_sel, xy_sel = o_row[sel], o_kf[sel], o_xy[sel]
        order = np.argsort(r_sel, kind="stable")
        r_sel, kf_sel, xy_sel = r_sel[order], kf_sel[order], xy_sel[order]
        local = np.searchsorted(rows, r_sel)
        counts = np.bincount(local, minlength=len(rows))
        start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        L0_rows = geo.normalize_plucker(L0[rows])
        origin, scale = np.zeros((len(rows), 3)), np.ones(len(rows))
        if code == 0 and len(rows):  # orthonormal lines live in a frame at their cameras' mean centre
            centre = np.zeros((len(rows), 3))
            np.add.at(centre, local, T[kf_sel, :3, 3])
            origin, scale = geo.line_frame(L0_rows, centre / np.maximum(counts, 1)[:, None])
        groups[name] = LineGroup(
            rows=rows,
            obs_start=start,
            obs_kf=kf_sel,
            obs_xy=xy_sel,
            ref_kf=ref[rows] if code else np.full(len(rows), -1, np.int64),
            bearing=bearing[rows],
            inv_depth=inv[rows],
            L0=L0_rows,
            weights=w[rows] if A else np.zeros((len(rows), 0)),
            offset_dir=q[rows],
            obs_bearing=obs_bearing[rows],
            frame_origin=origin,
            frame_scale=scale,
        )
    axis_used = (groups[KIND_ANCHORED].weights > 0).any(axis=0) if A else np.zeros(0, bool)
    return groups, axis_used
