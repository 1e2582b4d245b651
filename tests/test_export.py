"""Exporters: every registered format is read back by an independent reader and round-trips the map.

The tests loop over `REGISTRY`, so a new format fails here until it has a reader below. Readers are
the real consumers: the Khronos glTF validator, pygltflib and trimesh; USD's validators; plyfile and
Open3D; ezdxf and its audit; evo for TUM/KITTI; pycolmap for COLMAP text; a spec parser for OBJ.
"""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.errors import ConfigError, InputError, MapFormatError
from papl_mapper.exporters import REGISTRY, ExportOptions, export, prepare, supported_suffixes
from papl_mapper.exporters.gltf import srgb_to_linear
from papl_mapper.map import Camera, Keyframes, Map, Points
from papl_mapper.palette import UNANCHORED_RGB, VERTICAL_RGB
from tests.conftest import make_map
from tests.test_export_views import read_view_dxf, read_view_svg

ROUND_TRIP_RTOL = 1e-6  # coordinates read back, relative to the scene's extent
VALIDATOR = Path(__file__).resolve().parents[1] / ".tools" / "node_modules" / "gltf-validator"
ALL_PARTS = ("lines", "points", "trajectory", "frusta")


def known_map(offset: float = 100.0) -> Map:
    """make_map's lines and points moved off the origin, distorted camera, rotated keyframes whose
    point observations are OpenCV's own projections (cv2.projectPoints is the oracle)."""
    import cv2

    m = make_map(n_kf=4, n_pts=40, n_lines=60, seed=3)
    m.lines.endpoints_w += offset
    rng = np.random.default_rng(5)
    cam = Camera(640, 480, 520.0, 515.0, 321.3, 238.7, np.array([-0.12, 0.05, 0.001, -0.002, 0.0]))
    T = np.repeat(np.eye(4)[None], 4, axis=0)
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.05, size=(4, 3))).as_matrix()
    T[:, :3, 3] = [[offset + 0.3 * i, offset, offset - 6.0] for i in range(4)]
    kf = Keyframes(np.array([7, 3, 11, 20]), np.array([0, 5, 10, 15]), np.array([0.0, 0.5, 1.0, 1.5]), T)
    xyz = rng.uniform(-1, 1, (40, 3)) + [offset, offset, offset]
    pids = np.arange(40) * 2 + 1
    obs = np.array([(p, k) for p in pids for k in kf.ids[rng.choice(4, 2, replace=False)]])
    uv = np.empty((len(obs), 2))
    for j, (p, k) in enumerate(obs):
        T_cw = np.linalg.inv(T[list(kf.ids).index(k)])
        rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
        pt = xyz[list(pids).index(p)][None]
        uv[j] = cv2.projectPoints(pt, rvec, T_cw[:3, 3], cam.K, cam.distortion)[0].ravel()
    pts = Points(pids, xyz, rng.integers(0, 255, (40, 3), dtype=np.uint8), obs, uv)
    lines = m.lines
    lines.ref_keyframe_id[lines.ref_keyframe_id >= 0] = 7
    lines.obs_ids[:, 1] = 7
    lines.obs_ids = np.concatenate([lines.obs_ids, lines.obs_ids[:20] * [1, 0] + [0, 3]])
    lines.obs_xy = np.concatenate([lines.obs_xy, lines.obs_xy[:20]])
    out = Map(cam, kf, pts, lines, m.axes, {"units": "arbitrary"})
    out.validate()
    return out


@pytest.fixture(scope="module")
def kmap() -> Map:
    return known_map()


# ---- independent readers: path -> {"segments": {group: (S, 2, 3)}, "colors": {group: rgb}, ...} ----


