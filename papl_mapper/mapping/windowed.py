"""Windowed bundle adjustment during keyframe registration: the newest keyframes and their points.

Registration calls the refiner every few keyframes; the older keyframes that share points with
the window hold still, so the gauge and scale stay where the map put them.
"""

from __future__ import annotations

import logging

import numpy as np

from papl_mapper.backend import BAConfig, local_ba
from papl_mapper.errors import GeometryError, OptimizationError
from papl_mapper.mapping.assemble import assemble_map, cull_observations
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.tracks import PointRows, Tracks

log = logging.getLogger(__name__)


class WindowedRefiner:
    """Registration's refine callback: adjusts the newest `window` keyframes and their points.

    Only the window's points and the keyframes that see them are assembled (the others would be
    left out of the local BA anyway), so a call costs the same early and late in a long recording.
    """

    def __init__(self, tracks: Tracks, ba: BAConfig, window: int, max_point_error_px: float):
        self.tracks, self.ba, self.window, self.max_point_error_px = tracks, ba, window, max_point_error_px
        self._rows = PointRows(tracks)
        self._seen = (0, 0)  # (id of the segment's revisit list, how many of them the rows follow)

    def __call__(self, reg: Registration) -> None:
        tracks = self.tracks
        done = self._seen[1] if self._seen[0] == id(reg.revisits) else 0
        for rv in reg.revisits[done:]:  # loops closed since the last call renamed tracks
            self._rows.rename(rv.fused)
        self._seen = (id(reg.revisits), len(reg.revisits))
        frames = sorted(reg.frames)
        # the two oldest keyframes stay fixed: with the shared points they hold the gauge and scale
        keyframes = np.array(frames[max(2, len(frames) - self.window) :])
        seen = np.unique(np.concatenate([tracks.points_in(int(f))[0] for f in keyframes]))
        pids = seen[reg.points_w.has(seen)].tolist()
        rows = self._rows.rows(np.array(pids, np.int64))
        rows = rows[np.isin(tracks.point_frame[rows], frames)]
        T_wc = {int(f): np.linalg.inv(reg.T_cw[int(f)]) for f in np.unique(tracks.point_frame[rows])}
        T_wc.update({int(f): np.linalg.inv(reg.T_cw[int(f)]) for f in keyframes})
        points = {t: reg.points_w[t] for t in pids}
        m = assemble_map(tracks, T_wc, points, LineEstimates.empty(), point_rows=rows)
        cull_observations(m, self.max_point_error_px, self.max_point_error_px, self.ba.min_views)
        try:
            res = local_ba(m, keyframes, self.ba)
        except (GeometryError, OptimizationError) as exc:
            log.debug("windowed BA skipped: %s", exc)
            return
        for k, T in zip(res.map.keyframes.ids, res.map.keyframes.T_wc, strict=True):
            reg.T_cw[int(k)] = np.linalg.inv(T)
        for p, x in zip(res.map.points.ids, res.map.points.xyz, strict=True):
            reg.points_w[int(p)] = x
