"""The job on the synthetic adversarial recordings: rotation-first start, dropped frames, a photo set,
a low-texture corridor, a camera that only turns in place, and a hand-held camera's motion blur,
exposure changes and noise.

Each case is rendered once (cached under --cache) with `papl-map synth --variant`, then mapped by
the whole job (`pipelines.run.run`, as `papl-map run` does) with the full model and points only.
Prints one table (frames posed, ATE after Sim(3) as % of the path, run time; for the rotation-only
recording whether it was recognised and the largest orientation error) and writes
benchmarks/results/adversarial.json.

    .venv/bin/python benchmarks/adversarial.py
    .venv/bin/python benchmarks/adversarial.py --cases photo-set --variants full
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
from machine import machine_info

from papl_mapper.config import load_config
from papl_mapper.errors import UnmappableError
from papl_mapper.eval import evaluate
from papl_mapper.geometry.se3 import rotation_angle_deg
from papl_mapper.map import Map
from papl_mapper.pipelines.config import PRESETS, RunConfig
from papl_mapper.pipelines.run import run
from papl_mapper.synth import SynthConfig, generate, with_variants
from papl_mapper.trajectory_io import read_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "adversarial.json"
CASES = {
    "rotation-start": {},
    "dropped-frames": {},
    "photo-set": {"seconds": 40.0},  # 40 photos at 1 Hz
    "low-texture": {},
    "rotation-only": {},
    "hand-held": {},
}


def _recording(cache: Path, case: str, seconds: float) -> Path:
    folder = cache / f"corridor_{case}"
    if not (folder / "gt" / "trajectory.tum").exists():
        cfg = with_variants(SynthConfig(scene="corridor", seconds=seconds, seed=0), case)
        generate(cfg, folder)
    return folder


def _source(folder: Path) -> Path:
    return folder / "video.mp4" if (folder / "video.mp4").exists() else folder / "frames"


def _orientation_error_deg(folder: Path, out: Path) -> float:
    """Largest error of the orientations relative to the first frame."""
    est, gt = read_tum(out / "trajectory.tum"), read_tum(folder / "gt" / "trajectory.tum")
    R_est = est.T_wc[0, :3, :3].T @ est.T_wc[:, :3, :3]
    R_gt = gt.T_wc[0, :3, :3].T @ gt.T_wc[: len(est), :3, :3]
    return float(np.max(rotation_angle_deg(R_est, R_gt)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--variants", default="full,points-only")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the video cases")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_adversarial"))
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, every variant")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(message)s")
    rows = []
    print(f"{'case':15} {'variant':12} {'posed':>9} {'ATE %path':>9} {'map s':>6}  note")
    for case in args.cases.split(","):
        folder = _recording(args.cache, case, CASES[case].get("seconds", args.seconds))
        n_frames = len(read_tum(folder / "gt" / "trajectory.tum"))
        for variant in args.variants.split(","):
            out = args.cache / "runs" / f"{case}_{variant}"
            shutil.rmtree(out, ignore_errors=True)
            row = {"case": case, "variant": variant, "frames": n_frames}
            cfg = load_config(
                RunConfig, None, [*PRESETS[variant], *args.set, f"input.camera={folder / 'camera.json'}"]
            )
            t0 = time.perf_counter()
            try:
                run(_source(folder), out, cfg)
                row["map_s"] = time.perf_counter() - t0
                ev = evaluate(folder, Map.load(out / "map.papl"), out / "trajectory.tum")
                row.update(posed=ev.n_matched_poses, ate_rel_path=ev.ate_rmse_rel_path, note="")
            except UnmappableError as exc:
                row["map_s"] = time.perf_counter() - t0
                row.update(posed=len(read_tum(out / "trajectory.tum")), ate_rel_path=float("nan"))
                row["note"] = str(exc).split(":")[0]
                if row["note"] == "rotation only":
                    row["orientation_err_deg"] = _orientation_error_deg(folder, out)
                    row["note"] += f", orientations within {row['orientation_err_deg']:.2f} deg"
            except Exception as exc:  # noqa: BLE001 - a failed case is a row of the table
                row.update(posed=0, ate_rel_path=float("nan"), map_s=float("nan"), note=f"{exc}"[:80])
            rows.append(row)
            print(
                f"{case:15} {variant:12} {row['posed']:4d}/{n_frames:<4d} {100 * row['ate_rel_path']:9.3f} "
                f"{row['map_s']:6.1f}  {row['note']}"
            )
    if not args.no_write:
        args.out.write_text(
            json.dumps(
                {"benchmark": "adversarial", "rows": rows, "machine": machine_info()}, indent=1, default=float
            )
        )
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
