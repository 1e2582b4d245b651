"""Benchmark: hand-written PLY and GLB writers against the libraries that could replace them.

On one map of 1,000,000 segments and 1,000,000 points (benchmarks/export.py's synthetic map), each
writer encodes the same prepared scene to bytes in memory, best of `--repeat` runs; "product" in the
JSON says which writer the exporters use (a library where it is not slower):

- PLY: hand-written (the records of `exporters.ply.ply_elements` and a header, joined), plyfile
  (`exporters.ply.scene_to_ply`: `PlyData.write` of those records), Open3D (`write_line_set` of the
  segments alone, to a temporary file, colours as doubles);
- ASCII PLY: hand-written (`scene_to_ply(ascii=True)`) and plyfile's text writer, on the same records;
- tubes PLY (a triangle mesh, 16 vertices and faces per segment): hand-written
  (`exporters.tubes.export_tubes_ply`,
  preparation included) and plyfile (the records of `tube_ply_elements`, building included);
- GLB: hand-written (`exporters.gltf.scene_to_gltf`), pygltflib (the same document and buffer through
  `GLTF2.from_dict` and `save_to_bytes`), trimesh (a `Path3D` of the segments with their colours,
  `export(file_type="glb")`; its time includes building the Path3D, which it needs).

A library is worth using where it is not slower; the exporters' docstrings cite this file's result.
Prints a table and writes benchmarks/results/export_libraries.json.
Usage: .venv/bin/python benchmarks/export_libraries.py [--segments N] [--points N] [--repeat K]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from machine import machine_info

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "export_libraries.json"
PRODUCT = {"ply": "plyfile", "ply_ascii": "hand_written", "tubes_ply": "hand_written", "glb": "hand_written"}
"""The writer the exporters use for each format."""


def best_of(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """(fastest wall seconds, the last result) of `repeat` calls."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def ply_writers(scene) -> dict[str, Callable[[], bytes]]:  # noqa: ANN001
    from papl_mapper.exporters.ply import ply_elements, scene_to_ply

    def hand_written_bytes() -> bytes:
        """The binary writer the exporter had before plyfile: header text, then the records' memory."""
        vertex, edge, comments = ply_elements(scene)
        header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
        header += [
            f"element vertex {len(vertex)}",
            "property float x",
            "property float y",
            "property float z",
        ]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        header += [f"element edge {len(edge)}", "property int vertex1", "property int vertex2"]
        header += ["property uchar red", "property uchar green", "property uchar blue", "end_header", ""]
        return b"".join(["\n".join(header).encode("ascii"), vertex.view(np.uint8), edge.view(np.uint8)])

    def open3d_bytes() -> bytes:
        import open3d as o3d

        segs = np.concatenate([g.segments_w for g in scene.segment_groups()])
        rgb = np.concatenate([np.broadcast_to(g.rgb, (len(g.ids), 3)) for g in scene.segment_groups()])
        ls = o3d.geometry.LineSet()
        ls.points = o3d.utility.Vector3dVector(segs.reshape(-1, 3))
        ls.lines = o3d.utility.Vector2iVector(np.arange(2 * len(segs), dtype=np.int32).reshape(-1, 2))
        ls.colors = o3d.utility.Vector3dVector(rgb / 255.0)
        with tempfile.TemporaryDirectory(prefix="papl-bench-o3d-") as tmp:
            path = os.path.join(tmp, "o3d.ply")
            o3d.io.write_line_set(path, ls, write_ascii=False)
            return Path(path).read_bytes()

    return {
        "hand_written": hand_written_bytes,
        "plyfile": lambda: scene_to_ply(scene),
        "open3d": open3d_bytes,
    }


def ply_ascii_writers(scene) -> dict[str, Callable[[], bytes]]:  # noqa: ANN001
    from plyfile import PlyData, PlyElement

    from papl_mapper.exporters.ply import ply_elements, scene_to_ply

    def plyfile_bytes() -> bytes:
        vertex, edge, comments = ply_elements(scene)
        data = PlyData(
            [PlyElement.describe(vertex, "vertex"), PlyElement.describe(edge, "edge")],
            text=True,
            comments=comments,
        )
        buf = io.BytesIO()
        data.write(buf)
        return buf.getvalue()

    return {"hand_written": lambda: scene_to_ply(scene, ascii=True), "plyfile": plyfile_bytes}


def tubes_ply_writers(m) -> dict[str, Callable[[], bytes]]:  # noqa: ANN001
    from plyfile import PlyData, PlyElement

    from papl_mapper.exporters.scene import ExportOptions, prepare
    from papl_mapper.exporters.tubes import export_tubes_ply, tube_ply_elements

    options = ExportOptions()
    scene = prepare(m, options)

    def plyfile_bytes() -> bytes:
        vertex, face, comments = tube_ply_elements(scene, options)
        faces = np.empty(len(face), [("vertex_indices", "<i4", (3,))])
        faces["vertex_indices"] = face["vertex_indices"]
        data = PlyData(
            [
                PlyElement.describe(vertex, "vertex"),
                PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"}),
            ],
            byte_order="<",
            comments=comments,
        )
        buf = io.BytesIO()
        data.write(buf)
        return buf.getvalue()

    return {"hand_written": lambda: export_tubes_ply(m, options), "plyfile": plyfile_bytes}


