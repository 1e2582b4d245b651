"""Global bundle adjustment of a whole map as a pipeline stage: outlier observations culled, then
`backend.global_ba`, with the statistics summary.json reports."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from papl_mapper.backend import BAConfig, global_ba
from papl_mapper.map import Map
from papl_mapper.mapping.assemble import cull_observations

log = logging.getLogger(__name__)


def cull(
    m: Map, config: BAConfig, max_point_error_px: float, max_line_error_px: float, title: str
) -> dict[str, int]:
    """Observations reprojecting beyond the limits culled (in place), with the points and lines they
    leave with too few views (`config.min_views`; a line keeps one); the counts, logged under `title`."""
    culled = cull_observations(m, max_point_error_px, max_line_error_px, config.min_views, 1)
    log.info("%s: culled %s", title, ", ".join(f"{v} {k}" for k, v in culled.items() if v) or "nothing")
    return culled


def adjust(
    m: Map,
    config: BAConfig,
    max_point_error_px: float,
    max_line_error_px: float,
    title: str,
    progress: Callable[[int, int, str], None] | None = None,
) -> tuple[Map, dict[str, Any]]:
    """Observations reprojecting beyond the limits culled, then global BA (`progress(i, n, message)` per
    LM iteration); the adjusted map (metadata kept) and its statistics."""
    culled = cull(m, config, max_point_error_px, max_line_error_px, title)
    report = (lambda i, n, cost: progress(i, n, f"cost {cost:.6g}")) if progress is not None else None
    res = global_ba(m, config, progress=report)
    log.info(
        "%s: cost %.6g -> %.6g in %d iterations (%.2f s); rms %s px",
        title,
        res.initial_cost,
        res.final_cost,
        res.iterations,
        res.time_s,
        ", ".join(f"{k} {v:.3f}" for k, v in res.final_rms_px.items()),
    )
    if res.dropped:
        log.info(
            "%s: left out %s", title, ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in res.dropped.items())
        )
    res.map.metadata = dict(m.metadata)
    stats = {
        "initial_cost": res.initial_cost,
        "final_cost": res.final_cost,
        "iterations": res.iterations,
        "solves": res.n_solves,
        "converged": res.converged,
        "time_s": round(res.time_s, 3),
        "rms": {k: {"before": res.initial_rms_px.get(k), "after": v} for k, v in res.final_rms_px.items()},
        "culled_observations": sum(v for k, v in culled.items() if k.endswith("observations")),
        "problem": {
            "variables": res.n_variables,
            "observations": res.n_observations,
            "line_parameters": res.line_params,
            "culled_before": culled,
            "left_out": res.dropped,
        },
    }
    return res.map, stats
