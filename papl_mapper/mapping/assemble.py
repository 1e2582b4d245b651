"""Build the Map from registered keyframes, triangulated points and lines, and rotate it upright.

Keyframe ids are the Tracks frame rows, point and line ids their track ids, so every
observation in the Map refers back to the recording without a lookup table.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.errors import GeometryError
from papl_mapper.geometry.lines import endpoint_errors, plucker_from_endpoints, plucker_to_camera
from papl_mapper.geometry.se3 import project_points
from papl_mapper.geometry.triangulation import clear_of_camera, observation_planes
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.rows import unique_rows
from papl_mapper.tracks import Tracks


def vp_directions_w(tracks: Tracks, frame: np.ndarray, label: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """World vanishing direction (n,3) of each segment observation, NaN for non-structural ones."""
    out = np.full((len(frame), 3), np.nan)
    ok = label >= 0
    if ok.any():
        d_c = tracks.vp_dirs_c[frame[ok], label[ok]]
        out[ok] = np.einsum("nij,nj->ni", T_wc[ok, :3, :3], d_c)
    return out


def assemble_map(
    tracks: Tracks,
    T_wc_by_frame: dict[int, np.ndarray],
    points_w: dict[int, np.ndarray],
    lines: LineEstimates,
    axes: Axes | None = None,
    line_weights: np.ndarray | None = None,
    metadata: dict | None = None,
    point_rows: np.ndarray | None = None,
) -> Map:
    """A Map of the registered keyframes, with the observations of points and lines in them.

    `point_rows` (ascending), when given, are the only point observation rows to consider, so a
    small map of a large recording is made without scanning every observation.

    `line_weights` (M,A) are the soft axis associations of `lines` to `axes`; lines with no
    weight stay orthonormal, the others are anchored in their first observing keyframe.
    """
    frames = np.array(sorted(T_wc_by_frame), np.int64)
    kf = Keyframes(
        frames,
        tracks.frame_index[frames].astype(np.int64),
        tracks.timestamp[frames].astype(np.float64),
        np.stack([T_wc_by_frame[int(f)] for f in frames]) if len(frames) else np.zeros((0, 4, 4)),
    )
    pids = np.array(sorted(points_w), np.int64)
    xyz = np.stack([points_w[int(p)] for p in pids]) if len(pids) else np.zeros((0, 3))
    if point_rows is None:
        sel = np.isin(tracks.point_track, pids) & np.isin(tracks.point_frame, frames)
    else:
        sel = point_rows[
            np.isin(tracks.point_track[point_rows], pids) & np.isin(tracks.point_frame[point_rows], frames)
        ]
    pts = Points(
        pids,
        xyz,
        np.full((len(pids), 3), 160, np.uint8),
        np.column_stack([tracks.point_track[sel], tracks.point_frame[sel]]).astype(np.int64),
        tracks.point_uv[sel].astype(np.float64),
    )
    axes = axes or Axes.empty()
    n_axes = len(axes)
    weights = np.zeros((len(lines.track), n_axes)) if line_weights is None else np.asarray(line_weights)
    seen = np.isin(lines.track, tracks.line_track[np.isin(tracks.line_frame, frames)])
    if not seen.all():  # a line needs a keyframe observation to be in the map
        lines = LineEstimates(
            lines.track[seen], lines.endpoints_w[seen], lines.from_vp[seen], lines.rms_px[seen]
        )
        weights = weights[seen]
    anchored = weights.sum(axis=1) > 0 if n_axes else np.zeros(len(lines.track), bool)
    sel = np.isin(tracks.line_track, lines.track) & np.isin(tracks.line_frame, frames)
    obs_ids = np.column_stack([tracks.line_track[sel], tracks.line_frame[sel]]).astype(np.int64)
    ref = np.full(len(lines.track), -1, np.int64)
    inv_depth = np.full(len(lines.track), np.nan)
    if len(obs_ids):
        order = np.lexsort((obs_ids[:, 1], obs_ids[:, 0]))
        first = order[np.r_[True, obs_ids[order[1:], 0] != obs_ids[order[:-1], 0]]]
        first_kf = dict(zip(obs_ids[first, 0].tolist(), obs_ids[first, 1].tolist(), strict=True))
        ref = np.array([first_kf[int(t)] for t in lines.track], np.int64)
        T_ref = np.stack([T_wc_by_frame[int(f)] for f in ref]) if len(ref) else np.zeros((0, 4, 4))
        mid = lines.endpoints_w.mean(axis=1)
        depth = np.linalg.norm(mid - T_ref[:, :3, 3], axis=1)
        inv_depth = np.where(anchored, 1.0 / np.maximum(depth, 1e-12), np.nan)
    ln = Lines(
        lines.track.astype(np.int64),
        lines.endpoints_w.astype(np.float64),
        weights.astype(np.float64),
        np.where(anchored, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8),
        np.where(anchored, ref, -1),
        inv_depth,
        obs_ids,
        tracks.line_xy[sel].astype(np.float64),
    )
    cam = Camera.from_dict(tracks.camera.to_dict())
    return Map(cam, kf, pts, ln, axes, dict(metadata or {"units": "arbitrary"}))


def vertical_in_world(tracks: Tracks, T_wc_by_frame: dict[int, np.ndarray]) -> np.ndarray | None:
    """The world 'up' direction from each registered frame's vertical vanishing direction, or None.

    The frontend's vertical direction points up in the camera (towards -y for an upright camera);
    rotated into the world by each pose, their robust mean is the world vertical.
    """
    if len(tracks.vertical_vp) == 0:
        return None
    dirs = []
    for f, T in T_wc_by_frame.items():
        v = int(tracks.vertical_vp[f])
        if v < 0:
            continue
        d = tracks.vp_dirs_c[f, v]
        if np.isfinite(d).all():
            dirs.append(T[:3, :3] @ (d / np.linalg.norm(d)))
    if not dirs:
        return None
    D = np.array(dirs)
    up = np.median(D, axis=0)
    for _ in range(3):  # re-centre on the directions near the current estimate
        up /= np.linalg.norm(up)
        near = D[D @ up > np.cos(np.radians(5.0))]
        if len(near) == 0:
            break
        up = near.mean(axis=0)
    up /= np.linalg.norm(up)
    # every segment labelled vertical in any registered frame constrains the one world vertical
    frames = np.array(sorted(T_wc_by_frame))
    sel = np.isin(tracks.line_frame, frames)
    sel[sel] &= tracks.line_vp[sel] == tracks.vertical_vp[tracks.line_frame[sel]]
    if sel.sum() >= 3:
        T = np.stack([T_wc_by_frame[int(f)] for f in tracks.line_frame[sel]])
        xy = tracks.line_xy[sel]
        planes = observation_planes(T, tracks.camera.K, xy)
        length = np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1)
        up = refine_direction(planes[:, :3], length, up)
    return up


def refine_direction(
    normals: np.ndarray, weights: np.ndarray, init: np.ndarray, gate_deg: float = 3.0
) -> np.ndarray:
    """The direction lying in the planes with normals (n,3), near `init`: weighted SVD on the inliers.

    A segment's back-projection plane contains its 3D direction, so the common direction of
    many segments is the smallest singular vector of their stacked plane normals; segments
    whose plane is more than `gate_deg` off the current estimate are left out, re-gated 5 times.
    """
    d = init / np.linalg.norm(init)
    for _ in range(5):
        inl = np.abs(normals @ d) < np.sin(np.radians(gate_deg))
        if inl.sum() < 3:
            break
        v = np.linalg.svd(normals[inl] * np.sqrt(weights[inl])[:, None], full_matrices=False)[2][-1]
        d = v if v @ d >= 0 else -v
    return d


def rotation_to_z(up_w: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector `up_w` to +Z."""
    up = np.asarray(up_w, np.float64) / np.linalg.norm(up_w)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)
    c = float(up @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def transform_map(m: Map, R: np.ndarray, t: np.ndarray | None = None, scale: float = 1.0) -> Map:
    """Apply the similarity x -> scale * R x + t to everything in the map (in place), and return it."""
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) <= 0:
        raise GeometryError("transform_map needs a proper rotation")
    t = np.zeros(3) if t is None else np.asarray(t, np.float64)
    T = m.keyframes.T_wc.copy()
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = scale * T[:, :3, 3] @ R.T + t
    m.keyframes.T_wc = T
    m.points.xyz = scale * m.points.xyz @ R.T + t
    m.lines.endpoints_w = scale * m.lines.endpoints_w @ R.T + t
    m.lines.inverse_depth = m.lines.inverse_depth / scale
    if len(m.axes):
        m.axes.directions = m.axes.directions @ R.T
    return m