def _validate_gltf(path: Path) -> dict:
    node = shutil.which("node")
    if node is None or not VALIDATOR.is_dir():
        pytest.skip("the Khronos glTF validator is not installed (scripts/setup.sh installs it)")
    script = (
        "const fs=require('fs');const v=require(process.argv[1]);"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])),{maxIssues:1000})"
        ".then(r=>console.log(JSON.stringify(r)),e=>{console.error(String(e));process.exit(3);});"
    )
    res = subprocess.run(
        [node, "-e", script, str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    errors = [i for i in report["issues"]["messages"] if i["severity"] == 0]
    assert report["issues"]["numErrors"] == 0, errors[:5]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"][:5]
    return report


def _gltf_accessor(g, data: bytes, index: int) -> np.ndarray:
    acc = g.accessors[index]
    view = g.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(data, dtype, acc.count * width, start).reshape(acc.count, width)


def _from_y_up(p: np.ndarray) -> np.ndarray:
    return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1).astype(np.float64)


def read_gltf(path: Path) -> dict:
    import pygltflib
    import trimesh

    _validate_gltf(path)
    g = pygltflib.GLTF2().load(str(path))
    if not g.buffers:
        data = b""
    else:
        data = g.binary_blob() if path.suffix == ".glb" else g.get_data_from_buffer_uri(g.buffers[0].uri)
    out = {"segments": {}, "colors": {}, "modes": {}, "extras": g.asset.extras}
    for node in g.nodes:
        if node.mesh is None:
            continue
        prim = g.meshes[node.mesh].primitives[0]
        pos = _from_y_up(_gltf_accessor(g, data, prim.attributes.POSITION))
        mat = g.materials[prim.material]
        out["modes"][node.name] = prim.mode
        if prim.mode == 1:
            key = node.extras.get("group", node.name)
            out["segments"][key] = pos.reshape(-1, 2, 3)
            out["colors"][key] = np.asarray(mat.pbrMetallicRoughness.baseColorFactor[:3])
            assert "KHR_materials_unlit" in mat.extensions
        elif prim.mode == 3:
            out["trajectory"] = pos
        elif prim.mode == 0:
            out["points"] = pos
            out["points_rgb_linear"] = _gltf_accessor(g, data, prim.attributes.COLOR_0)
        elif prim.mode == 4:
            idx = _gltf_accessor(g, data, prim.indices).reshape(-1, 3)
            out.setdefault("tubes", {})[node.extras["group"]] = (pos, idx)
            out["colors"][node.extras["group"]] = np.asarray(mat.pbrMetallicRoughness.baseColorFactor[:3])
    scene = trimesh.load(str(path), force="scene")
    out["trimesh_geometries"] = len(scene.geometry)
    return out


def read_ply(path: Path) -> dict:
    import open3d as o3d
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    comments = ply.comments
    v = ply["vertex"].data
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    vrgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    out: dict = {"segments": {}, "colors": {}, "comments": comments}
    if "edge" in ply:
        e = ply["edge"].data
        ij = np.stack([e["vertex1"], e["vertex2"]], axis=1)
        ergb = np.stack([e["red"], e["green"], e["blue"]], axis=1)
        assert np.array_equal(vrgb[ij[:, 0]], ergb) and np.array_equal(
            vrgb[ij[:, 1]], ergb
        )  # vertex = edge colour
        ls = o3d.io.read_line_set(str(path))  # Open3D agrees with plyfile on segments and colours
        np.testing.assert_array_equal(np.asarray(ls.lines), ij)
        np.testing.assert_allclose(np.asarray(ls.points), xyz, rtol=1e-7)  # Open3D parses ASCII in float32
        np.testing.assert_allclose(np.asarray(ls.colors), ergb / 255.0, atol=1e-6)
        for c in comments:
            if c.startswith("edges "):
                _, key, a, b = c.split()
                out["segments"][key] = xyz[ij[int(a) : int(b)]]
                out["colors"][key] = ergb[int(a)]
                assert (ergb[int(a) : int(b)] == ergb[int(a)]).all()
            if c.startswith("points vertices "):
                a, b = map(int, c.split()[2:])
                out["points"], out["points_rgb"] = xyz[a:b], vrgb[a:b]
    if "face" in ply:
        faces = np.vstack([np.zeros((0, 3), int), *ply["face"].data["vertex_indices"]])
        mesh = o3d.io.read_triangle_mesh(str(path))
        np.testing.assert_array_equal(np.asarray(mesh.triangles), faces)
        for c in comments:
            if c.startswith("faces "):
                _, key, a, b = c.split()
                f = faces[int(a) : int(b)]
                lo = f.min()
                out.setdefault("tubes", {})[key] = (xyz[lo : f.max() + 1], f - lo)
                out["colors"][key] = vrgb[lo]
    return out


def _validate_usd(path: Path) -> None:
    from pxr import Usd

    try:  # usd-core < 25.8 ships the Python ComplianceChecker (usdchecker)
        from pxr.UsdUtils import ComplianceChecker

        checker = ComplianceChecker(skipARKitRootLayerCheck=True)
        checker.CheckCompliance(str(path))
        assert not checker.GetErrors() and not checker.GetFailedChecks(), checker.GetErrors()
        return
    except ImportError:
        pass
    from pxr import UsdValidation  # its successor: every registered validator, as usdchecker runs them

    stage = Usd.Stage.Open(str(path))
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    issues = ctx.Validate(stage)
    assert not issues, [(str(e.GetType()), e.GetMessage()) for e in issues]  # no errors, nor warnings


def read_usd(path: Path) -> dict:
    from pxr import Usd, UsdGeom

    _validate_usd(path)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    out: dict = {"segments": {}, "colors": {}, "layer_data": stage.GetRootLayer().customLayerData}
    out["meters_per_unit"] = UsdGeom.GetStageMetersPerUnit(stage)
    out["curve_prims"] = 0
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.BasisCurves):
            c = UsdGeom.BasisCurves(prim)
            assert c.GetTypeAttr().Get() == UsdGeom.Tokens.linear
            pts = np.asarray(c.GetPointsAttr().Get(), np.float64)
            counts = np.asarray(c.GetCurveVertexCountsAttr().Get())
            ext = np.asarray(c.GetExtentAttr().Get())
            assert (ext[0] <= pts.min(0)).all() and (ext[1] >= pts.max(0)).all()
            color = np.asarray(c.GetDisplayColorPrimvar().Get())[0]
            if prim.GetName() == "Trajectory":
                assert counts.tolist() == [len(pts)]
                out["trajectory"] = pts
                continue
            assert (counts == 2).all()
            out["curve_prims"] += prim.GetParent().GetName() == "Lines"
            out["segments"][prim.GetName().lower()] = pts.reshape(-1, 2, 3)
            out["colors"][prim.GetName().lower()] = color
        elif prim.IsA(UsdGeom.Points):
            out["points"] = np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get(), np.float64)
    return out


