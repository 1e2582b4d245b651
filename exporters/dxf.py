"""DXF (R2010, via ezdxf): LINE entities on one layer per axis plus UNANCHORED, coloured by layer.

Layers carry the palette colour as true colour and the nearest ACI index (for old readers);
entities stay BYLAYER, since some CAD tools lose per-entity colours. ezdxf builds the document
(header, tables, layers, the trajectory as a 3D polyline); the many LINE and POINT entities are
formatted in bulk with handles reserved from ezdxf's handle seed, so a million lines take
seconds instead of a Python object each. `ezdxf.audit` accepts the result (tests check it).
"""

from __future__ import annotations

import io

import numpy as np

from papl_mapper.errors import BackendUnavailableError
from papl_mapper.map import Map

from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, prepare
from .text import format_rows

POINT_LAYER_RGB = (90, 90, 90)
_LINE = (
    "  0\nLINE\n  5\n%X\n330\n{owner}\n100\nAcDbEntity\n  8\n{layer}\n100\nAcDbLine\n"
    " 10\n%.10g\n 20\n%.10g\n 30\n%.10g\n 11\n%.10g\n 21\n%.10g\n 31\n%.10g\n"
)
_POINT = (
    "  0\nPOINT\n  5\n%X\n330\n{owner}\n100\nAcDbEntity\n  8\n{layer}\n100\nAcDbPoint\n"
    " 10\n%.10g\n 20\n%.10g\n 30\n%.10g\n"
)


def layer_name(key: str) -> str:
    """DXF layer name of a segment group key ('horizontal_1' -> 'HORIZONTAL_1')."""
    return key.upper()


def nearest_aci(rgb: tuple[int, int, int]) -> int:
    """The AutoCAD Color Index (1..255) closest to an RGB colour, for readers without true colour."""
    from ezdxf.colors import DXF_DEFAULT_COLORS

    table = np.array([[(c >> 16) & 255, (c >> 8) & 255, c & 255] for c in DXF_DEFAULT_COLORS[1:256]])
    return int(np.argmin(((table - np.asarray(rgb)) ** 2).sum(axis=1))) + 1


def scene_to_dxf(scene: ExportScene) -> bytes:
    try:
        import ezdxf
        from ezdxf import units
        from ezdxf.colors import rgb2int
    except ImportError as exc:
        raise BackendUnavailableError(f"DXF export needs ezdxf ({exc}); pip install ezdxf") from exc
    doc = ezdxf.new("R2010", setup=False)
    doc.units = units.M if scene.meters_per_unit == 1.0 else units.CM if scene.meters_per_unit == 0.01 else (
        units.MM if scene.meters_per_unit == 0.001 else 0
    )  # fmt: skip
    doc.header.custom_vars.append("PAPL_UNITS", scene.units)
    doc.header.custom_vars.append("PAPL_UP_AXIS", "+Z")
    for a in scene.axis_info:
        d = a["direction"]
        doc.header.custom_vars.append(
            f"PAPL_AXIS_{a['index']}", f"{a['name']} {d[0]:.9g} {d[1]:.9g} {d[2]:.9g}"
        )
    msp = doc.modelspace()
    groups = list(scene.line_groups) + ([scene.frusta] if scene.frusta is not None else [])
    layers = [(layer_name(g.key), g.rgb) for g in groups]
    if len(scene.trajectory_w):
        layers.append(("TRAJECTORY", TRAJECTORY_RGB))
    if len(scene.points_xyz):
        layers.append(("POINTS", POINT_LAYER_RGB))
    for name, rgb in layers:
        layer = doc.layers.add(name, color=nearest_aci(rgb))
        layer.dxf.true_color = rgb2int(rgb)
    if len(scene.trajectory_w) >= 2:
        msp.add_polyline3d(scene.trajectory_w.tolist(), dxfattribs={"layer": "TRAJECTORY"})
    elif len(scene.trajectory_w) == 1:
        msp.add_point(scene.trajectory_w[0].tolist(), dxfattribs={"layer": "TRAJECTORY"})
    n_entities = sum(len(g.ids) for g in groups) + len(scene.points_xyz)
    handles = doc.entitydb.handles
    first = int(str(handles), 16)
    handles.reset(f"{first + n_entities:X}")  # reserve [first, first + n) for the bulk entities below
    owner = msp.block_record_handle
    bulk, h = [], first
    for g in groups:
        n = len(g.ids)
        if n:
            row = _LINE.format(owner=owner, layer=layer_name(g.key))
            bulk.append(format_rows(row, np.arange(h, h + n), g.segments_w.reshape(n, 6)))
            h += n
    if len(scene.points_xyz):
        n = len(scene.points_xyz)
        bulk.append(
            format_rows(_POINT.format(owner=owner, layer="POINTS"), np.arange(h, h + n), scene.points_xyz)
        )
        h += n
    stream = io.StringIO()
    doc.write(stream)
    text = stream.getvalue().encode("utf-8")
    start = text.index(b"\n  2\nENTITIES\n")
    end = text.index(b"  0\nENDSEC\n", start)
    return text[:end] + b"".join(bulk) + text[end:]


def export_dxf(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map's lines (one layer per axis), points and trajectory as an R2010 DXF drawing."""
    return scene_to_dxf(prepare(m, options or ExportOptions()))


FORMATS = {".dxf": export_dxf}
