"""Frontend stage: a recording -> `Tracks` (points, segments, keyframes, vanishing directions).

`open_recording` decodes videos and image folders, `camera_for_recording` gives intrinsics from a
file or a guess, and `process` turns both into undistorted observations with track ids.
"""

from papl_mapper.frontend.camera import (
    CameraSource,
    Undistorter,
    camera_for_recording,
    fit_camera,
    guess_camera,
    read_camera_file,
    scale_camera,
)
from papl_mapper.frontend.keyframes import KeyframeConfig
from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.lines import LineConfig, match_keyframe_lines
from papl_mapper.frontend.points import PointConfig
from papl_mapper.frontend.process import PRESETS, FrontendConfig, FrontendStats, frontend_preset, process
from papl_mapper.frontend.video import Frame, Recording, open_recording

__all__ = [
    "CameraSource",
    "FlowConfig",
    "Frame",
    "FrontendConfig",
    "FrontendStats",
    "PRESETS",
    "KeyframeConfig",
    "LineConfig",
    "PointConfig",
    "Recording",
    "Undistorter",
    "camera_for_recording",
    "fit_camera",
    "frontend_preset",
    "guess_camera",
    "match_keyframe_lines",
    "open_recording",
    "process",
    "read_camera_file",
    "scale_camera",
]
