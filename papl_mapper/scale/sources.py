"""The scale of a map from the sources a user gives: markers, camera height, known lengths.

`estimate_scale` gathers one estimate per source and keeps the best-conditioned one (refusing
conflicts); `scale_from_config` is the one call `papl-map run` makes after mapping.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable

from papl_mapper.errors import InputError
from papl_mapper.map import Map
from papl_mapper.trajectory_io import Trajectory

from .apply import scale_map, scale_trajectory
from .config import ScaleConfig
from .estimate import ScaleEstimate, choose
from .floor import camera_height_scale
from .markers import detect_markers, keyframe_images, marker_scale, parse_marker_spec

log = logging.getLogger(__name__)


def check_config(cfg: ScaleConfig) -> None:
    """Refuse a bad marker spec or camera height before any work is done."""
    for text in cfg.markers:
        parse_marker_spec(text)
    if cfg.camera_height < 0:
        raise InputError(f"--camera-height must be a positive number of metres, got {cfg.camera_height:g}")


def estimate_scale(
    m: Map,
    cfg: ScaleConfig,
    frames: Callable[[], Iterable] | None = None,
    extra: list[ScaleEstimate] = (),
) -> ScaleEstimate | None:
    """The chosen estimate over every configured source plus `extra`, or None when there are none.

    `frames` returns the recording's frames (objects with .index and .image); it is called only when
    markers are configured.
    """
    check_config(cfg)
    estimates = list(extra)
    if cfg.markers:
        if frames is None:
            raise InputError("--marker needs the recording: give it with --recording")
        specs = [parse_marker_spec(t) for t in cfg.markers]
        found = detect_markers(keyframe_images(frames(), m), specs)
        estimates += [marker_scale(m, s, found[s], cfg.max_view_angle_deg) for s in specs]
    if cfg.camera_height > 0:
        estimates.append(camera_height_scale(m, cfg.camera_height))
    if not estimates:
        return None
    for e in estimates:
        log.debug("scale from %s: %.6g m/unit (±%.2g%%)", e.description, e.scale, 100 * e.rel_sigma)
    return choose(estimates, cfg.max_disagreement_sigma, cfg.min_disagreement)


def scale_from_config(
    m: Map, traj: Trajectory, cfg: ScaleConfig, frames: Callable[[], Iterable] | None = None
) -> tuple[Map, Trajectory]:
    """`m` and its frame trajectory in metres when `cfg` names a scale source, else both as they are.

    Applied after the trajectory is found, so the mapping itself runs in its own units either way.
    """
    if not cfg.enabled:
        return m, traj
    try:
        est = estimate_scale(m, cfg, frames)
    except InputError as exc:
        raise InputError(
            f"{exc} (no outputs were written; the mapping is checkpointed: rerun with --resume and "
            "another scale source or none, then `papl-map scale` can add one)"
        ) from exc
    log.info("map scaled to metres by %s: %.6g m per unit", est.description, est.scale)
    return scale_map(m, est), scale_trajectory(traj, est.scale)
