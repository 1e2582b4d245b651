"""Scale from the camera height: the floor plane under the cameras, normal along the vertical axis.

The floor is the densest level of map points and horizontal-line endpoints below the cameras (walls
spread over every height, a floor or road piles up at one), measured around each keyframe so that a
sloping floor or road still counts. The scale is the known camera height over the median of the
keyframes' heights above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.map import LineState, Map

from .estimate import ScaleEstimate


@dataclass
class Floor:
    """The floor under the cameras: its normal and how far below the cameras it lies."""

    up: np.ndarray  # (3,) unit vertical, pointing from the floor towards the cameras
    drop: float  # typical height of the cameras above the floor, map units
    drop_sigma: float  # standard uncertainty of `drop`
    support: int  # samples at the floor level
    band: float  # half-width of the floor level, map units


def up_direction(m: Map) -> np.ndarray:
    """The map's vertical axis as a unit vector pointing up (towards +Z, where cameras look level)."""
    if m.axes.vertical_index < 0 or len(m.axes) == 0:
        raise InputError("the map has no vertical axis, so no floor plane can be fitted")
    v = np.asarray(m.axes.directions[m.axes.vertical_index], np.float64)
    return v if v[2] >= 0 else -v


def floor_samples_xyz(m: Map) -> np.ndarray:
    """(S, 3) the map's points and the endpoints of its anchored horizontal lines."""
    xyz = [m.points.xyz]
    if len(m.lines) and len(m.axes):
        axis = m.lines.axis_of_line()
        horizontal = (axis >= 0) & (axis != m.axes.vertical_index) & (m.lines.state == LineState.ANCHORED)
        xyz.append(m.lines.endpoints_w[horizontal].reshape(-1, 3))
    return np.concatenate(xyz)


#: keyframes the floor is measured around at most (evenly spread over the walk)
MAX_KEYFRAMES = 300


def _rows(m: Map) -> np.ndarray:
    n = len(m.keyframes)
    return np.unique(np.linspace(0, n - 1, min(n, MAX_KEYFRAMES)).round().astype(np.int64))


def _drops(m: Map, up: np.ndarray, radius: float | None) -> list[np.ndarray]:
    """Per keyframe of `_rows`, how far below it the samples lie (positive only), within `radius`
    horizontally."""
    xyz = floor_samples_xyz(m)
    h = xyz @ up
    flat = xyz - np.outer(h, up)
    out = []
    for c in m.keyframes.T_wc[_rows(m), :3, 3]:
        ch = float(c @ up)
        d = ch - h
        keep = d > 0
        if radius is not None:
            keep &= np.linalg.norm(flat - (c - ch * up), axis=1) <= radius
        out.append(d[keep])
    return out


def _level(values: np.ndarray, width: float) -> tuple[float, np.ndarray]:
    """The densest level of `values` and the values within 1.5 `width` of it: the peak of a smoothed
    histogram of bin `width`, then the median of the values around it (twice, recentred), which
    stays in the middle of a floor that is a little tilted or spread over two nearby levels."""
    edges = np.arange(values.min(), values.max() + 2 * width, width)
    counts, edges = np.histogram(values, edges)
    k = int(np.argmax(np.convolve(counts, [1, 2, 1], mode="same")))
    level = 0.5 * (edges[k] + edges[k + 1])
    near = values
    for _ in range(2):
        near = values[np.abs(values - level) <= 1.5 * width]
        if not len(near):
            break
        level = float(np.median(near))
    return float(level), near


