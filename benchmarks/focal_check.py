"""Focal-length check on real mapping runs: each recording mapped with its true camera and with the focal
length scaled (0.8, 1.2, 1.35 x), then `check_focal` on each map.

Prints a table and writes benchmarks/results/focal_check.json: used, estimated and true f (px), the
estimate's error against the truth (%), its relative sigma, the verdict (observable / warn) and the
seconds the check took. Maps are made with `papl-map run` into --work (reused when already there, so a
second run only re-checks).

    .venv/bin/python benchmarks/focal_check.py [--scenes demo,corridor,...] [--scales 1.0,0.8,1.2,1.35]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

from machine import ROOT, machine_info

from papl_mapper.backend.calibration import FocalCheckConfig, check_focal
from papl_mapper.map import Map

OUT = ROOT / "benchmarks" / "results" / "focal_check.json"
ACCURACY = Path("/tmp/papl_accuracy")  # benchmarks/accuracy.py's cached 10 s recordings
SCENES = {
    "demo": ROOT / "samples" / "demo",
    "corridor": ACCURACY / "corridor_noise0_10s",
    "atlanta": ACCURACY / "atlanta_noise0_10s",
    "garage": ACCURACY / "garage_noise0_10s",
}


def map_for(scene: str, folder: Path, scale: float, work: Path) -> tuple[Path, float, float]:
    """Map the recording with its camera's fx, fy times `scale` (reused if present); (map, f_true, run s)."""
    cam = json.loads((folder / "camera.json").read_text())
    f_true = (cam["fx"] * cam["fy"]) ** 0.5
    out = work / f"{scene}_x{scale:g}"
    if (out / "map.papl").exists():
        return out / "map.papl", f_true, float("nan")
    out.mkdir(parents=True, exist_ok=True)
    cam_file = out.with_name(out.name + "_camera.json")
    cam_file.write_text(json.dumps({**cam, "fx": cam["fx"] * scale, "fy": cam["fy"] * scale}))
    cmd = [str(Path(sys.executable).with_name("papl-map")), "-q", "run", str(folder / "video.mp4")]
    cmd += ["--camera", str(cam_file), "--out", str(out)]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    return out / "map.papl", f_true, time.perf_counter() - t


def _finite(v: object) -> object:
    """NaN and inf -> None, recursively (JSON has neither)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_finite(x) for x in v]
    return v


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--scales", default="1.0,0.8,1.2,1.35")
    ap.add_argument("--work", type=Path, default=Path("/tmp/focal_bench"), help="folder for the runs")
    args = ap.parse_args()
    config = FocalCheckConfig()
    rows = []
    for scene in args.scenes.split(","):
        folder = SCENES[scene]
        if not (folder / "video.mp4").exists():
            print(f"skipping {scene}: {folder} not found")
            continue
        for scale in [float(s) for s in args.scales.split(",")]:
            path, f_true, run_s = map_for(scene, folder, scale, args.work)
            m = Map.load(path)
            r = check_focal(m, config)
            rows.append(
                {
                    "scene": scene,
                    "focal_scale": scale,
                    "n_keyframes": len(m.keyframes),
                    "f_true_px": f_true,
                    "f_used_px": r.f_used,
                    "f_estimated_px": r.f_estimated,
                    "estimate_error_pct": 100 * (r.f_estimated / f_true - 1),
                    "rel_sigma_pct": 100 * r.rel_sigma,
                    "observable": r.observable,
                    "warn": r.warn,
                    "windows": r.n_windows,
                    "informative_windows": r.n_informative,
                    "check_s": r.time_s,
                    "mapping_run_s": run_s,
                    "message": r.message,
                }
            )
    head = f"{'scene':9} {'scale':>5} {'kf':>4} {'f used':>7} {'f est':>7} {'err%':>6} {'sig%':>5} "
    print(head + f"{'obs':>4} {'warn':>5} {'win':>6} {'check s':>8}")
    for r in rows:
        print(
            f"{r['scene']:9} {r['focal_scale']:5.2f} {r['n_keyframes']:4d} {r['f_used_px']:7.1f} "
            f"{r['f_estimated_px']:7.1f} {r['estimate_error_pct']:+6.1f} {r['rel_sigma_pct']:5.1f} "
            f"{'yes' if r['observable'] else 'no':>4} {'yes' if r['warn'] else 'no':>5} "
            f"{r['informative_windows']:>3}/{r['windows']:<2} {r['check_s']:8.1f}"
        )
    correct = [r for r in rows if r["focal_scale"] == 1.0]
    wrong = [r for r in rows if r["focal_scale"] != 1.0]
    result = {
        "what": "check_focal on maps made with the true and with scaled focal lengths",
        "config": vars(config),
        "false_warnings_with_true_f": sum(r["warn"] for r in correct),
        "runs_with_true_f": len(correct),
        "warnings_with_wrong_f": sum(r["warn"] for r in wrong),
        "runs_with_wrong_f": len(wrong),
        "rows": rows,
        "machine": machine_info(),
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(_finite(result), indent=1, allow_nan=False) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
