"""ATE with and without each term of the tracking pose refinement (points / lines / vanishing directions).

PnP poses are refined in two places: (a) while frames are registered, with the world directions
the keyframes so far agree on (`mapping.pnp.refine.in_registration`), and (b) for every
non-keyframe after the global BA, against the map's axes (and lines with `refine.lines`). Each
variant below is a set of config overrides of the whole mapping job on the cached 10 s scenes of
benchmarks/accuracy.py (run that first: it synthesises them and caches their frontend tracks).

    .venv/bin/python benchmarks/pose_refine.py                      # every scene and variant
    .venv/bin/python benchmarks/pose_refine.py --scenes atlanta0 --variants none,default
    .venv/bin/python benchmarks/pose_refine.py --micro              # refine_pose vs OpenCV's LM
Writes benchmarks/results/pose_refine.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
from machine import machine_info

from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.mapping.pose_refine import refine_pose
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.run import frame_trajectory, map_tracks
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import write_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "pose_refine.json"
CACHE = Path("/tmp/papl_accuracy")
SCENES = {f"{s}{n}": f"{s}_noise{n}_10s" for s in ("corridor", "atlanta", "garage") for n in (0, 3)}
VARIANTS = {
    "none": ["mapping.pnp.refine.enabled=false"],
    "frames-only": ["mapping.pnp.refine.in_registration=false"],
    "default": [],
    "vertical-only": ["mapping.pnp.refine.vertical_only=true"],
    "with-lines": ["mapping.pnp.refine.lines=true"],
}
"""Variant -> overrides: no refinement (OpenCV's points-only LM), (b) only, (a)+(b) as shipped, ..."""


def micro_timing(repeats: int = 200) -> dict:
    """ms per call of refine_pose per term set vs OpenCV's solvePnPRefineLM, on one synthetic frame
    (200 points with 0.5 px noise, 40 lines, 3 directions), measured in the same process."""
    import cv2

    from papl_mapper.geometry.se3 import retract

    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-2, 2, (200, 2)), rng.uniform(3, 8, 200)])
    uv = X[:, :2] / X[:, 2:] * 500 + [319.5, 239.5] + rng.normal(0, 0.5, (200, 2))
    ends = np.concatenate([X[:40, None], X[:40, None] + np.eye(3)[rng.integers(0, 3, 40)][:, None]], 1)
    pe = ends @ K.T
    seg = (pe[..., :2] / pe[..., 2:]).reshape(-1, 4)
    T0 = retract(np.eye(4), np.array([0.003, -0.002, 0.002, 0.01, 0.0, -0.01]))
    dirs = np.eye(3)
    out = {}
    for name, kw in {
        "points": {},
        "points_lines": {"lines_w": ends, "line_xy": seg},
        "points_dirs": {"dirs_w": dirs, "dirs_c": dirs},
        "all": {"lines_w": ends, "line_xy": seg, "dirs_w": dirs, "dirs_c": dirs},
    }.items():
        t0 = time.perf_counter()
        for _ in range(repeats):
            refine_pose(T0, X, uv, K, **kw)
        out[f"refine_pose_{name}_ms"] = 1e3 * (time.perf_counter() - t0) / repeats
    rvec = cv2.Rodrigues(T0[:3, :3])[0]
    tvec = T0[:3, 3].reshape(3, 1).copy()
    t0 = time.perf_counter()
    for _ in range(repeats):
        cv2.solvePnPRefineLM(X, uv, K, None, rvec.copy(), tvec.copy())
    out["opencv_refine_lm_points_ms"] = 1e3 * (time.perf_counter() - t0) / repeats
    return out


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": machine_info(), "variants": VARIANTS, "rows": rows}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--cache", type=Path, default=CACHE, help="benchmarks/accuracy.py's scene folder")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--micro", action="store_true", help="only time refine_pose against OpenCV's LM")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.micro:
        timing = micro_timing()
        for k, v in timing.items():
            print(f"{k:32s} {v:8.3f}")
        path = args.out.with_name(args.out.stem + "_micro.json")
        path.write_text(json.dumps({"machine": machine_info(), "timing": timing}, indent=1))
        print(f"wrote {path}")
        return
    tum = Path("/tmp/pose_refine_bench.tum")
    rows = []
    for name in args.scenes.split(","):
        folder = args.cache / SCENES[name]
        if not (folder / "tracks_default.npz").exists():
            print(
                f"{name}: {folder / 'tracks_default.npz'} missing (run benchmarks/accuracy.py first), skipped"
            )
            continue
        for variant in args.variants.split(","):
            tracks = Tracks.load(folder / "tracks_default.npz")  # fresh: loop closure renames tracks
            cfg = load_config(RunConfig, None, VARIANTS[variant])
            t0 = time.perf_counter()
            m, _ = map_tracks(tracks, cfg)
            write_tum(tum, frame_trajectory(tracks, m, cfg))
            wall = time.perf_counter() - t0
            ev = evaluate(folder, m, tum)
            row = {
                "scene": name,
                "variant": variant,
                "ate_pct_path": round(100 * ev.ate_rmse_rel_path, 4),
                "rpe_rot_deg": round(ev.rpe_rot_deg, 4),
                "posed": ev.n_matched_poses,
                "frames": len(tracks),
                "map_s": round(wall, 1),
            }
            rows.append(row)
            print(
                f"{name:10s} {variant:13s} ATE {row['ate_pct_path']:.3f}% "
                f"rpe_rot {row['rpe_rot_deg']:.3f} deg posed {row['posed']}/{row['frames']} map {wall:.1f} s",
                flush=True,
            )
            _write(args.out, rows)  # after every map: an interrupted run keeps its rows
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
