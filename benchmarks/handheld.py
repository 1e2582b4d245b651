"""The whole job on the hand-held renders: corridor and Atlanta walks with noise 2, exposure changes and
motion blur (`benchmarks/track_accuracy.py`'s "hand-held" effect, the same cached renders), several
seeds, each row mapped with every variant in one run.

A variant is a preset (`full`, `points-only`, `orthonormal-lines`, ...) or `KEY=VALUE` config
overrides joined by `+` on top of the full method (e.g. `reverse.enabled=false`). Each run is the
whole job (`pipelines.run.run`, as `papl-map run` does). Prints one table (ATE after Sim(3) as % of
the path, frames posed, run time) and writes benchmarks/results/handheld.json.

    .venv/bin/python benchmarks/handheld.py
    .venv/bin/python benchmarks/handheld.py --scenes corridor --seeds 2 --variants full,reverse.enabled=false
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

from machine import machine_info
from track_accuracy import _render

from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.map import Map
from papl_mapper.pipelines.config import PRESETS, RunConfig
from papl_mapper.pipelines.run import run

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "handheld.json"


def _overrides(variant: str) -> list[str]:
    """Config overrides of a variant: a preset's, or KEY=VALUE pairs joined by '+' on the full method."""
    if variant in PRESETS:
        return list(PRESETS[variant])
    return [*PRESETS["full"], *variant.split("+")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="corridor,atlanta")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--variants", default="full,reverse.enabled=false,points-only,orthonormal-lines")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_track_accuracy"))
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(message)s")
    variants = args.variants.split(",")
    rows = []
    print(f"{'scene':9} {'seed':>4} {'variant':28} {'ATE %path':>9} {'posed':>7} {'map s':>6}")
    for scene in args.scenes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            folder = _render(args.cache, scene, "hand-held", seed, args.seconds)
            for variant in variants:
                out = args.cache / "runs" / f"{scene}_{seed}_{variant.replace('=', '-')}"
                shutil.rmtree(out, ignore_errors=True)
                cfg = load_config(
                    RunConfig, None, [*_overrides(variant), f"input.camera={folder / 'camera.json'}"]
                )
                t0 = time.perf_counter()
                run(folder / "video.mp4", out, cfg)
                seconds = time.perf_counter() - t0
                ev = evaluate(folder, Map.load(out / "map.papl"), out / "trajectory.tum")
                summary = json.loads((out / "summary.json").read_text())
                row = {
                    "scene": scene,
                    "seed": seed,
                    "variant": variant,
                    "ate_rel_path": ev.ate_rmse_rel_path,
                    "posed": ev.n_matched_poses,
                    "map_s": seconds,
                    "reverse_kept": (summary.get("reverse_check") or {}).get("kept"),
                }
                rows.append(row)
                print(
                    f"{scene:9} {seed:4d} {variant:28} {100 * row['ate_rel_path']:9.3f} {row['posed']:7d} "
                    f"{seconds:6.1f}  {row['reverse_kept'] or ''}"
                )
    print()
    for variant in variants:
        total = sum(r["ate_rel_path"] for r in rows if r["variant"] == variant)
        print(f"{variant:28} summed ATE {100 * total:7.3f} % of path")
    if not args.no_write:
        args.out.write_text(
            json.dumps(
                {"benchmark": "handheld", "rows": rows, "machine": machine_info()}, indent=1, default=float
            )
        )
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