def cull_observations(
    m: Map, max_point_px: float, max_line_px: float, min_views: int = 2, min_line_views: int = 2
) -> dict[str, int]:
    """Drop outlier observations (in place): reprojection error over the limits, or a point behind the
    camera or on its centre (`geometry.triangulation.clear_of_camera`).

    Points left with fewer than `min_views` distinct keyframes, and lines with fewer than
    `min_line_views`, are removed with their observations, so bundle adjustment never sees an
    unconstrained point. (A line triangulated from many frames may keep a single keyframe view:
    BA holds it as it is.) Returns the counts.
    """
    kf_row = {int(k): i for i, k in enumerate(m.keyframes.ids)}
    T = m.keyframes.T_wc
    K = m.camera.K
    counts = {}
    pts = m.points
    if len(pts.obs_ids):
        rows = np.searchsorted(pts.ids, pts.obs_ids[:, 0])
        kfs = np.array([kf_row[int(k)] for k in pts.obs_ids[:, 1]])
        uv, z = project_points(K, T[kfs], pts.xyz[rows])
        ok = clear_of_camera(rows, pts.xyz, T[kfs, :3, 3], z)
        ok &= np.linalg.norm(uv - pts.obs_uv, axis=1) <= max_point_px
        counts["point_observations"] = int((~ok).sum())
        pts.obs_ids, pts.obs_uv = pts.obs_ids[ok], pts.obs_uv[ok]
    keep = _views(pts.ids, pts.obs_ids) >= min_views
    counts["points"] = int((~keep).sum())
    pts.ids, pts.xyz, pts.color = pts.ids[keep], pts.xyz[keep], pts.color[keep]
    sel = np.isin(pts.obs_ids[:, 0], pts.ids)
    pts.obs_ids, pts.obs_uv = pts.obs_ids[sel], pts.obs_uv[sel]
    ln = m.lines
    if len(ln.obs_ids):
        rows = np.searchsorted(ln.ids, ln.obs_ids[:, 0])
        kfs = np.array([kf_row[int(k)] for k in ln.obs_ids[:, 1]])
        ends = ln.endpoints_w[rows]
        L_w = plucker_from_endpoints(ends[:, 0], ends[:, 1])
        L_c = plucker_to_camera(L_w, T[kfs])
        err = np.abs(endpoint_errors(K, L_c, ln.obs_xy)).max(axis=1)
        _, z = project_points(K, T[kfs], ends.mean(axis=1))
        ok = (z > 0) & (err <= max_line_px)
        counts["line_observations"] = int((~ok).sum())
        ln.obs_ids, ln.obs_xy = ln.obs_ids[ok], ln.obs_xy[ok]
    keep = _views(ln.ids, ln.obs_ids) >= min_line_views
    counts["lines"] = int((~keep).sum())
    _keep_lines(ln, keep)
    # an anchored line's reference keyframe must still observe it
    if len(ln):
        seen = set(map(tuple, ln.obs_ids.tolist()))
        for i in np.flatnonzero(ln.ref_keyframe_id >= 0):
            if (int(ln.ids[i]), int(ln.ref_keyframe_id[i])) not in seen:
                ln.ref_keyframe_id[i] = int(ln.obs_ids[ln.obs_ids[:, 0] == ln.ids[i], 1].min())
                _, z = project_points(K, T[kf_row[int(ln.ref_keyframe_id[i])]], ln.endpoints_w[i].mean(0))
                ln.inverse_depth[i] = 1.0 / max(float(z), 1e-12)
    return counts