def glb_writers(scene) -> dict[str, Callable[[], bytes]]:  # noqa: ANN001
    from papl_mapper.exporters import gltf as G

    def pygltflib_bytes() -> bytes:
        import pygltflib

        builder = G.GltfBuilder()
        _fill(builder, scene)
        doc = {k: v for k, v in builder.doc.items() if v}
        children = list(range(len(doc.get("nodes", []))))
        extras = G.scene_extras(scene)
        doc.setdefault("nodes", []).append({"name": "papl_map", "extras": extras, "children": children})
        doc["scenes"] = [{"name": "papl_map", "nodes": [len(doc["nodes"]) - 1]}]
        doc["scene"] = 0
        doc["asset"] = {"version": "2.0", "generator": "papl-mapper", "extras": extras}
        doc["extensionsUsed"] = sorted(builder.used_extensions)
        doc["buffers"] = [{"byteLength": builder.offset}]
        gltf = pygltflib.GLTF2.from_dict(doc)
        gltf.set_binary_blob(b"".join(builder.chunks))
        out = gltf.save_to_bytes()
        return b"".join(out) if isinstance(out, list) else out

    def trimesh_bytes() -> bytes:
        import trimesh
        from trimesh.path.entities import Line

        groups = [g for g in scene.segment_groups() if g.key != "trajectory"]
        segs = np.concatenate([g.segments_w for g in groups])
        rgb = np.concatenate([np.broadcast_to(g.rgb, (len(g.ids), 3)) for g in groups])
        idx = np.arange(2 * len(segs)).reshape(-1, 2)
        entities = [Line(points=i) for i in idx]
        path = trimesh.path.Path3D(entities=entities, vertices=segs.reshape(-1, 3), colors=rgb, process=False)
        return trimesh.Scene(path).export(file_type="glb")

    return {
        "hand_written": lambda: G.scene_to_gltf(scene, binary=True),
        "pygltflib": pygltflib_bytes,
        "trimesh": trimesh_bytes,
    }


def _fill(b, scene) -> None:  # noqa: ANN001
    """The nodes `scene_to_gltf` adds, into builder `b` (the segments, trajectory and points)."""
    from papl_mapper.exporters import gltf as G

    for g in scene.segment_groups():
        if g.key == "trajectory":
            continue
        b.add_node(g.name, G.LINES, G.to_y_up(g.segments_w.reshape(-1, 3)), b.add_material(g.name, g.rgb))
    if len(scene.trajectory_w) >= 2:
        mat = b.add_material("trajectory", G.TRAJECTORY_RGB)
        b.add_node("trajectory", G.LINE_STRIP, G.to_y_up(scene.trajectory_w), mat)
    if len(scene.points_xyz):
        mat = b.add_material("points", None)
        b.add_node(
            "points", G.POINTS, G.to_y_up(scene.points_xyz), mat, colors=G.srgb_to_linear(scene.points_rgb)
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segments", type=int, default=1_000_000)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--skip", default="", help="comma-separated writers or formats to leave out, e.g. trimesh"
    )
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from export import synthetic_map

    from papl_mapper.exporters.scene import ExportOptions, prepare

    skip = {s for s in args.skip.split(",") if s}
    m = synthetic_map(args.segments, args.points)
    scene = prepare(m, ExportOptions())
    load = [round(os.getloadavg()[0], 2)]
    rows: dict[str, dict[str, dict]] = {}
    print(f"map: {args.segments:,} segments, {args.points:,} points; best of {args.repeat}")
    print(f"{'format':<10} {'writer':<10} {'seconds':>8} {'size MB':>8}  note")
    formats = (
        ("ply", ply_writers(scene)),
        ("ply_ascii", ply_ascii_writers(scene)),
        ("tubes_ply", tubes_ply_writers(m)),
        ("glb", glb_writers(scene)),
    )
    for fmt, writers in formats:
        if fmt in skip:
            continue
        rows[fmt] = {}
        ref = None
        for name, fn in writers.items():
            if name in skip:
                continue
            repeat = args.repeat if name != "trimesh" else 1
            try:
                seconds, data = best_of(fn, repeat)
            except Exception as exc:  # a library that cannot write this map is a result too
                rows[fmt][name] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
                print(f"{fmt:<10} {name:<10} failed: {rows[fmt][name]['error']}")
                continue
            ref = data if name == "hand_written" else ref
            row = {"seconds": round(seconds, 3), "size_mb": round(len(data) / 2**20, 2), "runs": repeat}
            if name != "hand_written" and ref is not None:
                row["same_bytes_as_hand_written"] = data == ref
                row["seconds_over_hand_written"] = round(seconds / rows[fmt]["hand_written"]["seconds"], 2)
            rows[fmt][name] = row
            note = f"{row.get('seconds_over_hand_written', 1.0):.2f}x hand-written" + (
                ", same bytes" if row.get("same_bytes_as_hand_written") else ""
            )
            print(f"{fmt:<10} {name:<10} {row['seconds']:>8.3f} {row['size_mb']:>8.2f}  {note}")
    load.append(round(os.getloadavg()[0], 2))
    result = {
        "benchmark": "export_libraries",
        "segments": args.segments,
        "points": args.points,
        "writers": rows,
        "product": PRODUCT,
        "notes": "seconds: best of the runs (trimesh: one run), encoding a prepared scene to bytes in memory "
        "(Open3D through a temporary file, its only way); 2 cores shared with other jobs",
        "load_average_1min_start_end": load,
        "machine": machine_info(),
    }
    OUT.write_text(json.dumps(result, indent=1) + "\n")
    print("wrote", OUT)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
