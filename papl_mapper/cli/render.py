"""`papl-map render MAP --out DIR`: off-screen PNG previews of a map coloured by axis, with a legend."""

from __future__ import annotations

import argparse
from pathlib import Path

from papl_mapper.cli.progress import progress_bar
from papl_mapper.config import load_config
from papl_mapper.map import Map, map_file


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render off-screen PNG previews of a map", description=__doc__)
    p.add_argument("map", help="a .papl map file, or a run folder holding map.papl")
    p.add_argument("--out", required=True, help="folder for <view>.png (created if missing)")
    p.add_argument("--views", help="comma-separated views (isometric,top,front,side); default all four")
    p.add_argument("--size", help="WIDTHxHEIGHT in pixels, default 1600x1200")
    p.add_argument("--theme", choices=("white", "dark"), help="background theme (default white)")
    p.add_argument("--frusta", action="store_true", help="draw a camera frustum at every keyframe")
    p.add_argument("--no-points", action="store_true", help="leave the points out")
    p.add_argument("--no-trajectory", action="store_true", help="leave the trajectory out")
    p.add_argument("--turntable", choices=("gif", "mp4"), help="also write a turntable animation")
    p.add_argument("--config", type=Path, help="TOML file with preview options (PreviewOptions fields)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an option")
    p.set_defaults(func=run)


def _overrides(args: argparse.Namespace) -> list[str]:
    out = []
    if args.views:
        out.append(f"views={args.views}")
    if args.size:
        w, _, h = args.size.lower().partition("x")
        out += [f"width={w}", f"height={h}"]
    if args.theme:
        out.append(f"theme={args.theme}")
    if args.frusta:
        out.append("show_frusta=true")
    if args.no_points:
        out.append("show_points=false")
    if args.no_trajectory:
        out.append("show_trajectory=false")
    if args.turntable:
        out.append(f"turntable={args.turntable}")
    return out + list(args.set)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.gui.preview import PreviewOptions, render_views

    options = load_config(PreviewOptions, args.config, _overrides(args))
    src = Path(args.map)
    m = Map.load(map_file(src))
    if not options.title:
        options.title = src.resolve().name if src.is_dir() else src.stem
    with progress_bar("rendering") as cb:
        res = render_views(m, args.out, options, progress=cb)
    for note in res.notes:
        print(f"note: {note}")
    for p in res.paths + ([res.turntable] if res.turntable else []):
        print(p)
    return 0
