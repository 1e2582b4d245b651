"""Scale from a known length: one map line of known length, or two map points a known distance apart.

The uncertainty is the position uncertainty of the two ends, one pixel at the distance of the
closest keyframe that saw them, over the measured length.
"""

from __future__ import annotations

import math

import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.map import Map

from .estimate import ScaleEstimate

#: assumed standard deviation of an endpoint's image position, pixels
ENDPOINT_SIGMA_PX = 1.0


def _check_metres(metres: float, what: str) -> None:
    if not (math.isfinite(metres) and metres > 0):
        raise InputError(f"{what}: the length must be a positive number of metres, got {metres:g}")


def _end_sigma(m: Map, xyz: np.ndarray, keyframe_ids: np.ndarray) -> float:
    """One pixel at the distance of the closest keyframe among `keyframe_ids`, in map units."""
    rows = np.flatnonzero(np.isin(m.keyframes.ids, keyframe_ids))
    if not len(rows):
        return float("inf")
    d = np.linalg.norm(m.keyframes.T_wc[rows, :3, 3] - xyz, axis=1).min()
    return float(d * ENDPOINT_SIGMA_PX / m.camera.fx)


def line_length_scale(m: Map, line_id: int, metres: float) -> ScaleEstimate:
    """Scale making line `line_id` `metres` long."""
    what = f"--length {line_id}={metres:g}"
    _check_metres(metres, what)
    hit = np.flatnonzero(m.lines.ids == line_id)
    if not len(hit):
        ids = m.lines.ids
        span = f"{ids.min()}..{ids.max()}" if len(ids) else "none"
        raise InputError(f"{what}: the map has no line {line_id} (its {len(ids)} line ids span {span})")
    ends = m.lines.endpoints_w[hit[0]]
    length = float(np.linalg.norm(ends[1] - ends[0]))
    if not length > 0:
        raise InputError(f"{what}: line {line_id} has zero length")
    seen = m.lines.obs_ids[m.lines.obs_ids[:, 0] == line_id, 1]
    sig = math.hypot(_end_sigma(m, ends[0], seen), _end_sigma(m, ends[1], seen))
    return ScaleEstimate(
        metres / length,
        sig / length,
        "length",
        f"line {line_id} of known length {metres:g} m",
        {"line_id": int(line_id), "length_m": metres, "length_units": length},
    )


def point_distance_scale(m: Map, point_a: int, point_b: int, metres: float) -> ScaleEstimate:
    """Scale putting points `point_a` and `point_b` `metres` apart."""
    what = f"--points {point_a},{point_b}={metres:g}"
    _check_metres(metres, what)
    if point_a == point_b:
        raise InputError(f"{what}: give two different point ids")
    xyz = []
    for pid in (point_a, point_b):
        hit = np.flatnonzero(m.points.ids == pid)
        if not len(hit):
            raise InputError(f"{what}: the map has no point {pid} ({len(m.points)} points)")
        xyz.append(m.points.xyz[hit[0]])
    length = float(np.linalg.norm(xyz[1] - xyz[0]))
    if not length > 0:
        raise InputError(f"{what}: points {point_a} and {point_b} coincide")
    sig = math.hypot(
        *(
            _end_sigma(m, x, m.points.obs_ids[m.points.obs_ids[:, 0] == pid, 1])
            for x, pid in zip(xyz, (point_a, point_b), strict=True)
        )
    )
    return ScaleEstimate(
        metres / length,
        sig / length,
        "points",
        f"points {point_a} and {point_b} {metres:g} m apart",
        {"point_ids": [int(point_a), int(point_b)], "length_m": metres, "length_units": length},
    )
