"""glTF 2.0 (.gltf with an embedded buffer, .glb): one LINES primitive per axis with an unlit material.

Each axis (and the unanchored lines, the trajectory as LINE_STRIP, frusta as LINES, points as
POINTS with COLOR_0) is its own node and mesh, so viewers can toggle them. Materials carry the
axis colour (converted to linear, as glTF requires) and `KHR_materials_unlit`. The map's +Z-up
world is converted to glTF's +Y-up: (x, y, z) -> (x, z, -y). Units and axes go in `extras`.

Hand-written (a dict and the buffer's bytes joined once) rather than through pygltflib or trimesh: on
1M segments both were slower, trimesh by far, and trimesh adds no unlit material
(benchmarks/export_libraries.py, benchmarks/RESULTS.md).
"""

from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from papl_mapper import __version__
from papl_mapper.map import Map

from .scene import TRAJECTORY_RGB, ExportOptions, ExportScene, prepare

POINTS, LINES, LINE_STRIP, TRIANGLES = 0, 1, 3, 4
FLOAT, UNSIGNED_INT = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
# (x, y, z) in the map's +Z-up world -> glTF's +Y-up: x stays, y_gltf = z, z_gltf = -y
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def to_y_up(xyz: np.ndarray) -> np.ndarray:
    """(K, 3) float32 positions in glTF's +Y-up frame from +Z-up world positions."""
    out = np.empty((len(xyz), 3), np.float32)
    out[:, 0] = xyz[:, 0]
    out[:, 1] = xyz[:, 2]
    out[:, 2] = -xyz[:, 1]
    return out


