"""Plan and elevation drawings as DXF (ezdxf, R2010) and SVG (ElementTree): `plan.dxf`, `plan.svg`,
`elevation-K.dxf`, `elevation-K.svg`.

Both carry one layer (DXF layer, SVG group) per axis, the trajectory, and an ANNOTATION layer with
the scale bar, the north arrow (plan) and a title naming the units and how the scale was found.
The DXF is in the map's units with extents set; the SVG's viewBox is the drawing, y up the page.
"""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET

import numpy as np

from papl_mapper.map import Map
from papl_mapper.palette import hex_color

from .dxf import add_layer, new_document, set_extents
from .scene import ExportOptions, header_text, prepare
from .views import View, elevation_view, nice_length, plan_view

ANNOTATION_RGB = (0, 0, 0)


def _annotations(view: View) -> dict:
    """Scale bar, north arrow and title placed below and beside the drawing's bounds."""
    lo, hi = view.bounds()
    ext = view.extent
    bar = nice_length(ext)
    y0 = lo[1] - 0.06 * ext
    text_h = 0.02 * ext
    out = {
        "bar": np.array([[lo[0], y0], [lo[0] + bar, y0]]),
        "ticks": np.array(
            [[[lo[0] + x, y0 - text_h / 2], [lo[0] + x, y0 + text_h / 2]] for x in (0, bar / 2, bar)]
        ),
        "bar_label": (view.unit_label(bar), np.array([lo[0] + bar + text_h, y0 - text_h / 2]), text_h),
        "title": (
            header_text(f"{view.title}; units {view.scale_note}", 160),
            np.array([lo[0], y0 - 2.5 * text_h]),
            0.7 * text_h,
        ),
        "text_h": text_h,
        "mark_r": 0.004 * ext,
    }
    if view.north:
        base = np.array([hi[0] + 0.05 * ext, hi[1] - 0.08 * ext])
        tip = base + [0, 0.07 * ext]
        w = 0.012 * ext
        out["arrow"] = np.array([tip, base + [w, 0.02 * ext], base + [-w, 0.02 * ext]])
        out["arrow_shaft"] = np.array([base, tip])
        out["north_label"] = (header_text(view.north_label, 60), tip + [-w, 0.01 * ext], text_h)
    return out


def view_to_dxf(view: View, scene) -> bytes:
    doc = new_document(scene)
    msp = doc.modelspace()
    ann = _annotations(view)
    drawn = []
    for ly in view.layers:
        add_layer(doc, ly.name, ly.rgb)
        attrs = {"layer": ly.name}
        if ly.polyline and len(ly.segments):
            pts = np.concatenate([ly.segments[:, 0], ly.segments[-1:, 1]])
            msp.add_lwpolyline(pts.tolist(), dxfattribs=attrs)
        else:
            for a, b in ly.segments.tolist():
                msp.add_line(a, b, dxfattribs=attrs)
        for p in ly.marks.tolist():
            msp.add_circle(p, ann["mark_r"], dxfattribs=attrs)
        drawn += [ly.segments.reshape(-1, 2), ly.marks]
    add_layer(doc, "ANNOTATION", ANNOTATION_RGB)
    attrs = {"layer": "ANNOTATION"}
    msp.add_line(*ann["bar"].tolist(), dxfattribs=attrs)
    for a, b in ann["ticks"].tolist():
        msp.add_line(a, b, dxfattribs=attrs)
    labels = [ann["bar_label"], ann["title"]]
    if "arrow" in ann:
        msp.add_lwpolyline(ann["arrow"].tolist(), close=True, dxfattribs=attrs)
        msp.add_line(*ann["arrow_shaft"].tolist(), dxfattribs=attrs)
        labels.append(ann["north_label"])
        drawn.append(ann["arrow"])
    for text, at, height in labels:
        msp.add_text(text, height=height, dxfattribs=attrs).set_placement(tuple(at.tolist()))
    drawn += [ann["bar"], ann["title"][1][None], ann["bar_label"][1][None]]
    xy = np.concatenate([a for a in drawn if len(a)])
    # the title's text runs to the right of its insertion point: keep its length inside the extents
    title, at, height = ann["title"]
    xy = np.concatenate([xy, at[None] + [len(title) * 0.6 * height, 0]])
    set_extents(doc, np.column_stack([xy, np.zeros(len(xy))]))
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue().encode("utf-8")


