"""DXF (R2010, via ezdxf): LINE entities on one layer per axis plus UNANCHORED, coloured by layer.

The drawing is in the map's units ($INSUNITS metres for a scaled map, unitless otherwise) with its
extents set, so CAD tools open on it. Stray geometry (lines seen in few keyframes, anything far
outside the structure) is left out unless `keep_stray` (then on an off STRAY layer); points sit on
their own POINTS layer, off by default.

Layers carry the palette colour as true colour and the nearest ACI index (for old readers);
entities stay BYLAYER, since some CAD tools lose per-entity colours. ezdxf builds the document
(header, tables, layers, the trajectory as a 3D polyline); the many LINE and POINT entities are
formatted in bulk with handles reserved from ezdxf's handle seed, so a million lines take
seconds instead of a Python object each. `ezdxf.audit` accepts the result (tests check it).
"""

from __future__ import annotations

import io

import numpy as np

from papl_mapper.extras import require
from papl_mapper.map import Map

from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, cad_split, prepare
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


def new_document(scene: ExportScene):
    """An R2010 ezdxf document with the scene's units ($INSUNITS, $MEASUREMENT) and papl header variables."""
    ezdxf = require("ezdxf", "DXF export")
    from ezdxf import units

    doc = ezdxf.new("R2010", setup=False)
    mpu = scene.meters_per_unit
    doc.units = {1.0: units.M, 0.01: units.CM, 0.001: units.MM}.get(mpu, 0)  # 0: unitless
    doc.header["$MEASUREMENT"] = 1  # metric (0 would say imperial; an unscaled map says so in $INSUNITS)
    doc.header["$LUNITS"] = 2  # decimal
    doc.header.custom_vars.append("PAPL_UNITS", scene.units)
    doc.header.custom_vars.append("PAPL_SCALE", scene.scale_note)
    doc.header.custom_vars.append("PAPL_UP_AXIS", "+Z")
    for a in scene.axis_info:
        d = a["direction"]
        doc.header.custom_vars.append(
            f"PAPL_AXIS_{a['index']}", f"{a['name']} {d[0]:.9g} {d[1]:.9g} {d[2]:.9g}"
        )
    return doc


def add_layer(doc, name: str, rgb: tuple[int, int, int], on: bool = True) -> None:
    """A layer with the palette colour as true colour and nearest ACI; `on=False` hides it."""
    from ezdxf.colors import rgb2int

    layer = doc.layers.add(name, color=nearest_aci(rgb))
    layer.dxf.true_color = rgb2int(rgb)
    if not on:
        layer.off()
        layer.freeze()  # LibreCAD prints layers that are only off


def set_extents(doc, xyz: np.ndarray) -> None:
    """Extents, limits and the opening view from every position drawn, so CAD tools open on the drawing.

    ezdxf copies the modelspace layout's extents and limits into $EXTMIN/$EXTMAX/$LIMMIN/$LIMMAX.
    """
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    lo, hi = (xyz.min(0), xyz.max(0)) if len(xyz) else (np.zeros(3), np.zeros(3))
    msp = doc.modelspace()
    msp.dxf.extmin = tuple(float(v) for v in lo)
    msp.dxf.extmax = tuple(float(v) for v in hi)
    msp.dxf.limmin = (float(lo[0]), float(lo[1]))
    msp.dxf.limmax = (float(hi[0]), float(hi[1]))
    size = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    centre = (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2)
    doc.set_modelspace_vport(height=1.1 * size if size > 0 else 1.0, center=centre)
    # the paper (A3 landscape) in drawing units: LibreCAD reads $PLIMMAX in them (420 m wide for metres)
    mpu = {6: 1.0, 5: 0.01, 4: 0.001}.get(doc.units, 0.001)
    paper = doc.paperspace()
    paper.dxf.limmin = (0.0, 0.0)
    paper.dxf.limmax = (0.420 / mpu, 0.297 / mpu)


def scene_to_dxf(scene: ExportScene, options: ExportOptions) -> bytes:
    doc = new_document(scene)
    msp = doc.modelspace()
    line_groups, stray, keep_pts = cad_split(scene, options)
    groups = list(line_groups) + ([scene.frusta] if scene.frusta is not None else [])
    if options.keep_stray:
        groups.append(stray)
    points = scene.points_xyz if options.keep_stray else scene.points_xyz[keep_pts]
    layers = [(layer_name(g.key), g.rgb, g.key != "stray") for g in groups]
    if len(scene.trajectory_w):
        layers.append(("TRAJECTORY", TRAJECTORY_RGB, True))
    if len(points):
        layers.append(("POINTS", POINT_LAYER_RGB, False))  # off: points crowd a drawing; turn on to see them
    for name, rgb, on in layers:
        add_layer(doc, name, rgb, on)
    if len(scene.trajectory_w) >= 2:
        msp.add_polyline3d(scene.trajectory_w.tolist(), dxfattribs={"layer": "TRAJECTORY"})
    elif len(scene.trajectory_w) == 1:
        msp.add_point(scene.trajectory_w[0].tolist(), dxfattribs={"layer": "TRAJECTORY"})
    set_extents(
        doc, np.concatenate([*(g.segments_w.reshape(-1, 3) for g in groups), points, scene.trajectory_w])
    )
    n_entities = sum(len(g.ids) for g in groups) + len(points)
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
    if len(points):
        n = len(points)
        bulk.append(format_rows(_POINT.format(owner=owner, layer="POINTS"), np.arange(h, h + n), points))
        h += n
    stream = io.StringIO()
    doc.write(stream)
    text = stream.getvalue().encode("utf-8")
    start = text.index(b"\n  2\nENTITIES\n")
    end = text.index(b"  0\nENDSEC\n", start)
    return text[:end] + b"".join(bulk) + text[end:]


def export_dxf(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map's lines (one layer per axis), points and trajectory as an R2010 DXF drawing."""
    options = options or ExportOptions()
    return scene_to_dxf(prepare(m, options), options)


FORMATS = {".dxf": export_dxf}
REQUIRES = {".dxf": ("ezdxf", "DXF export")}