def read_dxf(path: Path) -> dict:
    import ezdxf

    doc = ezdxf.readfile(str(path))
    auditor = doc.audit()
    assert not auditor.has_errors and not auditor.fixes, [str(e) for e in auditor.errors[:5]]
    out: dict = {"segments": {}, "colors": {}, "points": []}
    for e in doc.modelspace():
        layer = e.dxf.layer
        if e.dxftype() == "LINE":
            out["segments"].setdefault(layer.lower(), []).append([e.dxf.start, e.dxf.end])
        elif e.dxftype() == "POINT":
            out["points"].append(e.dxf.location)
        elif e.dxftype() == "POLYLINE":
            out["trajectory"] = np.array([v.dxf.location for v in e.vertices], np.float64)
    out["segments"] = {k: np.asarray(v, np.float64) for k, v in out["segments"].items()}
    out["points"] = np.asarray(out["points"], np.float64).reshape(-1, 3)
    for layer in doc.layers:
        if layer.dxf.name.lower() in out["segments"]:
            out["colors"][layer.dxf.name.lower()] = np.asarray(layer.rgb)
            assert 1 <= layer.dxf.color <= 255  # an ACI fallback colour too
    return out


def read_obj(path: Path) -> dict:
    """A parser written from the OBJ specification: v (with optional colour), l, o/g."""
    import trimesh

    verts, colors, groups, starts, current = [], [], {}, {}, None
    for line in path.read_text().splitlines():
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0] == "v":
            verts.append([float(t) for t in tok[1:4]])
            colors.append([float(t) for t in tok[4:7]])
        elif tok[0] in ("o", "g"):
            current = tok[1]
            groups.setdefault(current, [])
            starts.setdefault(current, len(verts))
        elif tok[0] == "l":
            groups[current].append([int(t) - 1 for t in tok[1:]])
        else:
            raise AssertionError(f"unexpected OBJ statement {tok[0]!r}")
    verts, colors = np.asarray(verts), np.asarray(colors)
    out: dict = {"segments": {}, "colors": {}}
    for key, elements in groups.items():
        if key == "trajectory":
            out["trajectory"] = verts[elements[0]]
        elif elements:
            ij = np.asarray(elements)
            out["segments"][key] = verts[ij]
            out["colors"][key] = np.round(colors[ij[0, 0]] * 255).astype(int)
    # trimesh ignores `l` elements (exchange/obj.py reads faces only) but loads every vertex
    loaded = trimesh.load(str(path), process=False)
    geoms = loaded.geometry.values() if isinstance(loaded, trimesh.Scene) else [loaded]
    loaded_verts = np.concatenate([np.zeros((0, 3))] + [g.vertices for g in geoms])
    np.testing.assert_allclose(loaded_verts, verts.reshape(-1, 3), rtol=1e-12)
    if "points" in groups:  # the last object: vertices without elements
        out["points"] = verts[starts["points"] :]
    return out


def read_tum(path: Path) -> dict:
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(path))
    return {
        "trajectory": traj.positions_xyz,
        "poses": np.asarray(traj.poses_se3),
        "timestamps": traj.timestamps,
    }


def read_kitti(path: Path) -> dict:
    from evo.tools import file_interface

    traj = file_interface.read_kitti_poses_file(str(path))
    return {"trajectory": traj.positions_xyz, "poses": np.asarray(traj.poses_se3)}


