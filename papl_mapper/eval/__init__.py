"""eval stage of papl-mapper: trajectory (ATE, RPE, scale), line-map and axis metrics against ground truth
(line recall also against the part of the ground truth the recording shows)."""

from .axes import AxisMatch, GtAxes, match_axes, read_axes
from .evaluate import (
    EvalConfig,
    EvalResult,
    GroundTruth,
    evaluate,
    load_ground_truth,
    resolve_gt_dir,
    resolve_result,
    trajectory_of_map,
    write_json,
)
from .lines import Segments, line_metrics, nearest_segment_distance, point_segment_distance, read_segments
from .trajectory import associate, associate_trajectories, rpe
from .visibility import Visibility, recording_camera, scene_occluders, segment_visibility

__all__ = [
    "AxisMatch",
    "EvalConfig",
    "EvalResult",
    "GroundTruth",
    "GtAxes",
    "Segments",
    "Visibility",
    "associate",
    "associate_trajectories",
    "evaluate",
    "line_metrics",
    "load_ground_truth",
    "match_axes",
    "nearest_segment_distance",
    "point_segment_distance",
    "read_axes",
    "read_segments",
    "recording_camera",
    "resolve_gt_dir",
    "resolve_result",
    "rpe",
    "scene_occluders",
    "segment_visibility",
    "trajectory_of_map",
    "write_json",
]
