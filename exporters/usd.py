"""USD (.usda, .usdc, .usdz): one linear BasisCurves prim per axis with a constant displayColor.

Layout: /Map (defaultPrim, kind component) holding Lines/<axis> (vertical, horizontal_1, ...,
unanchored), Frusta, Trajectory (one linear curve) and Points (UsdGeom.Points). Widths are a
fraction of the scene's bounding-box diagonal; extents are authored; the stage is `upAxis = Z` with
`metersPerUnit`, and customLayerData notes when the map's units are arbitrary. Arrays go in as
Vt arrays built from numpy, never element by element.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from papl_mapper.errors import BackendUnavailableError
from papl_mapper.extras import require
from papl_mapper.map import Map
from papl_mapper.palette import hex_color

from .gltf import srgb_to_linear
from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, prepare


def _pxr():
    require("pxr.Usd", "USD export")
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdUtils, Vt

    return Gf, Kind, Sdf, Usd, UsdGeom, UsdUtils, Vt


def build_stage(scene: ExportScene, options: ExportOptions):
    """An in-memory Usd.Stage holding the scene."""
    Gf, Kind, Sdf, Usd, UsdGeom, UsdUtils, Vt = _pxr()
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mpu = scene.meters_per_unit
    UsdGeom.SetStageMetersPerUnit(stage, mpu if mpu is not None else 1.0)
    note = {
        "papl:units": scene.units,
        "papl:scale": scene.scale_note,
        "papl:generator": "papl-mapper",
        "papl:axes": json.dumps(scene.axis_info),
    }
    if mpu is None:
        note["papl:note"] = (
            f"map units are {scene.units!r} (monocular scale is unknown): metersPerUnit = 1 is a placeholder"
        )
    stage.GetRootLayer().customLayerData = note
    root = UsdGeom.Xform.Define(stage, "/Map")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)

    def vec3f(xyz: np.ndarray):
        return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(xyz, dtype=np.float32))

    def curves(path: str, xyz: np.ndarray, counts: np.ndarray, rgb, width: float):
        c = UsdGeom.BasisCurves.Define(stage, path)
        c.CreateTypeAttr(UsdGeom.Tokens.linear)
        c.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
        c.CreatePointsAttr(vec3f(xyz))
        c.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
        c.CreateWidthsAttr(Vt.FloatArray([width]))
        c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
        pv = c.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant)
        pv.Set(Vt.Vec3fArray([Gf.Vec3f(*srgb_to_linear(rgb).tolist())]))
        _extent(c, xyz, width, Vt, Gf)
        return c

    width = options.line_width * scene.diagonal
    if any(len(g.ids) for g in scene.line_groups):
        UsdGeom.Scope.Define(stage, "/Map/Lines")
    for g in scene.line_groups:
        if not len(g.ids):
            continue
        c = curves(f"/Map/Lines/{g.key}", g.segments_w.reshape(-1, 3), np.full(len(g.ids), 2), g.rgb, width)
        data = {"papl:group": g.name, "papl:colorSrgb": hex_color(g.rgb), "papl:segments": len(g.ids)}
        if g.axis_index >= 0:
            data |= {"papl:axisIndex": g.axis_index, "papl:direction": Gf.Vec3d(*g.direction_w.tolist())}
        c.GetPrim().SetCustomData(data)
    if scene.frusta is not None and len(scene.frusta.ids):
        f = scene.frusta
        curves("/Map/Frusta", f.segments_w.reshape(-1, 3), np.full(len(f.ids), 2), f.rgb, width / 2)
    if len(scene.trajectory_w) >= 2:
        curves(
            "/Map/Trajectory", scene.trajectory_w, np.array([len(scene.trajectory_w)]), TRAJECTORY_RGB, width
        )
    if len(scene.points_xyz):
        p = UsdGeom.Points.Define(stage, "/Map/Points")
        size = options.point_size * scene.diagonal
        p.CreatePointsAttr(vec3f(scene.points_xyz))
        p.CreateWidthsAttr(Vt.FloatArray([size]))
        p.SetWidthsInterpolation(UsdGeom.Tokens.constant)
        pv = p.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
        pv.Set(vec3f(srgb_to_linear(scene.points_rgb)))
        _extent(p, scene.points_xyz, size, Vt, Gf)
    return stage


def _extent(prim, xyz: np.ndarray, width: float, Vt, Gf) -> None:
    lo = xyz.min(axis=0) - width / 2
    hi = xyz.max(axis=0) + width / 2
    prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))


def _export(m: Map, options: ExportOptions | None, suffix: str) -> bytes:
    options = options or ExportOptions()
    stage = build_stage(prepare(m, options), options)
    layer = stage.GetRootLayer()
    if suffix == ".usda":
        return layer.ExportToString().encode()
    _, _, Sdf, _, _, UsdUtils, _ = _pxr()
    with tempfile.TemporaryDirectory(prefix="papl-usd-") as tmp:
        usdc = Path(tmp) / "map.usdc"
        if not layer.Export(str(usdc)):
            raise BackendUnavailableError(f"USD could not write {usdc}")
        if suffix == ".usdc":
            return usdc.read_bytes()
        usdz = Path(tmp) / "map.usdz"
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(usdc)), str(usdz)):
            raise BackendUnavailableError(f"USD could not package {usdz}")
        return usdz.read_bytes()


def export_usda(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as a USD text layer."""
    return _export(m, options, ".usda")


def export_usdc(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as a USD binary (crate) layer."""
    return _export(m, options, ".usdc")


def export_usdz(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as a USDZ package holding one crate layer."""
    return _export(m, options, ".usdz")


FORMATS = {".usda": export_usda, ".usdc": export_usdc, ".usdz": export_usdz}
REQUIRES = {suffix: ("pxr.Usd", "USD export") for suffix in FORMATS}
