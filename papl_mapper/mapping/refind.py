"""Map points found again during registration: a new keyframe's young tracks joined to lost map points.

KLT ends a track when the corner is occluded, blurred or briefly out of view; the corner comes back as
a new track, and registration would triangulate it as a second point from the short baseline it has
so far, where its depth is least certain. Once a keyframe is posed, each map point its tracks do not
see is projected with that pose; an unmapped track whose corner lies within `search_radius_px` takes
the point's track id (in `tracks.point_track`, in place, as loop closures and track completion do)
when every registered view of it lies within `max_error_px` of the point's projection and its ORB
descriptor agrees with one of the point's. This is ORB-SLAM's search by projection; track completion
repeats it over every keyframe after each global BA.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from papl_mapper.frontend.descriptors import hamming_pairs
from papl_mapper.geometry.se3 import invert, project_points
from papl_mapper.tracks import PointRows, Tracks


@dataclass
class RefindConfig:
    """Thresholds of finding map points again at a new keyframe."""

    enabled: bool = True
    """Join a keyframe's unmapped tracks to the map points they continue."""
    search_radius_px: float = 3.0
    """A corner joins a map point only this close to where the keyframe's pose projects the point."""
    max_error_px: float = 3.0
    """Every registered view of the joining track lies this close to the point's projection (the poses
    are not yet adjusted)."""
    max_hamming: int = 48
    """Largest ORB distance (of 256 bits) between the joining corner's and the point's descriptors."""
    min_views_without_descriptor: int = 3
    """A joining track without a descriptor needs this many registered views, all explained by the point."""


class Refinder:
    """Search by projection over one registration; `refind` once per new keyframe."""

    def __init__(self, tracks: Tracks, config: RefindConfig) -> None:
        self.tracks = tracks
        self.config = config
        self.desc_of_row = np.full(len(tracks.point_track), -1, np.int64)
        self.desc_of_row[tracks.point_desc_row] = np.arange(len(tracks.point_desc_row))

    def refind(
        self,
        rows: PointRows,
        frame: int,
        T_cw: np.ndarray,
        points_w: dict[int, np.ndarray],
        poses: dict[int, np.ndarray],
    ) -> int:
        """Rename the unmapped tracks of `frame` that continue a map point; returns how many joined.

        `poses`: T_cw of the registered frames (keyframes and the frames between them), `frame`'s too.
        `rows` is told of each rename.
        """
        cfg, tracks = self.config, self.tracks
        ids, uv_f = tracks.points_in(frame)
        if len(ids) == 0 or not points_w:
            return 0
        young = np.array([t not in points_w for t in ids.tolist()])
        pid = np.fromiter(points_w, np.int64, len(points_w))
        pid = pid[~np.isin(pid, ids)]
        if not young.any() or len(pid) == 0:
            return 0
        cam = tracks.camera
        X = np.stack([points_w[int(p)] for p in pid])
        uv, z = project_points(cam.K, invert(T_cw), X)
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        if not vis.any():
            return 0
        pid, X, uv = pid[vis], X[vis], uv[vis]
        yid = ids[young]
        dist, j = cKDTree(uv_f[young]).query(uv, distance_upper_bound=cfg.search_radius_px)
        hit = np.flatnonzero(np.isfinite(dist))
        joined = 0
        taken: set[int] = set()
        for i in hit[np.argsort(dist[hit], kind="stable")].tolist():
            t = int(yid[j[i]])
            if t in taken:
                continue
            p = int(pid[i])
            if self._agrees(rows, p, t, X[i], poses):
                tracks.point_track[rows.rows(np.array([t]))] = p
                rows.rename(t, p)
                taken.add(t)
                joined += 1
        return joined

    def _agrees(self, rows: PointRows, p: int, t: int, X: np.ndarray, poses: dict[int, np.ndarray]) -> bool:
        """Whether track t can be point p's: never in a frame with it, every registered view within
        max_error_px of X's projection, and their descriptors close (or enough views without one)."""
        cfg, tracks = self.config, self.tracks
        rt, rp = rows.rows(np.array([t])), rows.rows(np.array([p]))
        if np.intersect1d(tracks.point_frame[rt], tracks.point_frame[rp]).size:
            return False
        posed = np.array([int(f) in poses for f in tracks.point_frame[rt]], bool)
        rt_posed = rt[posed]
        T_wc = invert(np.stack([poses[int(f)] for f in tracks.point_frame[rt_posed]]))
        uv, z = project_points(tracks.camera.K, T_wc, X)
        if (z <= 0).any() or np.linalg.norm(uv - tracks.point_uv[rt_posed], axis=1).max() > cfg.max_error_px:
            return False
        dt, dp = self.desc_of_row[rt], self.desc_of_row[rp]
        dt, dp = dt[dt >= 0], dp[dp >= 0]
        if len(dt) == 0 or len(dp) == 0:
            return len(rt_posed) >= cfg.min_views_without_descriptor
        ia, ib = np.repeat(dt, len(dp)), np.tile(dp, len(dt))
        return int(hamming_pairs(tracks.point_desc, tracks.point_desc, ia, ib).min()) <= cfg.max_hamming
