"""ATE with and without each term of the tracking pose refinement (points / lines / vanishing directions).

Two places use PnP: (a) registration of frames during incremental mapping (`incremental._pnp`) and
(b) the pose of every non-keyframe after the global BA (`pipelines.run.frame_poses`, the all-frames
trajectory ATE is measured on). Both are owned elsewhere, so this script monkeypatches them with the
hooks described in mapping/pose_refine.py and measures:

- b variants on one map per scene: none (OpenCV LM, today), points (our Huber LM, points only),
  lines, dirs, all;
- a variant (directions in registration, world directions from the registered keyframes), with b
  none and b all.

    .venv/bin/python benchmarks/pose_refine.py                      # the six cached 10 s scenes
    .venv/bin/python benchmarks/pose_refine.py --scenes atlanta0 --no-a
Writes benchmarks/results/pose_refine.json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import time
from pathlib import Path

import numpy as np
from machine import machine_info
from papl_mapper.pipelines import run as run_mod
from papl_mapper.pipelines.config import RunConfig

from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.eval.trajectory import Trajectory, write_tum
from papl_mapper.map import Map
from papl_mapper.mapping import incremental as inc
from papl_mapper.mapping.pose_refine import (
    FrameRefiner,
    PoseRefineConfig,
    RegistrationDirections,
    frame_directions,
    refine_pose,
)
from papl_mapper.mapping.tracking import track_pnp
from papl_mapper.tracks import Tracks

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "pose_refine.json"
SCENES = {
    f"{s}{n}": (Path(f"/tmp/papl_accuracy/{s}_noise{n}_10s"), Path(f"/tmp/s10/{s}{n}.npz"))
    for s in ("corridor", "atlanta", "garage")
    for n in (0, 3)
}
B_VARIANTS = {
    "none": None,
    "points": PoseRefineConfig(lines=False, directions=False),
    "lines": PoseRefineConfig(lines=True, directions=False),
    "dirs": PoseRefineConfig(lines=False, directions=True),
    "all": PoseRefineConfig(lines=True, directions=True),
}


def frame_poses_refined(
    tracks: Tracks, m: Map, cfg: RunConfig, refine: PoseRefineConfig | None, timing: list[float]
) -> dict[int, np.ndarray]:
    """`pipelines.run.frame_poses` plus the hook (b): the lines marked `# hook` are the change."""
    K = tracks.camera.K
    kf = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    pid = m.points.ids
    refiner = FrameRefiner.from_map(tracks, m, refine) if refine is not None else None  # hook
    out: dict[int, np.ndarray] = {}
    last = None
    for f in range(len(tracks)):
        if f in kf:
            T_wc = kf[f]
        else:
            ids, uv = tracks.points_in(f)
            idx = np.minimum(np.searchsorted(pid, ids), max(len(pid) - 1, 0))
            known = pid[idx] == ids if len(pid) else np.zeros(len(ids), bool)
            guess = np.linalg.inv(last) if last is not None else None
            res = track_pnp(m.points.xyz[idx[known]], uv[known], K, guess, cfg.mapping.pnp)
            if not res.ok:
                continue
            T_cw = res.T_cw
            if refiner is not None:  # hook
                t0 = time.perf_counter()
                X, x = m.points.xyz[idx[known]][res.inliers], uv[known][res.inliers]  # hook
                T_cw, _ = refiner.refine(f, res.T_cw, X, x)  # hook
                timing.append(time.perf_counter() - t0)
            T_wc = np.linalg.inv(T_cw)
        last = out[f] = T_wc
    return out


def make_pnp_with_directions(timing: list[float], vertical_only: bool = False):
    """`incremental._pnp` plus the hook (a): world directions from the registered keyframes."""
    world_dirs: dict[int, RegistrationDirections] = {}

    def _pnp(tracks: Tracks, reg: inc.Registration, f: int, guess: np.ndarray, cfg: inc.IncrementalConfig):
        ids, uv = tracks.points_in(f)
        known = np.array([t in reg.points_w for t in ids.tolist()], bool)
        if known.sum() < cfg.pnp.min_inliers:
            return None, len(ids)
        X = np.stack([reg.points_w[int(t)] for t in ids[known]])
        if id(tracks) not in world_dirs:
            world_dirs[id(tracks)] = RegistrationDirections(tracks, vertical_only=vertical_only)  # hook
        dirs_w, sigma = world_dirs[id(tracks)](reg.T_cw)  # hook
        t0 = time.perf_counter()
        vp_c = frame_directions(tracks, f, vertical_only)  # hook
        K = tracks.camera.K
        res = track_pnp(
            X, uv[known], K, guess, cfg.pnp, dirs_w=dirs_w, dirs_c=vp_c, dirs_sigma_deg=sigma
        )  # hook
        timing.append(time.perf_counter() - t0)
        return res, len(ids)

    return _pnp


@contextlib.contextmanager
def patched(obj, name: str, value):
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


def _ate(folder: Path, tracks: Tracks, m: Map, poses: dict[int, np.ndarray], tmp: Path) -> dict:
    frames = np.array(sorted(poses), np.int64)
    T = np.array([poses[int(f)] for f in frames]).reshape(-1, 4, 4)
    write_tum(tmp, Trajectory(tracks.timestamp[frames].astype(np.float64), T, "trajectory"))
    ev = evaluate(folder, m, tmp)
    return {
        "ate_pct_path": 100 * ev.ate_rmse_rel_path,
        "rpe_rot_deg": ev.rpe_rot_deg,
        "posed": ev.n_matched_poses,
        "frames": len(tracks),
    }


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


def _write(path: Path, overrides: list[str], rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": machine_info(), "overrides": overrides, "rows": rows}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--no-a", action="store_true", help="skip the registration hook (a)")
    ap.add_argument("--skip-base", action="store_true", help="skip the map without hook (a)")
    ap.add_argument("--a-sigmas", default="0.5", help="direction sigmas (deg) of (a) to try, comma-separated")
    ap.add_argument("--a-below", default="0", help="directions_below_inliers values of (a) to try")
    ap.add_argument("--a-vertical", action="store_true", help="also try (a) with the vertical direction only")
    ap.add_argument("--b", default=",".join(B_VARIANTS), help="b variants on the baseline map")
    ap.add_argument("--set", nargs="*", default=[], help="config overrides key=value")
    ap.add_argument("--seeds", default="0", help="PnP RANSAC seeds (mapping.pnp.seed): run-to-run spread")
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
    tmp = Path("/tmp/pose_refine_bench.tum")
    rows = []
    jobs = [(n, int(sd)) for sd in args.seeds.split(",") for n in args.scenes.split(",")]
    for name, seed in jobs:
        folder, tpath = SCENES[name]
        if not tpath.exists():
            print(f"{name}: {tpath} missing, skipped")
            continue
        tracks = Tracks.load(tpath)
        base_set = [*args.set, f"mapping.pnp.seed={seed}"]
        cfg = load_config(RunConfig, None, base_set)
        regs: list[tuple[str, bool | None, float, int]] = [] if args.skip_base else [("a:none", None, 0.0, 0)]
        if not args.no_a:
            for sig in (float(x) for x in args.a_sigmas.split(",")):
                for below in (int(x) for x in args.a_below.split(",")):
                    tag = f"{sig:g}" + (f"<{below}" if below > 0 else "")
                    regs.append((f"a:dirs{tag}", False, sig, below))
                    if args.a_vertical:
                        regs.append((f"a:vert{tag}", True, sig, below))
        for a_name, vertical, sigma, below in regs:
            t_a: list[float] = []
            ctx = (
                patched(inc, "_pnp", make_pnp_with_directions(t_a, vertical))
                if vertical is not None
                else None
            )
            a_over = [
                f"mapping.pnp.refine.direction_sigma_deg={sigma}",
                f"mapping.pnp.refine.directions_below_inliers={below}",
            ]
            a_cfg = load_config(RunConfig, None, [*base_set, *a_over])
            t0 = time.perf_counter()
            with ctx or contextlib.nullcontext():
                m, _ = run_mod.map_tracks(tracks, a_cfg if vertical is not None else cfg)
            t_map = time.perf_counter() - t0
            b_names = args.b.split(",") if seed == 0 else ["none"]
            b_list = {k: B_VARIANTS[k] for k in b_names}
            for b_name, rc in b_list.items():
                t_b: list[float] = []
                poses = frame_poses_refined(tracks, m, cfg, rc, t_b)
                row = {
                    "scene": name,
                    "seed": seed,
                    "a": a_name,
                    "b": b_name,
                    **_ate(folder, tracks, m, poses, tmp),
                }
                row["map_s"] = round(t_map, 1)
                row["b_refine_ms_per_frame"] = 1e3 * float(np.mean(t_b)) if t_b else None
                row["a_pnp_ms_per_frame"] = 1e3 * float(np.mean(t_a)) if t_a else None
                rows.append(row)
                b_ms = f"{row['b_refine_ms_per_frame']:.2f}" if t_b else "-"
                a_ms = f"{row['a_pnp_ms_per_frame']:.2f}" if t_a else "-"
                print(
                    f"{name:10s} s{seed} {a_name:9s} b:{b_name:7s} ATE {row['ate_pct_path']:.3f}% "
                    f"rpe_rot {row['rpe_rot_deg']:.3f} deg posed {row['posed']}/{row['frames']} "
                    f"refine {b_ms} ms/frame, a-PnP {a_ms} ms/frame, map {t_map:.1f} s",
                    flush=True,
                )
            _write(args.out, args.set, rows)  # after every map: a long run interrupted keeps its rows
    _write(args.out, args.set, rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
