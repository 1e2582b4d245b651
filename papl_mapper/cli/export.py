"""`papl-map export MAP OUT [OUT...]`: write a map to files whose suffixes name their formats.

Suffixes: .ply .glb .gltf .usda .usdc .usdz .dxf .obj .tubes.glb .tubes.ply .tum .kitti (.txt)
and .colmap (a folder of COLMAP text files). Each file is written to a temporary name and renamed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from papl_mapper.config import load_config
from papl_mapper.errors import OutputError
from papl_mapper.map import Map, map_file

MULTI_POLICY = (
    "Every OUT is checked before anything is written (known suffix, existing writable folder, and a "
    "name that is absent, a regular file, or a link to one: the link's target is written); one bad OUT "
    "writes nothing. A write that still fails (disk full) leaves that file as it was, the other outputs "
    "are written, and each failure is reported."
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a map to PLY, glTF, USD, DXF, OBJ, tubes, TUM/KITTI, COLMAP",
        description=__doc__,
        epilog=MULTI_POLICY,
    )
    p.add_argument("map", help="a .papl map file, or a run folder holding map.papl")
    p.add_argument("out", nargs="+", help="output files; each suffix picks the format")
    p.add_argument("--format", help="force one format for every output (a suffix such as ply or tubes.glb)")
    p.add_argument(
        "--parts",
        help="comma-separated parts: lines,points,trajectory,frusta (default lines,points,trajectory)",
    )
    p.add_argument("--min-obs", type=int, help="leave out lines with fewer observations than this")
    p.add_argument("--palette", help="axis palette: okabe-ito (default, colour-blind safe) or vivid")
    p.add_argument("--ascii", action="store_true", help="PLY: write ASCII instead of binary")
    p.add_argument("--tube-radius", type=float, help="tubes: radius as a fraction of the scene diagonal")
    p.add_argument("--config", type=Path, help="TOML file with export options (ExportOptions fields)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an option")
    p.set_defaults(func=run)


def _overrides(args: argparse.Namespace) -> list[str]:
    out = []
    if args.parts:
        out.append(f"parts={args.parts}")
    if args.min_obs is not None:
        out.append(f"min_observations={args.min_obs}")
    if args.palette:
        out.append(f"palette={args.palette}")
    if args.ascii:
        out.append("ascii=true")
    if args.tube_radius is not None:
        out.append(f"tube_radius={args.tube_radius}")
    return out + list(args.set)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.exporters import ExportOptions, check_target, export

    options = load_config(ExportOptions, args.config, _overrides(args))
    options.check()
    for out in args.out:  # refuse a bad target before any work (MULTI_POLICY)
        check_target(out, args.format)
    m = Map.load(map_file(args.map))
    failed = []
    for out in args.out:
        try:
            for path in export(m, out, options, format=args.format):
                print(path)
        except OutputError as exc:
            failed.append(str(exc))
    if failed:
        raise OutputError(f"{len(failed)} of {len(args.out)} outputs not written: {'; '.join(failed)}")
    return 0