def _cam_from_world(image):
    """pycolmap >= 3.12 made Image.cam_from_world a method; before, it was a property."""
    c = image.cam_from_world
    return c() if callable(c) else c


def read_colmap(path: Path) -> dict:
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(path))
    ids = sorted(rec.images)
    poses = []
    for i in ids:
        T_cw = np.eye(4)
        T_cw[:3] = _cam_from_world(rec.images[i]).matrix()
        poses.append(np.linalg.inv(T_cw))
    pts = np.array([rec.points3D[k].xyz for k in sorted(rec.points3D)]).reshape(-1, 3)
    poses = np.asarray(poses).reshape(-1, 4, 4)
    return {"trajectory": poses[:, :3, 3], "poses": poses, "points": pts, "rec": rec}


READERS = {
    ".ply": read_ply,
    ".glb": read_gltf,
    ".gltf": read_gltf,
    ".usda": read_usd,
    ".usdc": read_usd,
    ".usdz": read_usd,
    ".dxf": read_dxf,
    ".obj": read_obj,
    ".tubes.glb": read_gltf,
    ".tubes.ply": read_ply,
    ".tum": read_tum,
    ".tum.txt": read_tum,
    ".kitti": read_kitti,
    ".kitti.txt": read_kitti,
    ".txt": read_kitti,
    ".colmap": read_colmap,
    # plan and elevation views are 2D drawings: read back (audit, XML) here, checked in test_export_views
    ".plan.dxf": read_view_dxf,
    ".elevation.dxf": read_view_dxf,
    ".plan.svg": read_view_svg,
    ".elevation.svg": read_view_svg,
}


def test_every_registered_format_has_a_reader():
    assert set(READERS) == set(REGISTRY), "add an independent reader for every new format"


def _close(a: np.ndarray, b: np.ndarray, scale: float) -> None:
    np.testing.assert_allclose(np.asarray(a, np.float64), b, rtol=0, atol=ROUND_TRIP_RTOL * scale)


def _tube_segments(verts: np.ndarray, faces: np.ndarray, sides: int) -> np.ndarray:
    """Ring centres of each tube: the segment's two endpoints (a regular polygon's mean is its centre)."""
    assert len(faces) % (2 * sides) == 0
    return verts.reshape(-1, 2, sides, 3).mean(axis=2)


@pytest.mark.parametrize("suffix", supported_suffixes())
def test_round_trip(suffix: str, kmap: Map, tmp_path: Path):
    # every line and point, also those CAD exports leave out as stray (kmap's lines are seen once)
    options = ExportOptions(parts=ALL_PARTS, cad_min_observations=0, cad_stray_margin=1e6)
    scene = prepare(kmap, options)
    scale = float(np.abs(np.concatenate([g.segments_w.reshape(-1, 3) for g in scene.line_groups])).max())
    paths = export(kmap, tmp_path / f"map{suffix}", options)
    path = paths[0].parent if suffix == ".colmap" else paths[0]
    got = READERS[suffix](path)
    want = {g.key: g for g in scene.segment_groups()}
    if "segments" in got:
        segs = dict(got["segments"])
        if "trajectory" in got and "trajectory" not in segs:
            want.pop("trajectory")
        if "tubes" in got:
            segs = {k: _tube_segments(v, f, options.tube_sides) for k, (v, f) in got["tubes"].items()}
        assert set(segs) == set(want), (set(segs), set(want))
        for key, g in want.items():
            _close(segs[key], g.segments_w, scale)
            rgb = np.asarray(got["colors"][key], np.float64)
            expect = srgb_to_linear(g.rgb) if rgb.max() <= 1.0 else np.asarray(g.rgb)
            np.testing.assert_allclose(rgb, expect, atol=1e-6)
    if "trajectory" in got:
        _close(got["trajectory"], scene.trajectory_w, scale)
    if "poses" in got:
        order = np.argsort(kmap.keyframes.timestamp)
        _close(got["poses"], kmap.keyframes.T_wc[order], scale)
    if "points" in got:
        _close(got["points"], scene.points_xyz, scale)