def view_to_svg(view: View) -> bytes:
    ann = _annotations(view)
    lo, hi = view.bounds()
    ext = view.extent
    pad = 0.1 * ext
    x0, x1 = lo[0] - pad, hi[0] + (0.15 if view.north else 0.05) * ext + pad
    y0, y1 = lo[1] - 0.06 * ext - 3.5 * ann["text_h"] - pad, hi[1] + pad
    w, h = x1 - x0, y1 - y0
    width_mm = 400.0
    svg = ET.Element(
        "svg",
        {
            "xmlns": "http://www.w3.org/2000/svg",
            "version": "1.1",
            "width": f"{width_mm:g}mm",
            "height": f"{width_mm * h / w:.6g}mm",
            "viewBox": f"{x0:.9g} {-y1:.9g} {w:.9g} {h:.9g}",  # y flipped below: page up is +y
        },
    )
    ET.SubElement(svg, "title").text = header_text(f"papl-mapper {view.title}; units {view.scale_note}", 200)
    ET.SubElement(
        svg,
        "rect",
        {"x": f"{x0:.9g}", "y": f"{-y1:.9g}", "width": f"{w:.9g}", "height": f"{h:.9g}", "fill": "white"},
    )
    stroke = f"{0.0015 * ext:.6g}"

    def xy(p) -> tuple[str, str]:
        return f"{p[0]:.6f}", f"{-p[1]:.6f}"

    for ly in view.layers:
        g = ET.SubElement(
            svg, "g", {"id": ly.name, "stroke": hex_color(ly.rgb), "stroke-width": stroke, "fill": "none"}
        )
        if ly.polyline and len(ly.segments):
            pts = np.concatenate([ly.segments[:, 0], ly.segments[-1:, 1]])
            ET.SubElement(g, "polyline", {"points": " ".join(",".join(xy(p)) for p in pts)})
        else:
            for a, b in ly.segments:
                (ax, ay), (bx, by) = xy(a), xy(b)
                ET.SubElement(g, "line", {"x1": ax, "y1": ay, "x2": bx, "y2": by})
        for p in ly.marks:
            cx, cy = xy(p)
            ET.SubElement(g, "circle", {"cx": cx, "cy": cy, "r": f"{ann['mark_r']:.6g}"})
    g = ET.SubElement(
        svg, "g", {"id": "ANNOTATION", "stroke": "black", "stroke-width": stroke, "fill": "black"}
    )
    (ax, ay), (bx, by) = xy(ann["bar"][0]), xy(ann["bar"][1])
    ET.SubElement(g, "line", {"x1": ax, "y1": ay, "x2": bx, "y2": by})
    for a, b in ann["ticks"]:
        (ax, ay), (bx, by) = xy(a), xy(b)
        ET.SubElement(g, "line", {"x1": ax, "y1": ay, "x2": bx, "y2": by})
    labels = [("scale-bar-label", *ann["bar_label"]), ("title", *ann["title"])]
    if "arrow" in ann:
        ET.SubElement(
            g, "polygon", {"id": "north-arrow", "points": " ".join(",".join(xy(p)) for p in ann["arrow"])}
        )
        (ax, ay), (bx, by) = xy(ann["arrow_shaft"][0]), xy(ann["arrow_shaft"][1])
        ET.SubElement(g, "line", {"x1": ax, "y1": ay, "x2": bx, "y2": by})
        labels.append(("north-label", *ann["north_label"]))
    for ident, text, at, height in labels:
        x, y = xy(at)
        attrs = {"id": ident, "x": x, "y": y, "font-size": f"{height:.6g}", "stroke": "none"}
        t = ET.SubElement(g, "text", {**attrs, "font-family": "sans-serif"})
        t.text = text
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(svg, encoding="utf-8")


def _plan_scene(m: Map, options: ExportOptions | None):
    options = options or ExportOptions()
    return prepare(m, options), options


def export_plan_dxf(m: Map, options: ExportOptions | None = None) -> bytes:
    """The plan (floor plane, north = first horizontal axis) as DXF in the map's units."""
    scene, options = _plan_scene(m, options)
    return view_to_dxf(plan_view(scene, options), scene)


def export_plan_svg(m: Map, options: ExportOptions | None = None) -> bytes:
    """The plan as SVG."""
    scene, options = _plan_scene(m, options)
    return view_to_svg(plan_view(scene, options))


def export_elevation_dxf(m: Map, options: ExportOptions | None = None) -> bytes:
    """The elevation along horizontal axis `options.elevation_axis` as DXF."""
    scene, options = _plan_scene(m, options)
    return view_to_dxf(elevation_view(scene, options, options.elevation_axis), scene)


def export_elevation_svg(m: Map, options: ExportOptions | None = None) -> bytes:
    """The elevation along horizontal axis `options.elevation_axis` as SVG."""
    scene, options = _plan_scene(m, options)
    return view_to_svg(elevation_view(scene, options, options.elevation_axis))


FORMATS = {
    ".plan.dxf": export_plan_dxf,
    ".plan.svg": export_plan_svg,
    ".elevation.dxf": export_elevation_dxf,
    ".elevation.svg": export_elevation_svg,
}
REQUIRES = {suffix: ("ezdxf", "DXF drawing export") for suffix in FORMATS if suffix.endswith(".dxf")}
