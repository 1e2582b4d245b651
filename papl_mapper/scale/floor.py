"""Scale from the camera height: the floor plane under the cameras, normal along the vertical axis.

The floor is the densest level of map points and horizontal-line endpoints below the cameras (walls
spread over every height, a floor or road piles up at one); its height is the median of the samples
within a band of that level. The scale is the known camera height over the median height of the
keyframes above it.
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
    """The floor plane {x : x . up = height} and the samples that support it."""

    up: np.ndarray  # (3,) unit vertical, pointing from the floor towards the cameras
    height: float  # along `up`, map units
    height_sigma: float  # standard uncertainty of `height`
    support: int  # samples within the band of the floor level
    band: float  # half-width of that band, map units


def up_direction(m: Map) -> np.ndarray:
    """The map's vertical axis as a unit vector pointing up (towards +Z, where cameras look level)."""
    if m.axes.vertical_index < 0 or len(m.axes) == 0:
        raise InputError("the map has no vertical axis, so no floor plane can be fitted")
    v = np.asarray(m.axes.directions[m.axes.vertical_index], np.float64)
    return v if v[2] >= 0 else -v


def floor_samples(m: Map, up: np.ndarray) -> np.ndarray:
    """(S,) heights along `up` of the map's points and of the endpoints of its horizontal lines."""
    heights = [m.points.xyz @ up]
    if len(m.lines) and len(m.axes):
        axis = m.lines.axis_of_line()
        horizontal = (axis >= 0) & (axis != m.axes.vertical_index)
        horizontal &= m.lines.state == LineState.ANCHORED
        heights.append((m.lines.endpoints_w[horizontal] @ up).ravel())
    return np.concatenate(heights)


def fit_floor(m: Map, min_support: int = 20, min_drop_fraction: float = 0.2) -> Floor:
    """The floor under the keyframes; InputError when nothing below the cameras piles up at one level.

    Samples count when they lie at least `min_drop_fraction` of the cameras' spread-free height scale
    below the lowest camera quartile; the level is the histogram mode of those heights.
    """
    if len(m.keyframes) < 2:
        raise InputError("the map has fewer than 2 keyframes: no camera height to measure")
    up = up_direction(m)
    cam_h = m.keyframes.T_wc[:, :3, 3] @ up
    h = floor_samples(m, up)
    if len(h) == 0:
        raise InputError("no floor found: the map has no points or horizontal lines")
    cam_low = float(np.percentile(cam_h, 25))
    depth = cam_low - h  # how far below the lower cameras each sample lies
    below = depth[depth > 0]
    if len(below) < min_support:
        raise InputError(
            f"no floor found: only {len(below)} map points lie below the cameras "
            f"(need {min_support}); map a recording that sees the floor, or give a marker or a known length"
        )
    # scale-free binning: the bin width is a fraction of how far the map reaches below the cameras
    reach = float(np.percentile(below, 95))
    lowest = below[below >= min_drop_fraction * reach]
    if len(lowest) < min_support:
        raise InputError(f"no floor found: only {len(lowest)} map points lie well below the cameras")
    width = reach / 40.0
    edges = np.arange(lowest.min(), lowest.max() + 2 * width, width)
    counts, edges = np.histogram(lowest, edges)
    counts = np.convolve(counts, [1, 2, 1], mode="same")  # a level split across two bins still wins
    k = int(np.argmax(counts))
    mode = 0.5 * (edges[k] + edges[k + 1])
    band = 1.5 * width
    near = lowest[np.abs(lowest - mode) <= band]
    # the floor must stand out of the background of wall points at every height
    background = len(lowest) * (2 * band) / max(float(lowest.max() - lowest.min()), 2 * band)
    if len(near) < min_support or len(near) < 3 * background:
        raise InputError(
            f"no floor found: no level below the cameras holds more map points than the walls "
            f"around it ({len(near)} at the best level); give a marker or a known length instead"
        )
    drop = float(np.median(near))
    mad = float(np.median(np.abs(near - drop))) * 1.4826
    return Floor(up, cam_low - drop, mad * math.sqrt(math.pi / 2 / len(near)), len(near), band)


def camera_height_scale(m: Map, camera_height_m: float) -> ScaleEstimate:
    """Scale from the median keyframe height above the fitted floor and the known height in metres."""
    if not (math.isfinite(camera_height_m) and camera_height_m > 0):
        raise InputError(f"--camera-height must be a positive number of metres, got {camera_height_m}")
    floor = fit_floor(m)
    above = m.keyframes.T_wc[:, :3, 3] @ floor.up - floor.height
    med = float(np.median(above))
    spread = float(np.median(np.abs(above - med))) * 1.4826
    n = len(above)
    rel = math.hypot(floor.height_sigma, spread * math.sqrt(math.pi / 2 / n)) / med
    return ScaleEstimate(
        camera_height_m / med,
        rel,
        "camera_height",
        f"camera height {camera_height_m:g} m above the floor",
        {
            "camera_height_m": camera_height_m,
            "median_height_units": med,
            "floor_support": floor.support,
            "keyframes": n,
        },
    )