def test_gltf_is_y_up_with_one_lines_primitive_per_axis(kmap: Map, tmp_path: Path):
    (path,) = export(kmap, tmp_path / "m.glb", parts=ALL_PARTS)
    got = read_gltf(path)
    scene = prepare(kmap, ExportOptions(parts=ALL_PARTS))
    assert got["modes"] == {
        **{g.name: 1 for g in scene.line_groups if len(g.ids)},
        "frusta": 1,
        "trajectory": 3,
        "points": 0,
    }
    # trimesh loads one geometry per LINES or POINTS primitive (it skips LINE_STRIP, the trajectory)
    assert got["trimesh_geometries"] == len(got["modes"]) - 1
    import pygltflib

    g = pygltflib.GLTF2().load(str(path))
    (vertical,) = [n for n in g.nodes if n.name == "vertical"]
    pos = _gltf_accessor(g, g.binary_blob(), g.meshes[vertical.mesh].primitives[0].attributes.POSITION)
    d = pos[1::2] - pos[0::2]
    assert np.allclose(d[:, [0, 2]], 0, atol=1e-4) and (np.abs(d[:, 1]) > 0.5).all()  # world +Z is glTF +Y
    extras = got["extras"]
    assert extras["units"] == "arbitrary" and [a["name"] for a in extras["axes"]][0] == "vertical"
    np.testing.assert_allclose(extras["axes"][0]["direction_gltf"], [0, 1, 0], atol=1e-12)
    assert np.allclose(got["colors"]["vertical"], srgb_to_linear(VERTICAL_RGB))
    assert np.allclose(got["colors"]["unanchored"], srgb_to_linear(UNANCHORED_RGB))


def test_usd_one_curves_prim_per_axis_and_stage_metadata(kmap: Map, tmp_path: Path):
    (path,) = export(kmap, tmp_path / "m.usda")
    got = read_usd(path)
    scene = prepare(kmap, ExportOptions())
    groups = [g for g in scene.line_groups if len(g.ids)]
    assert got["curve_prims"] == len(groups) == 4  # three axes + unanchored
    for g in groups:
        assert len(got["segments"][g.key]) == len(g.ids)
    assert got["meters_per_unit"] == 1.0 and "arbitrary" in got["layer_data"]["papl:note"]
    text = path.read_text()
    assert 'upAxis = "Z"' in text and "float[] widths" in text and "extent" in text


def test_usd_metres(kmap: Map, tmp_path: Path):
    m = known_map()
    m.metadata["units"] = "m"
    (path,) = export(m, tmp_path / "m.usdc")
    got = read_usd(path)
    assert got["meters_per_unit"] == 1.0 and "papl:note" not in got["layer_data"]


def test_ply_ascii_equals_binary(kmap: Map, tmp_path: Path):
    b = read_ply(export(kmap, tmp_path / "b.ply", parts=ALL_PARTS)[0])
    a = read_ply(export(kmap, tmp_path / "a.ply", parts=ALL_PARTS, ascii=True)[0])
    assert b"format ascii" in (tmp_path / "a.ply").read_bytes()[:40]
    assert set(a["segments"]) == set(b["segments"])
    for k in a["segments"]:
        np.testing.assert_array_equal(a["segments"][k], b["segments"][k])
    np.testing.assert_array_equal(a["points_rgb"], kmap.points.color)


def test_dxf_layers_and_counts(kmap: Map, tmp_path: Path):
    got = read_dxf(export(kmap, tmp_path / "m.dxf", parts=ALL_PARTS, cad_min_observations=0)[0])
    scene = prepare(kmap, ExportOptions(parts=ALL_PARTS))
    counts = {k: len(v) for k, v in got["segments"].items()}
    assert counts == {g.key: len(g.ids) for g in scene.line_groups if len(g.ids)} | {
        "frusta": 8 * len(kmap.keyframes)
    }
    assert len(got["points"]) == len(kmap.points)
    np.testing.assert_allclose(got["colors"]["vertical"], VERTICAL_RGB)


