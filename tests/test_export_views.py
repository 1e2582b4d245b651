"""CAD exports read back: plan and elevation views (DXF through ezdxf's audit, SVG through an XML
parser and headless Chromium), the structure DXF's units, extents and stray geometry, and both
printed by LibreCAD's dxf2pdf to check the drawing fills the page."""

from __future__ import annotations

import os
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.exporters import export
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points
from papl_mapper.scale import ScaleEstimate, scale_map

SVG = "{http://www.w3.org/2000/svg}"


def read_view_dxf(path: Path) -> dict:
    """Layers of a plan or elevation DXF: segments (S, 2, 2), circle centres (K, 2), texts; audit clean."""
    import ezdxf

    doc = ezdxf.readfile(str(path))
    auditor = doc.audit()
    assert not auditor.has_errors and not auditor.fixes, [str(e) for e in auditor.errors[:5]]
    layers: dict = {}
    texts = []
    for e in doc.modelspace():
        ly = layers.setdefault(e.dxf.layer, {"segments": [], "marks": []})
        if e.dxftype() == "LINE":
            ly["segments"].append([list(e.dxf.start)[:2], list(e.dxf.end)[:2]])
        elif e.dxftype() == "CIRCLE":
            ly["marks"].append(list(e.dxf.center)[:2])
        elif e.dxftype() == "LWPOLYLINE":
            pts = np.array(e.get_points("xy"))
            ly["segments"] += [[a, b] for a, b in zip(pts[:-1], pts[1:], strict=True)]
        elif e.dxftype() == "TEXT":
            texts.append(e.dxf.text)
    for ly in layers.values():
        ly["segments"] = np.asarray(ly["segments"], np.float64).reshape(-1, 2, 2)
        ly["marks"] = np.asarray(ly["marks"], np.float64).reshape(-1, 2)
    return {
        "layers": layers,
        "texts": texts,
        "insunits": doc.header["$INSUNITS"],
        "extents": (np.array(doc.header["$EXTMIN"]), np.array(doc.header["$EXTMAX"])),
        "layer_names": [ly.dxf.name for ly in doc.layers],
    }


def read_view_svg(path: Path) -> dict:
    """Groups of a plan or elevation SVG in drawing coordinates (y up again), and its texts."""
    root = ET.parse(path).getroot()
    assert root.tag == f"{SVG}svg" and len(root.get("viewBox").split()) == 4
    layers, texts = {}, {}
    for g in root.iter(f"{SVG}g"):
        segs = [
            [[float(e.get("x1")), -float(e.get("y1"))], [float(e.get("x2")), -float(e.get("y2"))]]
            for e in g.iter(f"{SVG}line")
        ]
        for pl in g.iter(f"{SVG}polyline"):
            p = np.array([[float(v) for v in xy.split(",")] for xy in pl.get("points").split()]) * [1, -1]
            segs += [[a, b] for a, b in zip(p[:-1].tolist(), p[1:].tolist(), strict=True)]
        marks = [[float(c.get("cx")), -float(c.get("cy"))] for c in g.iter(f"{SVG}circle")]
        layers[g.get("id")] = {
            "segments": np.asarray(segs, np.float64).reshape(-1, 2, 2),
            "marks": np.asarray(marks, np.float64).reshape(-1, 2),
            "stroke": g.get("stroke"),
        }
        for t in g.iter(f"{SVG}text"):
            texts[t.get("id")] = t.text
    return {"layers": layers, "texts": texts, "title": root.find(f"{SVG}title").text}


def structure_map(metres: bool = True) -> Map:
    """Corner posts (vertical lines) at known plan positions, wall lines along +X and +Y, a walk.

    Axes: 0 vertical (+Z), 1 = +X (north of the plan), 2 = +Y. Every line is seen in 4 keyframes.
    """
    posts = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0], [2.0, 3.0]])
    ends, axis = [], []
    for x, y in posts:
        ends.append([[x, y, 0.2], [x, y, 2.2]])
        axis.append(0)
    for y in (0.0, 3.0):  # walls along +X at two heights
        for z in (0.1, 2.4):
            ends.append([[0.3, y, z], [3.7, y, z]])
            axis.append(1)
    for x in (0.0, 4.0):
        ends.append([[x, 0.3, 0.1], [x, 2.7, 0.1]])
        axis.append(2)
    ends = np.array(ends)
    n, n_kf = len(ends), 6
    w = np.zeros((n, 3))
    w[np.arange(n), axis] = 1.0
    T = np.repeat(np.eye(4)[None], n_kf, axis=0)
    T[:, :3, 3] = np.stack([np.linspace(0.8, 3.2, n_kf), np.full(n_kf, 1.5), np.full(n_kf, 1.6)], axis=1)
    obs = np.array([[i, k] for i in range(n) for k in range(4)])
    lines = Lines(
        np.arange(n), ends, w, np.full(n, LineState.ANCHORED, np.int8), np.zeros(n, np.int64),
        np.full(n, 0.3), obs, np.zeros((len(obs), 4)),
    )  # fmt: skip
    pts = Points(np.arange(3), np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [3.0, 2.0, 0.0]]),
                 np.zeros((3, 3), np.uint8), np.zeros((0, 2), np.int64), np.zeros((0, 2)))  # fmt: skip
    kf = Keyframes(np.arange(n_kf), np.arange(n_kf), np.arange(n_kf) / 10, T)
    m = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5), kf, pts, lines, Axes(np.eye(3)[[2, 0, 1]], 0))
    if metres:
        m = scale_map(m, ScaleEstimate(1.0, 0.004, "marker", "ArUco 4X4_50 id 0 (0.2 m) in 6 keyframes"))
    return m


