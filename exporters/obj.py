"""Wavefront OBJ: `v x y z r g b` vertices and `l` lines grouped per axis (`o`/`g`), for CloudCompare.

Each group (axis, unanchored, frusta) is an object with its own vertices and `l i j` segments;
the trajectory is one `l` polyline; points are vertices of a `points` object. Vertex colours use
the common `v x y z r g b` extension (0..1). Coordinates are the map's +Z-up world, unchanged.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.map import Map

from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, prepare
from .text import format_rows

_V = "v %.9g %.9g %.9g %.4g %.4g %.4g\n"


def _v_constant(rgb: tuple[int, int, int]) -> str:
    """A vertex row format with the group's constant colour written in (half the numbers to format)."""
    r, g, b = (f"{c / 255.0:.4g}" for c in rgb)
    return f"v %.9g %.9g %.9g {r} {g} {b}\n"


def scene_to_obj(scene: ExportScene) -> bytes:
    out = [f"# papl-mapper map; units {scene.units}; up +Z\n# scale {scene.scale_note}\n".encode()]
    for a in scene.axis_info:
        d = a["direction"]
        out.append(f"# axis {a['index']} {a['name']} direction {d[0]:.9g} {d[1]:.9g} {d[2]:.9g}\n".encode())
    base = 1  # OBJ indices start at 1
    for g in scene.segment_groups():
        if g.key == "trajectory":
            continue
        n = len(g.ids)
        out.append(f"o {g.key}\ng {g.key}\n".encode())
        out.append(format_rows(_v_constant(g.rgb), g.segments_w.reshape(-1, 3)))
        first = base + 2 * np.arange(n, dtype=np.int64)
        out.append(format_rows("l %d %d\n", first, first + 1))
        base += 2 * n
    n = len(scene.trajectory_w)
    if n >= 2:
        out.append(
            b"o trajectory\ng trajectory\n" + format_rows(_v_constant(TRAJECTORY_RGB), scene.trajectory_w)
        )
        out.append(("l " + " ".join(map(str, range(base, base + n))) + "\n").encode())
        base += n
    if len(scene.points_xyz):
        out.append(b"o points\ng points\n" + format_rows(_V, scene.points_xyz, scene.points_rgb / 255.0))
    return b"".join(out)


def export_obj(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as an OBJ file of coloured vertices and line elements, one group per axis."""
    return scene_to_obj(prepare(m, options or ExportOptions()))


FORMATS = {".obj": export_obj}
