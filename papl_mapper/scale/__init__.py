"""Metric scale of monocular maps: fiducial markers, camera height above the floor, known lengths.

Each source gives a `ScaleEstimate` (metres per map unit and its relative uncertainty); `choose`
keeps the best-conditioned one; `scale_map` applies it to a map, `rescale_run` to a finished run.
"""

from .apply import scale_map, scale_trajectory
from .config import ScaleConfig
from .estimate import ScaleEstimate, choose, units_note
from .floor import Floor, camera_height_scale, fit_floor, up_direction
from .length import line_length_scale, point_distance_scale
from .markers import MarkerSpec, detect_markers, keyframe_images, marker_scale, parse_marker_spec
from .sources import check_config, estimate_scale, scale_from_config

__all__ = [
    "Floor",
    "MarkerSpec",
    "ScaleConfig",
    "ScaleEstimate",
    "camera_height_scale",
    "check_config",
    "choose",
    "detect_markers",
    "estimate_scale",
    "fit_floor",
    "keyframe_images",
    "line_length_scale",
    "marker_scale",
    "parse_marker_spec",
    "point_distance_scale",
    "scale_from_config",
    "scale_map",
    "scale_trajectory",
    "units_note",
    "up_direction",
]
