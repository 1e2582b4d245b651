"""Keyframe trajectories: TUM (`timestamp tx ty tz qx qy qz qw`) and KITTI (3x4 row-major per line).

Both write the camera-to-world poses `T_wc` of every keyframe in time order, whatever `parts`
says, so evo and other SLAM tools can compare them (monocular maps: use Sim(3) alignment). The text
comes from `papl_mapper.trajectory_io`, the formats' one home, as the run's `keyframes.tum` does.
"""

from __future__ import annotations

import logging

import numpy as np

from papl_mapper.map import Map
from papl_mapper.trajectory_io import TUM_HEADER, format_kitti, format_tum

from .scene import ExportOptions, check_finite, header_text

log = logging.getLogger(__name__)


def _poses(m: Map, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(N,) timestamps and (N, 4, 4) T_wc in time order, checked finite."""
    kf = m.keyframes
    check_finite(kf.T_wc, kf.ids, "keyframes.T_wc")
    check_finite(kf.timestamp, kf.ids, "keyframes.timestamp")
    if len(kf) == 0:
        log.warning("the map has no keyframes: writing an empty %s trajectory", what)
    order = np.argsort(kf.timestamp, kind="stable")
    return kf.timestamp[order], kf.T_wc[order]


def export_tum(m: Map, options: ExportOptions | None = None) -> bytes:
    """TUM RGB-D trajectory: one `timestamp tx ty tz qx qy qz qw` line per keyframe (T_wc)."""
    t, T = _poses(m, "TUM")
    if len(t) == 0:
        return b""
    units = header_text(m.metadata.get("units", "arbitrary"), 40)
    return format_tum(t, T, f"{TUM_HEADER} (T_wc); units {units}").encode()


def export_kitti(m: Map, options: ExportOptions | None = None) -> bytes:
    """KITTI odometry poses: the 3x4 top of T_wc, row-major, one keyframe per line (no timestamps)."""
    _, T = _poses(m, "KITTI")
    return format_kitti(T).encode()


FORMATS = {
    ".tum": export_tum,
    ".tum.txt": export_tum,
    ".kitti": export_kitti,
    ".kitti.txt": export_kitti,
    ".txt": export_kitti,  # plain .txt is KITTI (as evo reads it); name a TUM file .tum or .tum.txt
}
