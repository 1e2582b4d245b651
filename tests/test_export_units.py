"""Every export says its units in the format's own field, the same way for a scaled map ('m' and how
the scale was found) and an unscaled one ('arbitrary'), and strings reaching headers stay one line."""

from __future__ import annotations

import json

import pytest

from papl_mapper.exporters import REGISTRY, export
from papl_mapper.scale import ScaleEstimate, scale_map
from tests.conftest import make_map
from tests.test_export_views import read_view_svg

NOTE = "camera height 1.6 m above the floor"


def maps():
    m = make_map(seed=4)
    return {"arbitrary": m, "m": scale_map(m, ScaleEstimate(2.5, 0.003, "camera_height", NOTE))}


def units_of(path, suffix: str) -> tuple[str, str]:
    """(units, scale note) as each format's own reader sees them."""
    if suffix in (".ply", ".tubes.ply"):
        from plyfile import PlyData

        comments = PlyData.read(str(path)).comments
        return next(c[6:] for c in comments if c.startswith("units ")), next(
            c[6:] for c in comments if c.startswith("scale ")
        )
    if suffix in (".glb", ".gltf", ".tubes.glb"):
        import pygltflib

        g = pygltflib.GLTF2().load(str(path))
        extras = g.asset.extras
        return extras["units"], extras.get("scale", "")
    if suffix in (".usda", ".usdc", ".usdz"):
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(path))
        data = stage.GetRootLayer().customLayerData
        assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0  # metres, or the placeholder noted as such
        return data["papl:units"], data["papl:scale"]
    if suffix in (".dxf", ".plan.dxf", ".elevation.dxf"):
        import ezdxf

        doc = ezdxf.readfile(str(path))
        assert doc.header["$INSUNITS"] == (6 if doc.header.custom_vars.get("PAPL_UNITS") == "m" else 0)
        return doc.header.custom_vars.get("PAPL_UNITS"), doc.header.custom_vars.get("PAPL_SCALE")
    if suffix == ".obj":
        head = path.read_text().splitlines()[:2]
        return head[0].split("units ")[1].split(";")[0], head[1].removeprefix("# scale ")
    if suffix in (".plan.svg", ".elevation.svg"):
        title = read_view_svg(path)["title"]
        return title.split("; units ")[1].split(" ")[0], title.split("; units ")[1]
    if suffix == ".colmap":
        line = next(x for x in (path / "cameras.txt").read_text().splitlines() if x.startswith("# Units:"))
        return line.split("# Units: ")[1].split(";")[0], line.split("; scale ")[1]
    if suffix in (".tum", ".tum.txt"):
        return path.read_text().splitlines()[0].split("units ")[1], ""
    raise AssertionError(f"no units reader for {suffix}")


UNITLESS = {".kitti", ".kitti.txt", ".txt"}  # KITTI pose files have no comment syntax: bare rows


@pytest.mark.parametrize("suffix", sorted(set(REGISTRY) - UNITLESS))
@pytest.mark.parametrize("units", ["arbitrary", "m"])
def test_every_format_says_its_units(suffix, units, tmp_path):
    m = maps()[units]
    name = {".plan.dxf": "plan.dxf", ".plan.svg": "plan.svg", ".elevation.dxf": "elevation.dxf",
            ".elevation.svg": "elevation.svg"}.get(suffix, f"map{suffix}")  # fmt: skip
    paths = export(m, tmp_path / name)
    got_units, note = units_of(paths[0].parent if suffix == ".colmap" else paths[0], suffix)
    assert got_units == units
    if suffix not in (".tum", ".tum.txt"):
        want = f"m from {NOTE} +-0.3%" if units == "m" else "arbitrary (monocular scale unknown)"
        assert want in note


def test_usd_and_gltf_metres(tmp_path):
    from pxr import Usd, UsdGeom

    m = maps()["m"]
    stage = Usd.Stage.Open(str(export(m, tmp_path / "m.usda")[0]))
    assert (
        UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        and "papl:note" not in stage.GetRootLayer().customLayerData
    )
    gltf = json.loads(export(m, tmp_path / "m.gltf")[0].read_text())
    assert gltf["asset"]["extras"]["meters_per_unit"] == 1.0


def test_strings_reaching_headers_stay_one_printable_line(tmp_path):
    from plyfile import PlyData

    m = maps()["m"]
    m.metadata["units"] = "m\nend_header\n"
    m.metadata["scale"]["description"] = "evil\r\n0\nEOF\x00"
    ply = PlyData.read(str(export(m, tmp_path / "m.ply")[0]))  # still one valid header
    assert any(c.startswith("units m?end_header?") for c in ply.comments)
    import ezdxf

    doc = ezdxf.readfile(str(export(m, tmp_path / "m.dxf")[0]))
    assert not doc.audit().has_errors
    assert "\n" not in doc.header.custom_vars.get("PAPL_SCALE")
    obj = export(m, tmp_path / "m.obj")[0].read_text().splitlines()
    assert obj[1].startswith("# scale") and not obj[2].startswith("0")
