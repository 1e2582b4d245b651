"""The frontend's point tracks against ground truth, for frontend settings compared in one run.

The frontend runs alone (`frontend.process`, as `papl-map run` calls it) on synthetic renders and on
the real sequences in ../shared/data/real, once per setting, and its point tracks are measured with
the ground-truth poses (no mapping involved, so nothing chaotic downstream hides a change):

- reprojection: every track with 3 or more observations and 2 degrees of parallax is triangulated
  from all its observations with the ground-truth poses (midpoint); the median distance of its
  observations to their projections, and the share of tracks with a view more than 3 px off;
- epipolar: each pair of consecutive frames' tracks against the ground-truth epipolar geometry, the
  median Sampson distance (px) over the pairs' medians; it needs no triangulation, so it also holds
  where ground-truth poses are not precise enough for the first measure (the real sequences).

Synthetic cases are rendered once into --cache: the corridor and Atlanta walks with image noise 2
alone and with each hand-held effect (exposure changes, motion blur, both). Prints one table and
writes benchmarks/results/track_accuracy.json.

    .venv/bin/python benchmarks/track_accuracy.py
    .venv/bin/python benchmarks/track_accuracy.py --cases corridor/exposure --seeds 0,1,2 \\
        --setting default: --setting exposure-compensation:frontend.flow.exposure_gate=0.0025
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from machine import machine_info

from papl_mapper.config import load_config
from papl_mapper.eval.trajectory import associate
from papl_mapper.frontend import process
from papl_mapper.frontend.camera import camera_for_recording
from papl_mapper.frontend.video import open_recording
from papl_mapper.geometry.se3 import skew
from papl_mapper.geometry.triangulation import triangulate_points
from papl_mapper.geometry.two_view import sampson_px
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.synth import SynthConfig, generate
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import read_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "track_accuracy.json"
REAL = ROOT.parent / "shared" / "data" / "real"
#: synthetic effects: SynthConfig fields on top of the walk (the hand-held variant is all of them)
EFFECTS = {
    "noise-2": {"noise_sigma": 2.0},
    "exposure": {"noise_sigma": 2.0, "exposure_jitter": 0.3},
    "blur": {"noise_sigma": 2.0, "motion_blur": 0.5},
    "hand-held": {"noise_sigma": 2.0, "exposure_jitter": 0.3, "motion_blur": 0.5},
}
SCENES = ("corridor", "atlanta")
DEFAULT_SETTINGS = ["default:", "exposure-compensation:frontend.flow.exposure_gate=0.0025"]
MIN_VIEWS = 3
MIN_PARALLAX_DEG = 2.0
FAR_PX = 3.0


def _render(cache: Path, scene: str, effect: str, seed: int, seconds: float) -> Path:
    folder = cache / f"{scene}_{effect}_seed{seed}"
    if not (folder / "gt" / "trajectory.tum").exists():
        generate(SynthConfig(scene=scene, seconds=seconds, seed=seed, **EFFECTS[effect]), folder)
    return folder


def _real_cases() -> dict[str, tuple[Path, Path, Path]]:
    """name -> (images folder, camera file, ground truth) of every sequence in ../shared/data/real."""
    out = {}
    if REAL.is_dir():
        for folder in sorted(p for p in REAL.iterdir() if (p / "images").is_dir()):
            cams = [folder / c for c in ("camera.json", "calib.txt") if (folder / c).is_file()]
            if cams and (folder / "groundtruth.tum").is_file():
                out[folder.name] = (folder / "images", cams[0], folder / "groundtruth.tum")
    return out


def _gt_poses(tracks: Tracks, gt_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth T_wc (F, 4, 4) of the tracks' frames by timestamp, and which frames have one."""
    gt = read_tum(gt_path)
    i_est, i_gt = associate(tracks.timestamp, gt.timestamps, 0.01)
    T = np.tile(np.eye(4), (len(tracks), 1, 1))
    has = np.zeros(len(tracks), bool)
    T[i_est], has[i_est] = gt.T_wc[i_gt], True
    return T, has


