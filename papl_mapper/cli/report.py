"""`papl-map report RUN_DIR_OR_MAP [--gt DIR] [--out FILE]`: one self-contained HTML map report."""

from __future__ import annotations

import argparse
from pathlib import Path

from papl_mapper.config import load_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report", help="write a self-contained HTML report of a run or map", description=__doc__
    )
    p.add_argument("source", help="a run folder (map.papl, summary.json, ...) or a .papl map file")
    p.add_argument("--gt", type=Path, help="ground-truth folder (gt/trajectory.tum, gt/segments.txt, ...)")
    p.add_argument("--out", type=Path, help="output HTML file (default RUN_DIR/report.html or MAP.html)")
    p.add_argument("--no-previews", action="store_true", help="leave the 3D previews out")
    p.add_argument("--config", type=Path, help="TOML file with report options (ReportOptions fields)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an option")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.gui.report import ReportOptions, write_report

    overrides = list(args.set) + (["previews=false"] if args.no_previews else [])
    options = load_config(ReportOptions, args.config, overrides)
    src = Path(args.source)
    out = args.out or (src / "report.html" if src.is_dir() else src.with_suffix(".html"))
    print(write_report(src, out, args.gt, options))
    return 0