def fit_floor(m: Map, min_support: int = 20) -> Floor:
    """The floor under the keyframes; InputError when nothing below the cameras piles up at one level.

    The reach is the 95th percentile of how far the samples lie below the cameras. Each keyframe
    contributes the samples below it within twice the reach horizontally (so that a sloping floor or
    road still piles up at one drop); the level is the densest of the pooled drops between 0.6 and
    1.5 reaches (bins a fortieth of the reach), and must hold three times the walls' density.
    """
    if len(m.keyframes) < 2:
        raise InputError("the map has fewer than 2 keyframes: no camera height to measure")
    up = up_direction(m)
    if not len(floor_samples_xyz(m)):
        raise InputError("no floor found: the map has no points or horizontal lines")
    every = np.concatenate(_drops(m, up, None))
    if len(every) < min_support:
        raise InputError(
            f"no floor found: only {len(every)} map points lie below the cameras (need {min_support}); "
            "map a recording that sees the floor, or give a marker or a known length"
        )
    reach = float(np.percentile(every, 95))
    pooled = np.concatenate(_drops(m, up, 2 * reach))
    # the floor is the lowest thing below the cameras, near the bottom of what the map holds there;
    # walls at eye level are often denser, so only the lower part of the reach is searched
    pooled = pooled[(pooled >= 0.6 * reach) & (pooled <= 1.5 * reach)]
    if len(pooled) < min_support:
        raise InputError(f"no floor found: only {len(pooled)} map points lie well below the cameras")
    width = reach / 40
    drop, near = _level(pooled, width)
    # the floor must stand out of the background of wall points spread over every height
    counts, _ = np.histogram(pooled, np.arange(0.6 * reach, 1.5 * reach + width, width))
    background = 3 * float(np.median(counts))  # what three bins of walls alone would hold
    if len(near) < min_support or len(near) < 3 * background:
        raise InputError(
            f"no floor found: no level below the cameras holds more map points than the walls "
            f"around it ({len(near)} at the best level); give a marker or a known length instead"
        )
    mad = float(np.median(np.abs(near - drop))) * 1.4826
    return Floor(up, drop, mad * math.sqrt(math.pi / 2 / len(near)), len(near), width)


def local_heights(m: Map, floor: Floor, radius: float = 2.0, min_support: int = 10) -> np.ndarray:
    """(N,) each keyframe's height above the floor around it (NaN where too little floor is seen, and
    for keyframes between the MAX_KEYFRAMES measured): the densest level of the samples within
    `radius` camera heights horizontally and between half and one and a half camera heights below."""
    out = np.full(len(m.keyframes), np.nan)
    for k, d in zip(_rows(m), _drops(m, floor.up, radius * floor.drop), strict=True):
        d = d[(d >= 0.5 * floor.drop) & (d <= 1.5 * floor.drop)]
        if len(d) < min_support:
            continue
        level, near = _level(d, floor.band)
        if len(near) >= min_support // 2:
            out[k] = level
    return out


def keyframe_heights(m: Map, floor: Floor) -> tuple[np.ndarray, str]:
    """(K,) keyframe heights above the floor and how they were measured.

    A level floor (the floor level under the keyframes varies less than its band) is one plane for
    the whole walk, fitted to every sample at once; a sloping floor or road is measured around each
    keyframe, as close as the samples allow.
    """
    up = floor.up
    cam_h = m.keyframes.T_wc[:, :3, 3] @ up
    local = local_heights(m, floor)
    ok = np.isfinite(local)
    if ok.sum() >= 3:
        under = cam_h[ok] - local[ok]  # the floor level under each keyframe
        if 1.4826 * float(np.median(np.abs(under - np.median(under)))) > floor.band:
            close = local_heights(m, floor, radius=1.0)
            use = close if np.isfinite(close).sum() >= 0.5 * ok.sum() else local
            return use[np.isfinite(use)], "around each keyframe (the floor slopes)"
    h = floor_samples_xyz(m) @ up
    ch = float(np.median(cam_h))
    h = h[(h <= ch - 0.5 * floor.drop) & (h >= ch - 1.5 * floor.drop)]
    level, _ = _level(h, floor.band)
    return cam_h - level, "one level floor under the walk"


def camera_height_scale(m: Map, camera_height_m: float) -> ScaleEstimate:
    """Scale from the median keyframe height above the floor around it and the known height in metres."""
    if not (math.isfinite(camera_height_m) and camera_height_m > 0):
        raise InputError(f"--camera-height must be a positive number of metres, got {camera_height_m}")
    floor = fit_floor(m)
    above, how = keyframe_heights(m, floor)
    med = float(np.median(above))
    spread = float(np.median(np.abs(above - med))) * 1.4826
    # the spread of the keyframes' heights, the floor level's own scatter and its resolution
    rel = math.hypot(floor.drop_sigma, spread * math.sqrt(math.pi / 2 / len(above)), 0.1 * floor.band) / med
    return ScaleEstimate(
        camera_height_m / med,
        rel,
        "camera_height",
        f"camera height {camera_height_m:g} m above the floor",
        {
            "camera_height_m": camera_height_m,
            "median_height_units": med,
            "floor_support": floor.support,
            "keyframes": int(len(above)),
            "floor": how,
        },
    )
