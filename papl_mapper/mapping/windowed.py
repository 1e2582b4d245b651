"""Windowed bundle adjustment during keyframe registration: the newest keyframes and their points.

Registration calls the refiner every few keyframes; the older keyframes that share points with
the window hold still, so the gauge and scale stay where the map put them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from papl_mapper.backend import BAConfig, local_ba
from papl_mapper.errors import GeometryError, OptimizationError
from papl_mapper.mapping.assemble import assemble_map, cull_observations
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.tracks import PointRows, Tracks

log = logging.getLogger(__name__)


def windowed_refiner(
    tracks: Tracks, ba: BAConfig, window: int, max_point_error_px: float
) -> Callable[[Registration], None]:
    """A callback that adjusts the newest `window` keyframes of a Registration and their points.

    Only the window's points and the keyframes that see them are assembled (the others would be
    left out of the local BA anyway), so a call costs the same early and late in a long recording.
    """
    index: list = [-1, None]  # revisits seen when the rows were grouped, and the grouping

    def refine(reg: Registration) -> None:
        if index[0] != len(reg.revisits):  # a closed loop renamed tracks
            index[:] = [len(reg.revisits), PointRows(tracks)]
        frames = sorted(reg.frames)
        # the two oldest keyframes stay fixed: with the shared points they hold the gauge and scale
        keyframes = np.array(frames[max(2, len(frames) - window) :])
        seen = np.unique(np.concatenate([tracks.points_in(int(f))[0] for f in keyframes]))
        pids = [int(t) for t in seen if int(t) in reg.points_w]
        rows = index[1].rows(np.array(pids, np.int64))
        rows = rows[np.isin(tracks.point_frame[rows], frames)]
        T_wc = {int(f): np.linalg.inv(reg.T_cw[int(f)]) for f in np.unique(tracks.point_frame[rows])}
        T_wc.update({int(f): np.linalg.inv(reg.T_cw[int(f)]) for f in keyframes})
        m = assemble_map(
            tracks, T_wc, {t: reg.points_w[t] for t in pids}, LineEstimates.empty(), point_rows=rows
        )
        cull_observations(m, max_point_error_px, max_point_error_px, ba.min_views)
        try:
            res = local_ba(m, keyframes, ba)
        except (GeometryError, OptimizationError) as exc:
            log.debug("windowed BA skipped: %s", exc)
            return
        for k, T in zip(res.map.keyframes.ids, res.map.keyframes.T_wc, strict=True):
            reg.T_cw[int(k)] = np.linalg.inv(T)
        for p, x in zip(res.map.points.ids, res.map.points.xyz, strict=True):
            reg.points_w[int(p)] = x

    return refine