def column_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column min and max of an (N, k) array, fast for tall arrays (min(axis=0) walks row by row)."""
    n, k = a.shape
    if n == 0:
        return np.zeros(k, a.dtype), np.zeros(k, a.dtype)
    rows = 1024
    bulk = (n // rows) * rows
    parts_lo, parts_hi = [a[bulk:]] if bulk < n else [], [a[bulk:]] if bulk < n else []
    if bulk:
        wide = a[:bulk].reshape(-1, rows * k)  # rows of 1024 records: reduce across them, then within
        parts_lo.append(wide.min(axis=0).reshape(rows, k))
        parts_hi.append(wide.max(axis=0).reshape(rows, k))
    return np.vstack(parts_lo).min(axis=0), np.vstack(parts_hi).max(axis=0)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB 0..255 -> linear 0..1 (glTF colour factors and COLOR_0 are linear)."""
    c = np.asarray(rgb, np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@dataclass
class GltfBuilder:
    """Accumulates one binary buffer, accessors, meshes, materials and nodes; emits .gltf or .glb bytes."""

    chunks: list[bytes] = field(default_factory=list)
    offset: int = 0
    doc: dict[str, Any] = field(
        default_factory=lambda: {
            "bufferViews": [],
            "accessors": [],
            "meshes": [],
            "materials": [],
            "nodes": [],
        }
    )
    used_extensions: set[str] = field(default_factory=set)

    def add_accessor(self, array: np.ndarray, kind: str, target: int, with_bounds: bool) -> int:
        """Append a tightly packed float32 or uint32 array as its own buffer view and accessor."""
        data = np.ascontiguousarray(array)
        raw = memoryview(data).cast("B")  # no copy: the array's bytes are joined once, in finish()
        self.chunks.append(raw)
        view = {"buffer": 0, "byteOffset": self.offset, "byteLength": raw.nbytes, "target": target}
        self.offset += raw.nbytes  # 4-byte components only, so every view stays 4-byte aligned
        self.doc["bufferViews"].append(view)
        comp = FLOAT if data.dtype == np.float32 else UNSIGNED_INT
        acc: dict[str, Any] = {
            "bufferView": len(self.doc["bufferViews"]) - 1,
            "componentType": comp,
            "count": len(data),
            "type": kind,
        }
        if with_bounds:
            lo, hi = column_bounds(data.reshape(len(data), -1))
            acc["min"], acc["max"] = [float(v) for v in lo], [float(v) for v in hi]
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def add_material(
        self, name: str, rgb: tuple[int, int, int] | None, unlit: bool = True, **extra: Any
    ) -> int:
        factor = [*srgb_to_linear(rgb).tolist(), 1.0] if rgb is not None else [1.0, 1.0, 1.0, 1.0]
        mat: dict[str, Any] = {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": factor,
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            **extra,
        }
        if unlit:
            mat["extensions"] = {"KHR_materials_unlit": {}}
            self.used_extensions.add("KHR_materials_unlit")
        if rgb is not None:
            mat["extras"] = {"color_srgb": [int(c) for c in rgb]}
        self.doc["materials"].append(mat)
        return len(self.doc["materials"]) - 1

    def add_node(
        self,
        name: str,
        mode: int,
        positions_yup: np.ndarray,
        material: int,
        *,
        indices: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        extras: dict[str, Any] | None = None,
    ) -> int:
        """One node holding one mesh with one primitive; returns the node index."""
        attrs = {
            "POSITION": self.add_accessor(
                positions_yup.astype(np.float32, copy=False), "VEC3", ARRAY_BUFFER, True
            )
        }
        if normals is not None:
            attrs["NORMAL"] = self.add_accessor(
                normals.astype(np.float32, copy=False), "VEC3", ARRAY_BUFFER, False
            )
        if colors is not None:
            attrs["COLOR_0"] = self.add_accessor(
                colors.astype(np.float32, copy=False), "VEC3", ARRAY_BUFFER, False
            )
        prim: dict[str, Any] = {"attributes": attrs, "mode": mode, "material": material}
        if indices is not None:
            flat = indices.astype(np.uint32, copy=False).ravel()
            prim["indices"] = self.add_accessor(flat, "SCALAR", ELEMENT_ARRAY_BUFFER, False)
        self.doc["meshes"].append({"name": name, "primitives": [prim]})
        node: dict[str, Any] = {"name": name, "mesh": len(self.doc["meshes"]) - 1}
        if extras:
            node["extras"] = extras
        self.doc["nodes"].append(node)
        return len(self.doc["nodes"]) - 1

    def finish(self, root_name: str, extras: dict[str, Any], binary: bool) -> bytes:
        doc = {k: v for k, v in self.doc.items() if v}
        children = list(range(len(self.doc["nodes"])))
        doc.setdefault("nodes", []).append(
            {"name": root_name, "extras": extras, **({"children": children} if children else {})}
        )
        doc["scenes"] = [{"name": root_name, "nodes": [len(doc["nodes"]) - 1]}]
        doc["scene"] = 0
        doc["asset"] = {"version": "2.0", "generator": f"papl-mapper {__version__}", "extras": extras}
        if self.used_extensions:
            doc["extensionsUsed"] = sorted(self.used_extensions)
        n_bin = self.offset
        if n_bin:
            doc["buffers"] = [{"byteLength": n_bin}]
            if not binary:
                blob = base64.b64encode(b"".join(self.chunks)).decode()
                doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + blob
        text = json.dumps(doc, separators=(",", ":")).encode()
        if not binary:
            return text
        text += b" " * (-len(text) % 4)
        out = [None, struct.pack("<I4s", len(text), b"JSON"), text]
        if n_bin:
            out += [struct.pack("<I4s", n_bin, b"BIN\x00"), *self.chunks]
        total = 12 + 8 + len(text) + (8 + n_bin if n_bin else 0)
        out[0] = struct.pack("<4sII", b"glTF", 2, total)
        return b"".join(out)  # the one copy of the binary data


def scene_extras(scene: ExportScene) -> dict[str, Any]:
    """Units, axes and the frame note carried in the file's `extras`."""
    axes = [
        {**a, "direction_gltf": [float(v) for v in Z_UP_TO_Y_UP @ np.asarray(a["direction"])]}
        for a in scene.axis_info
    ]
    return {
        "units": scene.units,
        "meters_per_unit": scene.meters_per_unit,
        "scale": scene.scale_note,
        "source_up_axis": "+Z (converted to glTF +Y up: x, z, -y)",
        "axes": axes,
        "generator": "papl-mapper",
    }


def scene_to_gltf(scene: ExportScene, binary: bool) -> bytes:
    b = GltfBuilder()
    for g in scene.segment_groups():
        if g.key == "trajectory":
            continue  # written below as one LINE_STRIP
        extras: dict[str, Any] = {"group": g.key, "segments": len(g.ids), "color_srgb": list(g.rgb)}
        if g.axis_index >= 0:
            extras |= {"axis_index": g.axis_index, "direction": g.direction_w.tolist()}
        mat = b.add_material(g.name, g.rgb)
        b.add_node(g.name, LINES, to_y_up(g.segments_w.reshape(-1, 3)), mat, extras=extras)
    if len(scene.trajectory_w) >= 2:
        mat = b.add_material("trajectory", TRAJECTORY_RGB)
        b.add_node(
            "trajectory",
            LINE_STRIP,
            to_y_up(scene.trajectory_w),
            mat,
            extras={"keyframes": len(scene.trajectory_w)},
        )
    if len(scene.points_xyz):
        mat = b.add_material("points", None)
        b.add_node(
            "points", POINTS, to_y_up(scene.points_xyz), mat, colors=srgb_to_linear(scene.points_rgb),
            extras={"points": len(scene.points_xyz)},
        )  # fmt: skip
    return b.finish("papl_map", scene_extras(scene), binary)


def export_glb(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as one binary glTF (.glb)."""
    return scene_to_gltf(prepare(m, options or ExportOptions()), binary=True)


def export_gltf(m: Map, options: ExportOptions | None = None) -> bytes:
    """The map as one .gltf JSON file with its buffer embedded as a data URI (no side files)."""
    return scene_to_gltf(prepare(m, options or ExportOptions()), binary=False)


FORMATS = {".glb": export_glb, ".gltf": export_gltf}