def _views(ids: np.ndarray, obs_ids: np.ndarray) -> np.ndarray:
    """Distinct keyframes observing each id."""
    if len(obs_ids) == 0:
        return np.zeros(len(ids), np.int64)
    pairs = unique_rows(obs_ids)
    return np.bincount(np.searchsorted(ids, pairs[:, 0]), minlength=len(ids))


def drop_stray_lines(m: Map, margin: float = 0.2, percentile: float = 1.0) -> int:
    """Remove lines (in place) with an endpoint outside the points' box (robust percentiles, grown
    by `margin` of its diagonal): a segment seen almost end-on gets an unbounded extent."""
    ln = m.lines
    if len(ln) == 0 or len(m.points) < 20:
        return 0
    lo = np.percentile(m.points.xyz, percentile, axis=0)
    hi = np.percentile(m.points.xyz, 100.0 - percentile, axis=0)
    grow = margin * np.linalg.norm(hi - lo)
    ends = ln.endpoints_w.reshape(-1, 6)
    inside = (ends >= np.tile(lo - grow, 2)) & (ends <= np.tile(hi + grow, 2))
    keep = inside.all(axis=1)
    _keep_lines(ln, keep)
    return int((~keep).sum())


def _keep_lines(ln: Lines, keep: np.ndarray) -> None:
    """Keep the lines where `keep` (M,) is True, with their observations (in place)."""
    for name in ("ids", "endpoints_w", "axis_weights", "state", "ref_keyframe_id", "inverse_depth"):
        setattr(ln, name, getattr(ln, name)[keep])
    sel = np.isin(ln.obs_ids[:, 0], ln.ids)
    ln.obs_ids, ln.obs_xy = ln.obs_ids[sel], ln.obs_xy[sel]