def measure(tracks: Tracks, T_wc: np.ndarray, has_gt: np.ndarray) -> dict:
    """Reprojection and epipolar errors of the point tracks under the ground-truth poses (see module doc)."""
    K = tracks.camera.K
    keep = has_gt[tracks.point_frame]
    frame, track, uv = tracks.point_frame[keep], tracks.point_track[keep], tracks.point_uv[keep]
    ids, inv = np.unique(track, return_inverse=True)
    X, ok = triangulate_points(inv, T_wc[frame], K, uv, len(ids), min_angle_deg=MIN_PARALLAX_DEG)
    ok &= np.bincount(inv, minlength=len(ids)) >= MIN_VIEWS
    T_cw = np.linalg.inv(T_wc[frame])
    Xc = np.einsum("kij,kj->ki", T_cw[:, :3, :3], X[inv]) + T_cw[:, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = Xc[:, :2] / Xc[:, 2:3] @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
    err = np.linalg.norm(proj - uv, axis=1)
    used = ok[inv] & np.isfinite(err)
    worst = np.zeros(len(ids))
    np.maximum.at(worst, inv[used], err[used])
    # consecutive frames: Sampson distance of the tracks both hold to the ground-truth epipolar geometry
    pair_medians = []
    for f in range(len(tracks) - 1):
        if not (has_gt[f] and has_gt[f + 1]):
            continue
        a, b = tracks.point_frame == f, tracks.point_frame == f + 1
        common, ia, ib = np.intersect1d(tracks.point_track[a], tracks.point_track[b], return_indices=True)
        T21 = np.linalg.inv(T_wc[f + 1]) @ T_wc[f]
        if len(common) < 8 or np.linalg.norm(T21[:3, 3]) < 1e-9:
            continue
        E = skew(T21[:3, 3]) @ T21[:3, :3]
        pair_medians.append(
            float(np.median(sampson_px(E, tracks.point_uv[a][ia], tracks.point_uv[b][ib], K)))
        )
    return {
        "tracks_measured": int(ok.sum()),
        "reprojection_median_px": float(np.median(err[used])) if used.any() else float("nan"),
        "tracks_over_3px": float(np.mean(worst[ok] > FAR_PX)) if ok.any() else float("nan"),
        "epipolar_median_px": float(np.median(pair_medians)) if pair_medians else float("nan"),
        "frame_pairs": len(pair_medians),
    }


def _settings(specs: list[str]) -> list[tuple[str, list[str]]]:
    out = []
    for spec in specs:
        name, _, rest = spec.partition(":")
        out.append((name, [s for s in rest.split(",") if s]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    all_cases = [f"{s}/{e}" for s in SCENES for e in EFFECTS] + list(_real_cases())
    ap.add_argument(
        "--cases", default=",".join(all_cases), help="scene/effect renders and real sequence names"
    )
    ap.add_argument("--seeds", default="0", help="walk seeds of the synthetic cases")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the synthetic walks")
    ap.add_argument(
        "--setting",
        action="append",
        default=None,
        metavar="NAME:KEY=VALUE,...",
        help=f"a frontend setting to measure (repeatable; default {' and '.join(DEFAULT_SETTINGS)})",
    )
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_track_accuracy"))
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR, format="%(message)s")
    settings = _settings(args.setting or DEFAULT_SETTINGS)
    real = _real_cases()
    jobs = []
    for case in args.cases.split(","):
        if case in real:
            jobs.append((case, *real[case]))
            continue
        scene, effect = case.split("/")
        for seed in (int(s) for s in args.seeds.split(",")):
            folder = _render(args.cache, scene, effect, seed, args.seconds)
            gt_path = folder / "gt" / "trajectory.tum"
            jobs.append((f"{case}/seed{seed}", folder / "video.mp4", folder / "camera.json", gt_path))
    rows = []
    print(f"{'case':32} {'setting':26} {'tracks':>6} {'reproj px':>9} {'>3 px':>6} {'epipolar px':>11}")
    for name, source, camera_file, gt_path in jobs:
        for setting, sets in settings:
            cfg = load_config(RunConfig, None, sets)
            rec = open_recording(source)
            camera = camera_for_recording(camera_file, rec.width, rec.height).camera
            tracks = process(rec, camera, cfg.frontend, seed=cfg.seed)
            row = {
                "case": name,
                "setting": setting,
                "overrides": sets,
                **measure(tracks, *_gt_poses(tracks, gt_path)),
            }
            rows.append(row)
            print(
                f"{name:32} {setting:26} {row['tracks_measured']:6d} {row['reprojection_median_px']:9.3f} "
                f"{100 * row['tracks_over_3px']:5.1f}% {row['epipolar_median_px']:11.4f}"
            )
    if not args.no_write:
        args.out.write_text(
            json.dumps({"benchmark": "track_accuracy", "rows": rows, "machine": machine_info()}, indent=1)
        )
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