def test_tubes_have_outward_normals(kmap: Map, tmp_path: Path):
    from papl_mapper.exporters.tubes import tube_mesh

    seg = np.array([[[0.0, 0, 0], [0, 0, 2]], [[1, 1, 1], [2, 1, 1]], [[0, 0, 0], [0, 0, 0]]])
    verts, normals, faces = tube_mesh(seg, 0.1, 5)
    assert verts.shape == (30, 3) and faces.shape == (30, 3)
    tri = verts[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis_pt = np.repeat(seg.mean(axis=1), 10, axis=0)
    outward = np.einsum("ij,ij->i", fn, tri.mean(axis=1) - axis_pt)
    assert (
        outward[:20] > 0
    ).all()  # counter-clockwise seen from outside (the zero-length tube is degenerate)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(verts[:5], axis=1), 0.1, atol=1e-6)  # ring about the origin


def test_colmap_matches_opencv_projection(kmap: Map, tmp_path: Path):
    """pycolmap projects our points where OpenCV put the observations, +0.5 pixel (COLMAP's centres)."""
    export(kmap, tmp_path, format="colmap")
    got = read_colmap(tmp_path)
    rec = got["rec"]
    cam = rec.cameras[1]
    assert cam.model.name == "OPENCV"
    np.testing.assert_allclose(cam.params[:4], [520.0, 515.0, 321.8, 239.2])
    pts = kmap.points
    order = np.argsort(kmap.keyframes.timestamp)
    max_err = 0.0
    for image_id, im in rec.images.items():
        kf_row = order[image_id - 1]
        assert im.name == f"frame_{kmap.keyframes.frame_index[kf_row]:06d}.png"
        for p2d in im.points2D:
            xyz = rec.points3D[p2d.point3D_id].xyz
            proj = cam.img_from_cam(_cam_from_world(im) * xyz)
            max_err = max(max_err, float(np.abs(proj - p2d.xy).max()))
            row = p2d.point3D_id - 1
            sel = (pts.obs_ids[:, 0] == pts.ids[row]) & (pts.obs_ids[:, 1] == kmap.keyframes.ids[kf_row])
            np.testing.assert_allclose(p2d.xy, pts.obs_uv[sel][0] + 0.5, atol=1e-6)
    assert max_err < 1e-4
    assert sum(im.num_points2D() for im in rec.images.values()) == len(pts.obs_ids)
    assert max(p.error for p in rec.points3D.values()) < 1e-4  # our ERROR agrees: observations are exact


def test_colmap_text_follows_the_format_spec(kmap: Map, tmp_path: Path):
    """A parser from COLMAP's documented text format, independent of pycolmap."""
    export(kmap, tmp_path / "m.colmap")

    def rows(name: str) -> list[str]:
        return [r for r in (tmp_path / "m.colmap" / name).read_text().splitlines() if not r.startswith("#")]

    (cam,) = rows("cameras.txt")
    assert cam.split()[:4] == ["1", "OPENCV", "640", "480"] and len(cam.split()) == 12
    images = rows("images.txt")
    assert len(images) == 2 * len(kmap.keyframes)
    T = kmap.keyframes.T_wc[np.argsort(kmap.keyframes.timestamp)]
    n_obs = 0
    for i in range(len(kmap.keyframes)):
        head, p2d = images[2 * i].split(), images[2 * i + 1].split()
        assert int(head[0]) == i + 1 and head[8] == "1"
        qw, qx, qy, qz, tx, ty, tz = map(float, head[1:8])
        R_cw = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        np.testing.assert_allclose(R_cw, T[i, :3, :3].T, atol=1e-12)
        np.testing.assert_allclose([tx, ty, tz], -T[i, :3, :3].T @ T[i, :3, 3], atol=1e-9)
        assert len(p2d) % 3 == 0
        n_obs += len(p2d) // 3
    assert n_obs == len(kmap.points.obs_ids)
    pts = rows("points3D.txt")
    assert len(pts) == len(kmap.points)
    for r, xyz in zip(pts, kmap.points.xyz, strict=True):
        tok = r.split()
        np.testing.assert_allclose([float(t) for t in tok[1:4]], xyz, rtol=1e-15)
        assert (len(tok) - 8) % 2 == 0 and len(tok) - 8 == 4  # two observations each


@pytest.mark.parametrize(
    ("dist", "model", "n"),
    [
        (np.zeros(5), "PINHOLE", 4),
        (np.array([0.1, 0.0, 0.0, 0.0]), "OPENCV", 8),
        (np.array([0.1, 0, 0, 0, 0.01]), "FULL_OPENCV", 12),
    ],
)
def test_colmap_camera_models(dist, model, n):
    from papl_mapper.exporters.colmap import colmap_camera

    name, params = colmap_camera(Camera(100, 80, 90.0, 91.0, 49.5, 39.5, dist))
    assert name == model and len(params) == n and params[2] == 50.0 and params[3] == 40.0


# ---- options ------------------------------------------------------------------------------


def test_parts_and_min_observations(kmap: Map, tmp_path: Path):
    got = read_ply(export(kmap, tmp_path / "l.ply", parts=("lines",), min_observations=2)[0])
    assert "points" not in got and "trajectory" not in got["segments"]
    n = sum(len(v) for v in got["segments"].values())
    assert n == 20  # known_map gives the first 20 lines a second observation
    with pytest.raises(ConfigError, match="unknown part"):
        export(kmap, tmp_path / "x.ply", parts=("walls",))
    with pytest.raises(ConfigError, match="palette"):
        export(kmap, tmp_path / "x.ply", palette="rainbow")
    with pytest.raises(ConfigError, match="unknown export option"):
        export(kmap, tmp_path / "x.ply", colour="red")


def test_vivid_palette_keeps_vertical_blue_and_unanchored_grey(kmap: Map, tmp_path: Path):
    got = read_ply(export(kmap, tmp_path / "v.ply", palette="vivid")[0])
    np.testing.assert_array_equal(got["colors"]["vertical"], VERTICAL_RGB)
    np.testing.assert_array_equal(got["colors"]["unanchored"], UNANCHORED_RGB)
    assert tuple(got["colors"]["horizontal_1"]) == (228, 26, 28)


# ---- bad input ------------------------------------------------------------------------------


def test_unknown_suffix_lists_supported(kmap: Map, tmp_path: Path):
    with pytest.raises(InputError, match=r"unknown export suffix '\.stl'.*\.ply.*\.glb"):
        export(kmap, tmp_path / "m.stl")
    with pytest.raises(InputError, match="unknown export format"):
        export(kmap, tmp_path / "m.ply", format="stl")
    assert not list(tmp_path.iterdir())


def test_unwritable_path(kmap: Map, tmp_path: Path, monkeypatch):
    with pytest.raises(InputError, match="does not exist"):
        export(kmap, tmp_path / "missing" / "m.ply")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        export(kmap, tmp_path / "dir.ply")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    if os.geteuid() == 0:  # root writes anywhere: make the folder refuse the temporary file instead
        import papl_mapper.atomic as atomic

        def refuse(*a, **k):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    with pytest.raises(InputError, match="cannot write in .*Permission denied"):
        export(kmap, ro / "m.ply")
    assert not list(ro.iterdir())


@pytest.mark.parametrize("suffix", supported_suffixes())
def test_empty_map_gives_valid_empty_file_and_warning(suffix: str, tmp_path: Path, caplog):
    m = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5))
    with caplog.at_level(logging.WARNING, logger="papl_mapper"):
        paths = export(m, tmp_path / f"e{suffix}")
    assert all(p.is_file() for p in paths)
    assert any("empty" in r.getMessage() for r in caplog.records)
    path = paths[0].parent if suffix == ".colmap" else paths[0]
    if suffix in (".tum", ".tum.txt", ".kitti", ".kitti.txt", ".txt"):
        assert path.read_bytes() == b""  # no poses, no rows (evo refuses an empty trajectory)
        return
    got = READERS[suffix](path)
    assert all(len(v) == 0 for v in got.get("segments", {}).values())