def set_line_states(m: Map) -> None:
    """Lines with axis weight become anchored, the others orthonormal (in place), keeping the anchor
    data consistent: a newly anchored line is referenced to its first observing keyframe with the
    inverse depth of its midpoint there; an orthonormal line has none."""
    ln = m.lines
    anchored = ln.axis_weights.sum(axis=1) > 0 if ln.axis_weights.size else np.zeros(len(ln), bool)
    ln.state = np.where(anchored, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8)
    need = np.flatnonzero(anchored & ((ln.ref_keyframe_id < 0) | ~np.isfinite(ln.inverse_depth)))
    for i in need:
        kfs = ln.obs_ids[ln.obs_ids[:, 0] == ln.ids[i], 1]
        row = int(np.searchsorted(m.keyframes.ids, kfs.min()))
        _, z = project_points(m.camera.K, m.keyframes.T_wc[row], ln.endpoints_w[i].mean(axis=0))
        ln.ref_keyframe_id[i] = int(kfs.min())
        ln.inverse_depth[i] = 1.0 / max(float(z), 1e-12)
    ln.ref_keyframe_id[~anchored] = -1
    ln.inverse_depth[~anchored] = np.nan


def upright_by_vanishing_points(tracks: Tracks, m: Map) -> bool:
    """Turn `m` (in place) so that the world vertical its keyframes' vertical vanishing directions agree
    on is +Z; False (the map keeps the first camera's orientation) when there is none."""
    poses = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    up = vertical_in_world(tracks, poses)
    if up is None:
        return False
    transform_map(m, rotation_to_z(up))
    return True


def upright_by_axes(m: Map) -> None:
    """Turn `m` (in place) so that its vertical principal axis is +Z (nothing when it has none)."""
    if len(m.axes) and m.axes.vertical_index >= 0:
        v = m.axes.directions[m.axes.vertical_index]
        transform_map(m, rotation_to_z(v if v[2] >= 0 else -v))
