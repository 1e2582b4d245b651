"""VTK geometry of the viewer's 3D view: segments, points, trajectory and keyframe frusta as PolyData.

Built straight from numpy arrays (one points array and one cell array each), so a million segments
become one PolyData without a Python loop. The frusta are the exporters' own edges.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from papl_mapper.map import Map


def segments_polydata(endpoints_w: np.ndarray, rgb: np.ndarray | None = None) -> Any:
    """One PolyData of (k, 2, 3) segments, with a per-segment 'rgb' uint8 colour when given."""
    import pyvista as pv

    k = len(endpoints_w)
    cells = np.empty((k, 3), np.int64)
    cells[:, 0] = 2
    cells[:, 1] = np.arange(0, 2 * k, 2)
    cells[:, 2] = cells[:, 1] + 1
    poly = pv.PolyData(
        np.ascontiguousarray(endpoints_w.reshape(-1, 3), dtype=np.float32), lines=cells.ravel()
    )
    if rgb is not None:
        poly.cell_data["rgb"] = np.ascontiguousarray(rgb, dtype=np.uint8)
    return poly


def points_polydata(xyz: np.ndarray, rgb: np.ndarray) -> Any:
    """Vertices of (n, 3) points with an 'rgb' uint8 colour each."""
    import pyvista as pv

    poly = pv.PolyData(np.ascontiguousarray(xyz, dtype=np.float32))
    poly.point_data["rgb"] = np.ascontiguousarray(rgb, dtype=np.uint8)
    return poly


def trajectory_polydata(m: Map) -> Any | None:
    """The keyframe centres as one polyline, or None with fewer than two keyframes."""
    import pyvista as pv

    c = m.keyframes.T_wc[:, :3, 3]
    return pv.lines_from_points(c) if len(c) >= 2 else None


def frusta_segments(m: Map, depth: float, rows: np.ndarray | None = None) -> np.ndarray:
    """(8k, 2, 3) frustum edges of the keyframes at `rows` (all when None)."""

    from papl_mapper.exporters.scene import frustum_segments  # after the first frame: it imports scipy

    if len(m.keyframes) == 0:
        return np.zeros((0, 2, 3))
    seg = frustum_segments(m, depth).reshape(len(m.keyframes), -1, 2, 3)
    if rows is not None:
        seg = seg[np.asarray(rows, np.int64)]
    return seg.reshape(-1, 2, 3)