@pytest.mark.parametrize("suffix", supported_suffixes())
def test_non_finite_coordinates_refused_with_ids(suffix: str, kmap: Map, tmp_path: Path):
    m = known_map()
    if suffix in (".tum", ".tum.txt", ".kitti", ".kitti.txt", ".txt", ".colmap"):
        m.keyframes.T_wc[2, 0, 3] = np.inf
        bad = m.keyframes.ids[2]
    else:
        m.lines.endpoints_w[[4, 9], 1, 2] = np.nan
        bad = m.lines.ids[4]
    with pytest.raises(MapFormatError, match=rf"NaN or infinite.*\b{bad}\b"):
        export(m, tmp_path / f"n{suffix}")
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def test_non_finite_points_refused_with_ids(tmp_path: Path):
    m = known_map()
    m.points.xyz[[3, 17]] = [np.nan, np.inf, 0.0]
    with pytest.raises(MapFormatError, match=rf"points.xyz.*ids \[{m.points.ids[3]}, {m.points.ids[17]}\]"):
        export(m, tmp_path / "p.glb")
    export(m, tmp_path / "p.glb", parts=("lines",))  # not exported, so not in the way


def test_existing_output_is_replaced_atomically(kmap: Map, tmp_path: Path, monkeypatch):
    path = tmp_path / "m.glb"
    path.write_bytes(b"old")
    export(kmap, path)
    new = path.read_bytes()
    assert new[:4] == b"glTF"
    # a failure while writing leaves the old file whole and no temporary file behind
    import papl_mapper.exporters.registry as registry

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(registry.os, "fsync", boom)
    with pytest.raises(InputError, match="No space left"):
        export(make_map(seed=9), path)
    assert path.read_bytes() == new
    assert [p.name for p in tmp_path.iterdir()] == ["m.glb"]


def test_exports_are_deterministic(kmap: Map, tmp_path: Path):
    for suffix in (".ply", ".glb", ".usda", ".obj", ".tubes.ply"):  # not DXF: its header holds dates
        a = export(kmap, tmp_path / f"a{suffix}")[0].read_bytes()
        b = export(kmap, tmp_path / f"b{suffix}")[0].read_bytes()
        assert a == b, suffix


# ---- CLI --------------------------------------------------------------------------------------


