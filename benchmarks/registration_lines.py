"""ATE with and without line tracks in the registration's pose refinement (mapping.track_lines).

Each variant is a set of config overrides of the whole mapping job on the cached 10 s scenes of
benchmarks/accuracy.py (run that first: it synthesises them and caches their frontend tracks), so every
variant maps the same tracks. Besides the whole job's ATE (all frames, after the full BA), the table
gives the ATE of the registration's keyframe poses alone (`reg ATE`, Sim(3)-aligned to the ground truth
before any global BA), which is where the line term acts.

The garage's ATE swings between runs under any change (its U-turn either keeps the scale or not), so
`--perturb-scenes` also runs each variant there under threshold changes that should not matter
(PERTURBATIONS) and the summary gives the median and range over them.

    .venv/bin/python benchmarks/registration_lines.py --scenes garage0,garage3,corridor0,corridor3,\
        atlanta0,atlanta3 --variants default,lines --perturb-scenes garage0,garage3   # the results file
    .venv/bin/python benchmarks/registration_lines.py --scenes garage0 --variants default,lines
Writes benchmarks/results/registration_lines.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
from machine import machine_info

from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.eval.trajectory import associate
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.mapping import incremental
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.run import frame_trajectory, map_tracks
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import read_tum, write_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "registration_lines.json"
CACHE = Path("/tmp/papl_accuracy")
SCENES = {f"{s}{n}": f"{s}_noise{n}_10s" for s in ("garage", "corridor", "atlanta") for n in (0, 3)}
VARIANTS = {
    "default": [],
    "lines": ["mapping.track_lines.enabled=true"],
    "lines-weak": ["mapping.track_lines.enabled=true", "mapping.track_lines.below_inliers=100"],
    "lines-1deg": [
        "mapping.track_lines.enabled=true",
        "mapping.track_lines.triangulation.min_plane_angle_deg=1",
    ],
}
"""Variant -> overrides: as shipped, line tracks on in every frame, only where points are weak, ..."""
PERTURBATIONS = {
    "base": [],
    "ransac1.9": ["mapping.pnp.ransac_threshold_px=1.9"],
    "ransac2.1": ["mapping.pnp.ransac_threshold_px=2.1"],
    "reproj2.8": ["mapping.max_reprojection_px=2.8"],
    "reproj3.2": ["mapping.max_reprojection_px=3.2"],
}
"""Threshold changes that should not matter: on scenes named by --perturb-scenes every variant also runs
under each, so a difference can be judged against the spread they give (the garage swings 0.3-7%)."""


def _registration_ate_pct(folder: Path, tracks: Tracks, T_cw: dict[int, np.ndarray]) -> float:
    """ATE (% of the ground-truth path) of registered keyframe centres after a Sim(3) fit."""
    gt = read_tum(folder / "gt" / "trajectory.tum")
    frames = np.array(sorted(T_cw), np.int64)
    if len(frames) < 3:
        return float("nan")
    i, j = associate(tracks.timestamp[frames], gt.timestamps, 0.01)
    est = np.array([-T_cw[int(f)][:3, :3].T @ T_cw[int(f)][:3, 3] for f in frames[i]])
    ref = gt.positions[j]
    sim = umeyama(est, ref)
    err = np.linalg.norm(sim.apply(est) - ref, axis=1)
    return float(100 * np.sqrt(np.mean(err**2)) / gt.path_length())


class _RegistrationSpy:
    """Keeps the last Registration register_keyframes returned (the benchmark's only hook)."""

    def __init__(self) -> None:
        self.reg = None
        self._orig = incremental.register_keyframes

    def __enter__(self) -> _RegistrationSpy:
        def spy(*a, **kw):
            self.reg = self._orig(*a, **kw)
            return self.reg

        import papl_mapper.pipelines.run as run

        self._run = run
        run.register_keyframes = spy
        return self

    def __exit__(self, *exc) -> None:
        self._run.register_keyframes = self._orig


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    info = machine_info()
    info["loadavg_1m_at_write"] = round(os.getloadavg()[0], 2)
    path.write_text(json.dumps({"machine": info, "variants": VARIANTS, "rows": rows}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--variants", default="default,lines")
    ap.add_argument("--set", action="append", default=[], help="extra override for every variant")
    ap.add_argument("--cache", type=Path, default=CACHE, help="benchmarks/accuracy.py's scene folder")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--perturb-scenes", default="", help="scenes also run under every PERTURBATIONS entry")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    tum = Path(f"/tmp/registration_lines_bench_{os.getpid()}.tum")
    rows = []
    print(
        f"{'scene':10s} {'variant':13s} {'perturb':10s} {'ATE %path':>9s} {'reg ATE %':>9s} "
        f"{'rpe rot':>8s} {'posed':>7s} {'map s':>6s}"
    )
    for name in args.scenes.split(","):
        folder = args.cache / SCENES[name]
        if not (folder / "tracks_default.npz").exists():
            print(
                f"{name}: {folder / 'tracks_default.npz'} missing (run benchmarks/accuracy.py first), skipped"
            )
            continue
        perturb = list(PERTURBATIONS) if name in args.perturb_scenes.split(",") else ["base"]
        for variant, pert in ((v, p) for p in perturb for v in args.variants.split(",")):
            tracks = Tracks.load(folder / "tracks_default.npz")  # fresh: loop closure renames tracks
            overrides = VARIANTS[variant] + PERTURBATIONS[pert] + args.set
            cfg = load_config(RunConfig, None, overrides)
            t0 = time.perf_counter()
            with _RegistrationSpy() as spy:
                m, _ = map_tracks(tracks, cfg)
            write_tum(tum, frame_trajectory(tracks, m, cfg))
            wall = time.perf_counter() - t0
            ev = evaluate(folder, m, tum)
            row = {
                "scene": name,
                "variant": variant,
                "perturbation": pert,
                "overrides": overrides,
                "ate_pct_path": round(100 * ev.ate_rmse_rel_path, 4),
                "registration_ate_pct_path": round(_registration_ate_pct(folder, tracks, spy.reg.T_cw), 4),
                "rpe_rot_deg": round(ev.rpe_rot_deg, 4),
                "posed": ev.n_matched_poses,
                "frames": len(tracks),
                "keyframes_registered": len(spy.reg.frames),
                "map_s": round(wall, 1),
                "loadavg_1m": round(os.getloadavg()[0], 2),
            }
            rows.append(row)
            print(
                f"{name:10s} {variant:13s} {pert:10s} {row['ate_pct_path']:9.3f} "
                f"{row['registration_ate_pct_path']:9.3f} {row['rpe_rot_deg']:8.4f} "
                f"{row['posed']:3d}/{row['frames']:3d} {wall:6.1f}",
                flush=True,
            )
            _write(args.out, rows)  # after every map: an interrupted run keeps its rows
    tum.unlink(missing_ok=True)
    _summary(rows)
    print(f"wrote {args.out}")


def _summary(rows: list[dict]) -> None:
    """Median and range of the ATE over the perturbations, per scene and variant (where there are several)."""
    keys = sorted({(r["scene"], r["variant"]) for r in rows})
    for scene, variant in keys:
        ate = [r["ate_pct_path"] for r in rows if (r["scene"], r["variant"]) == (scene, variant)]
        if len(ate) > 1:
            print(
                f"{scene:10s} {variant:13s} ATE over {len(ate)} perturbations: median {np.median(ate):.3f}%, "
                f"range {min(ate):.3f}-{max(ate):.3f}%"
            )


if __name__ == "__main__":
    main()
