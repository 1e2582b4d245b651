"""`papl-map eval --gt DIR RESULT [--json OUT]`: compare a run or map with ground truth.

RESULT is a run folder (map.papl with trajectory.tum or keyframes.tum) or a .papl map (its
keyframes are the trajectory). Prints ATE/RPE after Sim(3) alignment, line recall and precision
at thresholds relative to the scene size, and axis errors; --json writes every number.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from papl_mapper.config import load_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="compare a run folder or map with ground truth (ATE, RPE, line recall/precision, axes)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("result", type=Path, help="a run folder (map.papl, trajectory.tum) or a .papl map file")
    p.add_argument(
        "--gt",
        type=Path,
        required=True,
        metavar="DIR",
        help="ground-truth folder (GT or GT/gt with trajectory.tum, ...)",
    )
    p.add_argument("--json", type=Path, metavar="OUT", help="also write every metric to this JSON file")
    p.add_argument(
        "--trajectory", type=Path, metavar="TUM", help="use this TUM file as the estimated trajectory"
    )
    p.add_argument("--config", type=Path, help="TOML file with eval options (EvalConfig fields)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an option")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.eval import EvalConfig, evaluate, resolve_result, write_json

    config = load_config(EvalConfig, args.config, args.set)
    m, tum = resolve_result(args.result)
    res = evaluate(args.gt, m, args.trajectory or tum, config)
    print(res.table())
    if args.json:
        print(f"wrote {write_json(res, args.json)}")
    return 0