def test_cli_export(kmap: Map, tmp_path: Path, capsys):
    from papl_mapper.cli import main

    src = kmap.save(tmp_path / "m.papl")
    outs = [tmp_path / "o.ply", tmp_path / "o.tubes.glb", tmp_path / "o.colmap"]
    rc = main(["export", str(src), *map(str, outs), "--parts", "lines,points", "--min-obs", "2", "--ascii"])
    assert rc == 0
    printed = capsys.readouterr().out.split()
    assert str(outs[0]) in printed and str(outs[2] / "points3D.txt") in printed
    got = read_ply(outs[0])
    assert sum(len(v) for v in got["segments"].values()) == 20
    assert main(["export", str(src), str(tmp_path / "o.abc")]) == 2
    assert "unknown export suffix" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "nope.papl"), str(tmp_path / "o.ply")]) == 2
    assert "no such map file" in capsys.readouterr().err


def test_ply_header_is_what_open3d_writes(kmap: Map):
    """Our binary layout matches Open3D's own write_line_set element and property names."""
    from papl_mapper.exporters.ply import export_ply

    head = export_ply(kmap).split(b"end_header")[0].decode()
    for want in (
        "element vertex",
        "element edge",
        "property int vertex1",
        "property int vertex2",
        "property uchar red",
    ):
        assert want in head
    assert io.BytesIO(export_ply(kmap)).read(3) == b"ply"


def test_format_rows_matches_python_formatting():
    from papl_mapper.exporters.text import BLOCK_ROWS, format_rows

    rng = np.random.default_rng(0)
    n = BLOCK_ROWS + 7  # more than one block
    ints, floats = rng.integers(-(10**6), 10**6, n), rng.normal(size=(n, 2)) * 1e3
    want = "".join(f"{i:d} {a:.9g} {b:.3f}\n" for i, a, b in zip(ints, *floats.T, strict=True)).encode()
    assert format_rows("%d %.9g %.3f\n", ints, floats) == want  # float path
    big = np.array([2**60 + 1, 7])  # beyond float64's exact integers: the object path keeps them exact
    assert format_rows("%d %X\n", big, big) == f"{2**60 + 1} {2**60 + 1:X}\n7 7\n".encode()
    assert format_rows("%d\n", np.zeros(0, int)) == b""


@pytest.mark.parametrize("n", [1, 7, 1024, 1025, 5000])
def test_column_bounds_equal_numpy(n: int):
    from papl_mapper.exporters.gltf import column_bounds

    a = np.random.default_rng(n).normal(size=(n, 3)).astype(np.float32)
    lo, hi = column_bounds(a)
    np.testing.assert_array_equal(lo, a.min(axis=0))
    np.testing.assert_array_equal(hi, a.max(axis=0))


def test_frusta_corners_project_to_the_image_corners(kmap: Map):
    """Each frustum's far corners reproject (pinhole) onto the image borders, at the asked depth."""
    from papl_mapper.exporters.scene import frustum_segments

    seg = frustum_segments(kmap, depth=2.0).reshape(len(kmap.keyframes), 8, 2, 3)
    cam = kmap.camera
    for T_wc, s in zip(kmap.keyframes.T_wc, seg, strict=True):
        np.testing.assert_allclose(s[:4, 0], np.broadcast_to(T_wc[:3, 3], (4, 3)))  # rays leave the centre
        corners_c = (s[:4, 1] - T_wc[:3, 3]) @ T_wc[:3, :3]  # world -> camera (R^T x)
        np.testing.assert_allclose(corners_c[:, 2], 2.0)
        uv = corners_c[:, :2] / corners_c[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        w, h = cam.width - 0.5, cam.height - 0.5
        np.testing.assert_allclose(uv, [[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], atol=1e-9)
        np.testing.assert_allclose(s[4:, 0], s[:4, 1])  # the rim joins the corners in order
        np.testing.assert_allclose(s[4:, 1], np.roll(s[:4, 1], -1, axis=0))


def test_observation_counts_ignore_unknown_ids():
    from papl_mapper.exporters.scene import observation_counts

    ids = np.array([30, 10, 20])
    obs = np.array([10, 10, 20, 99, 30, 10, 5])
    np.testing.assert_array_equal(observation_counts(ids, obs), [1, 3, 1])
    np.testing.assert_array_equal(observation_counts(np.zeros(0, int), obs), [])


def test_options_from_toml(tmp_path: Path):
    from papl_mapper.config import load_config

    cfg = tmp_path / "export.toml"
    cfg.write_text('parts = ["lines", "frusta"]\nmin_observations = 3\npalette = "vivid"\n')
    o = load_config(ExportOptions, cfg, ["tube_sides=8"])
    assert o.parts == ("lines", "frusta") and o.min_observations == 3 and o.palette == "vivid"
    assert o.tube_sides == 8
    with pytest.raises(ConfigError, match="tube_sides"):
        ExportOptions(tube_sides=2).check()