def plan_xy(xyz: np.ndarray) -> np.ndarray:
    """Plan coordinates of the structure map: north (page up) = +X, east (right) = north x up = -Y."""
    return np.stack([-xyz[..., 1], xyz[..., 0]], axis=-1)


def test_plan_dxf_holds_posts_as_marks_and_walls_as_traces(tmp_path):
    m = structure_map()
    got = read_view_dxf(export(m, tmp_path / "plan.dxf")[0])
    assert got["insunits"] == 6  # metres
    layers = got["layers"]
    assert {"VERTICAL", "HORIZONTAL_1", "HORIZONTAL_2", "TRAJECTORY", "ANNOTATION"} <= set(layers)
    np.testing.assert_allclose(
        np.sort(layers["VERTICAL"]["marks"], axis=0), np.sort(plan_xy(m.lines.endpoints_w[:5, 0]), axis=0)
    )
    want = plan_xy(m.lines.endpoints_w[5:9])
    np.testing.assert_allclose(layers["HORIZONTAL_1"]["segments"], want, atol=1e-9)
    assert len(layers["VERTICAL"]["segments"]) == 0
    assert "0.5 m" in got["texts"] and "N: horizontal 1" in got["texts"]
    assert any("units m from ArUco 4X4_50 id 0" in t for t in got["texts"])
    lo, hi = got["extents"]
    every = np.concatenate([ly["segments"].reshape(-1, 2) for ly in layers.values()])
    assert (every >= lo[:2] - 1e-9).all() and (every <= hi[:2] + 1e-9).all()


def test_plan_svg_matches_the_dxf(tmp_path):
    m = structure_map()
    dxf = read_view_dxf(export(m, tmp_path / "site.plan.dxf")[0])
    svg = read_view_svg(export(m, tmp_path / "site.plan.svg")[0])
    for name in ("VERTICAL", "HORIZONTAL_1", "HORIZONTAL_2"):
        np.testing.assert_allclose(svg["layers"][name]["marks"], dxf["layers"][name]["marks"], atol=1e-5)
        np.testing.assert_allclose(
            svg["layers"][name]["segments"], dxf["layers"][name]["segments"], atol=1e-5
        )
    assert svg["layers"]["VERTICAL"]["stroke"] == "#0072b2"
    assert svg["texts"]["scale-bar-label"] == "0.5 m" and svg["texts"]["north-label"] == "N: horizontal 1"
    assert "units m from ArUco" in svg["title"]


def test_elevation_looks_along_its_axis(tmp_path):
    m = structure_map()
    got = read_view_svg(export(m, tmp_path / "elevation-2.svg")[0])["layers"]
    # looking along +Y (horizontal 2): right = +Y x up = +X, page up = +Z; Y lines seen end-on
    assert len(got["HORIZONTAL_2"]["segments"]) == 0 and len(got["HORIZONTAL_2"]["marks"]) == 2
    np.testing.assert_allclose(got["VERTICAL"]["segments"], m.lines.endpoints_w[:5][..., [0, 2]], atol=1e-5)
    one = read_view_dxf(export(m, tmp_path / "elevation-1.dxf")[0])["layers"]
    assert len(one["HORIZONTAL_1"]["marks"]) == 4 and len(one["HORIZONTAL_2"]["segments"]) == 2
    with pytest.raises(InputError, match="elevation-3: the map has horizontal axes 1..2"):
        export(m, tmp_path / "elevation-3.dxf")
    assert not (tmp_path / "elevation-3.dxf").exists()


def test_arbitrary_units_say_so(tmp_path):
    m = structure_map(metres=False)
    svg = read_view_svg(export(m, tmp_path / "plan.svg")[0])
    assert svg["texts"]["scale-bar-label"].endswith(" units")
    assert "units arbitrary (monocular scale unknown)" in svg["title"]
    assert read_view_dxf(export(m, tmp_path / "plan.dxf")[0])["insunits"] == 0


def test_no_vertical_axis_is_refused(tmp_path):
    m = structure_map()
    m.axes.vertical_index = -1
    with pytest.raises(InputError, match="no vertical axis"):
        export(m, tmp_path / "plan.svg")


