"""The culling schedule around each global BA: gross outliers before it, the limits applied after it."""

from __future__ import annotations

import numpy as np
from papl_mapper.pipelines import run
from papl_mapper.pipelines.config import RunConfig

from papl_mapper.geometry.se3 import project_points
from papl_mapper.mapping.assemble import assemble_map
from papl_mapper.mapping.lines import LineEstimates

from .test_mapping_incremental import make_tracks


def _map_with_outliers(gross_px: float, moderate_px: float, n: int = 10):
    """A points map at the true poses and points; n observations moved by `gross_px`, n by `moderate_px`
    (each on a different point seen by many keyframes, so no point loses its views)."""
    tracks, T_cw, pts = make_tracks(n_frames=30, noise_px=0.3, seed=3)
    T_wc = {f: np.linalg.inv(T) for f, T in enumerate(T_cw)}
    ids, counts = np.unique(tracks.point_track, return_counts=True)
    chosen = ids[counts >= 10][: 2 * n]
    rows = np.array([np.flatnonzero(tracks.point_track == t)[5] for t in chosen])
    tracks.point_uv[rows[:n], 0] += gross_px
    tracks.point_uv[rows[n:], 1] += moderate_px
    points = {int(t): pts[t] for t in ids}
    return assemble_map(tracks, T_wc, points, LineEstimates.empty()), n


def test_gross_outliers_go_before_ba_and_the_limits_apply_after_it():
    m, n = _map_with_outliers(gross_px=40.0, moderate_px=6.0)
    cfg = RunConfig()  # limits 4 px, pre-BA factor 3: 12 px before BA
    out, stats = run._ba(m, cfg, run._silent, "test")
    assert stats["problem"]["culled_before"]["point_observations"] == n
    assert stats["problem"]["culled_after"]["point_observations"] == n
    assert stats["culled_observations"] == 2 * n
    assert len(out.points.obs_ids) == len(m.points.obs_ids) - n  # m lost the gross ones in place
    # what is left agrees with the adjusted map within the limit
    kf = {int(k): i for i, k in enumerate(out.keyframes.ids)}
    T = out.keyframes.T_wc[[kf[int(k)] for k in out.points.obs_ids[:, 1]]]
    X = out.points.xyz[np.searchsorted(out.points.ids, out.points.obs_ids[:, 0])]

    uv, _ = project_points(out.camera.K, T, X)
    assert np.linalg.norm(uv - out.points.obs_uv, axis=1).max() <= cfg.max_point_error_px


def test_no_second_adjustment_when_nothing_is_over_the_limits():
    m, _ = _map_with_outliers(gross_px=0.0, moderate_px=0.0)
    _, stats = run._ba(m, RunConfig(), run._silent, "test")
    assert not any(stats["problem"]["culled_after"].values())