def test_header_strings_are_escaped(tmp_path):
    m = structure_map()
    m.metadata["scale"]["description"] = 'evil <svg onload="x"> & \n0\nEOF'
    svg_path = export(m, tmp_path / "plan.svg")[0]
    svg = read_view_svg(svg_path)  # still well-formed XML
    assert "<svg onload" in svg["title"] and "\n" not in svg["title"]
    assert "onload" not in ET.parse(svg_path).getroot().attrib
    got = read_view_dxf(export(m, tmp_path / "plan.dxf")[0])  # audit clean: no stray group codes
    assert all("\n" not in t for t in got["texts"])


def test_structure_dxf_units_extents_and_strays(tmp_path):
    import ezdxf

    m = structure_map()
    n = len(m.lines)
    far = np.array([[[500.0, 500.0, 0.0], [501.0, 500.0, 0.0]]])  # a stray line far outside
    ln = m.lines
    m.lines = Lines(
        np.append(ln.ids, [100, 101]), np.concatenate([ln.endpoints_w, far, ln.endpoints_w[:1]]),
        np.concatenate([ln.axis_weights, ln.axis_weights[5:6], ln.axis_weights[:1]]),
        np.append(ln.state, [LineState.ANCHORED] * 2).astype(np.int8), np.append(ln.ref_keyframe_id, [0, 0]),
        np.append(ln.inverse_depth, [0.3, 0.3]),
        np.concatenate([m.lines.obs_ids, [[100, 0], [100, 1], [100, 2], [101, 0]]]),  # 101: seen once
        np.zeros((len(m.lines.obs_ids) + 4, 4)),
    )  # fmt: skip
    doc = ezdxf.readfile(str(export(m, tmp_path / "map.dxf")[0]))
    assert doc.header["$INSUNITS"] == 6 and doc.header["$MEASUREMENT"] == 1
    lo, hi = np.array(doc.header["$EXTMIN"]), np.array(doc.header["$EXTMAX"])
    assert hi[0] < 100 and lo[0] > -100  # the stray line is not in the drawing
    assert doc.header.custom_vars.get("PAPL_SCALE").startswith("m from ArUco")
    lines = [e for e in doc.modelspace() if e.dxftype() == "LINE"]
    assert len(lines) == n
    assert not doc.layers.get("POINTS").is_on()
    kept = ezdxf.readfile(str(export(m, tmp_path / "all.dxf", keep_stray=True)[0]))
    stray = [e for e in kept.modelspace() if e.dxftype() == "LINE" and e.dxf.layer == "STRAY"]
    assert len(stray) == 2 and not kept.layers.get("STRAY").is_on()


def _page_ink(pdf: Path, tmp: Path) -> tuple[float, float]:
    """Fractions of the page's width and height spanned by non-white pixels (pdftoppm at 40 dpi)."""
    from PIL import Image

    subprocess.run(["pdftoppm", "-r", "40", "-png", "-singlefile", str(pdf), str(tmp / "page")], check=True)
    ink = np.asarray(Image.open(tmp / "page.png").convert("L")) < 200
    ys, xs = np.nonzero(ink)
    assert len(xs), "the page is blank"
    return (xs.max() - xs.min()) / ink.shape[1], (ys.max() - ys.min()) / ink.shape[0]


@pytest.mark.skipif(
    not (shutil.which("librecad") and shutil.which("pdftoppm")), reason="librecad or pdftoppm missing"
)
@pytest.mark.parametrize("name", ["map.dxf", "plan.dxf"])
def test_librecad_prints_the_drawing_filling_the_page(name, tmp_path):
    m = structure_map()
    m.points = Points(
        np.arange(4), np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [900.0, -700.0, 3.0], [-800, 600, 0.0]]),
        np.zeros((4, 3), np.uint8), np.zeros((0, 2), np.int64), np.zeros((0, 2)),
    )  # fmt: skip  # two stray points far away
    path = export(m, tmp_path / name)[0]
    run = subprocess.run(
        ["librecad", "dxf2pdf", "-a", "-o", str(tmp_path / "out.pdf"), str(path)],
        capture_output=True, text=True, timeout=120, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"},
        cwd=tmp_path,
    )  # fmt: skip
    pdf = tmp_path / "out.pdf" if (tmp_path / "out.pdf").exists() else path.with_suffix(".pdf")
    assert pdf.exists(), run.stdout + run.stderr
    w, h = _page_ink(pdf, tmp_path)
    assert max(w, h) > 0.6, (w, h)  # fills the page, not squeezed into a corner


@pytest.mark.skipif(not shutil.which("chromium"), reason="chromium missing")
def test_chromium_renders_the_plan(tmp_path):
    from PIL import Image

    svg = export(structure_map(), tmp_path / "plan.svg")[0]
    shot = tmp_path / "shot.png"
    subprocess.run(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
         "--window-size=800,1000", svg.as_uri()],
        capture_output=True, timeout=120, check=True,
    )  # fmt: skip
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    blue = (np.abs(img - [0, 114, 178]).sum(axis=2) < 60).sum()  # vertical posts
    green = (np.abs(img - [0, 158, 115]).sum(axis=2) < 60).sum()  # horizontal 2 walls
    assert blue > 20 and green > 20, (blue, green)
