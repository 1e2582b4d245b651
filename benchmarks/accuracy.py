"""Accuracy of `papl-map run` on the synthetic scenes, every ablation variant, two noise levels.

For each scene and image-noise level a walkthrough is rendered (cached under --cache), the
frontend runs once per frontend setting (vertical prior / VP refinement variants differ there),
and the mapping stage runs once per variant. Prints one table (ATE after Sim(3) as % of the path,
frames with a pose, line recall at 1% of the scene diagonal against all of the ground truth and
against the part of it the recording shows ("rec vis", papl_mapper/eval/visibility.py), precision at
1%, vertical axis error, run time) and writes benchmarks/results/accuracy.json.

    .venv/bin/python benchmarks/accuracy.py                       # everything (long)
    .venv/bin/python benchmarks/accuracy.py --scenes corridor --seconds 8 --variants full,points-only
    .venv/bin/python benchmarks/accuracy.py --scenes corridor --seconds 35 --noise 1 \
        --variants full,no-revisit --out benchmarks/results/accuracy_loop.json   # one whole loop
    .venv/bin/python benchmarks/accuracy.py --source frames --seeds 0,1,2 --variants full,points-only \
        --out benchmarks/results/accuracy_frames.json   # the same renders' lossless PNG frames

`--source frames` renders each case once more with its PNG frames (the MP4 of that render is the same
file) and maps the frames: the difference to `--source video` is the video codec's share of the error.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
from pathlib import Path

import numpy as np
from machine import git_commit

from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.frontend import FrontendStats, open_recording, process, read_camera_file
from papl_mapper.pipelines.config import PRESETS, RunConfig
from papl_mapper.pipelines.run import frame_trajectory, map_tracks
from papl_mapper.synth import SynthConfig, generate
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import write_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "accuracy.json"
FRONTEND_KEYS = ("frontend.",)


def _commit() -> str:
    return git_commit()


def cached_render(
    cache: Path, scene: str, noise: float, seconds: float, seed: int = 0, frames: bool = False
) -> Path:
    """The cached render of one case; with `frames` a separate render that also holds its PNG frames."""
    name = f"{scene}_noise{noise:g}_{seconds:g}s{f'_seed{seed}' if seed else ''}{'_frames' if frames else ''}"
    folder = cache / name
    if not (folder / ("frames" if frames else "video.mp4")).exists():
        cfg = SynthConfig(scene=scene, seconds=seconds, noise_sigma=noise, seed=seed, write_frames=frames)
        generate(cfg, folder)
    return folder


def _tracks(folder: Path, overrides: list[str], source: str) -> tuple[Tracks, float]:
    """Frontend tracks of a recording for the frontend part of a variant (cached on disk); `source` is
    "video" (the MP4) or "frames" (the lossless PNG frames of the same render)."""
    fe = [o for o in overrides if o.startswith(FRONTEND_KEYS)]
    tag = "_".join(fe).replace("=", "-").replace(".", "-") or "default"
    path = folder / f"tracks_{tag}{'_frames' if source == 'frames' else ''}.npz"
    if path.exists():
        return Tracks.load(path), float("nan")
    cfg = load_config(RunConfig, None, fe)
    if source == "frames":  # the render's own frame times, as the MP4 carries them
        rec = open_recording(folder / "frames", timestamps=folder / "timestamps.txt")
    else:
        rec = open_recording(folder / "video.mp4")
    t0 = time.perf_counter()
    tracks = process(rec, read_camera_file(folder / "camera.json"), cfg.frontend, stats=FrontendStats())
    dt = time.perf_counter() - t0
    tracks.save(path)
    return tracks, dt


def _f(v: float | None, width: int, digits: int) -> str:
    """A number for the table; '-' where it is undefined (e.g. line precision without lines)."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "-".rjust(width)
    return f"{v:{width}.{digits}f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="corridor,atlanta,garage")
    ap.add_argument("--noise", default="0,3", help="image noise sigmas (grey levels)")
    ap.add_argument("--variants", default=",".join(PRESETS))
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_accuracy"))
    ap.add_argument("--out", type=Path, default=OUT, help="results JSON")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--seeds", default="0", help="walk seeds per scene (the walk and the noise differ)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, every variant")
    ap.add_argument(
        "--source",
        choices=("video", "frames"),
        default="video",
        help="map the render's MP4 (default) or its lossless PNG frames: the codec's share of the error",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    rows = []
    header = (
        f"{'scene':9} {'noise':>5} {'variant':19} {'ATE %path':>9} {'posed':>7} {'recall':>6} "
        f"{'rec vis':>7} {'prec':>6} {'vert deg':>8} {'map s':>6}"
    )
    print(header)
    print("-" * len(header))
    cases = [
        (scene, noise, seed)
        for seed in (int(v) for v in args.seeds.split(","))
        for scene in args.scenes.split(",")
        for noise in (float(n) for n in args.noise.split(","))
    ]
    for scene, noise, seed in cases:
        folder = cached_render(args.cache, scene, noise, args.seconds, seed, frames=args.source == "frames")
        label = f"{scene}#{seed}" if seed else scene
        for variant in args.variants.split(","):
            overrides = PRESETS[variant] + args.set
            row = {"scene": scene, "noise": noise, "seed": seed, "variant": variant}
            try:
                tracks, fe_s = _tracks(folder, overrides, args.source)
                cfg = load_config(RunConfig, None, overrides)
                t0 = time.perf_counter()
                m, _ = map_tracks(tracks, cfg)
                traj = frame_trajectory(tracks, m, cfg)
                row["map_s"] = time.perf_counter() - t0
                row["frontend_s"] = fe_s
                tum = folder / f"traj_{variant}.tum"
                write_tum(tum, traj)
                ev = evaluate(folder, m, tum)
                row.update(
                    ate_rel_path=ev.ate_rmse_rel_path,
                    ate_rmse=ev.ate_rmse,
                    posed_fraction=ev.n_matched_poses / len(tracks),
                    line_recall_1pct=ev.line_recall.get("1%", float("nan")),
                    line_recall_visible_1pct=ev.line_recall_visible.get("1%", float("nan")),
                    gt_visible_fraction=ev.gt_visible_fraction,
                    line_precision_1pct=ev.line_precision.get("1%", float("nan")),
                    vertical_err_deg=float(ev.axis_errors_deg[0])
                    if len(ev.axis_errors_deg)
                    else float("nan"),
                    n_axes=len(m.axes),
                    lines=len(m.lines),
                )
            except Exception as exc:  # noqa: BLE001 - a failed variant is a row of the table, not the end
                row["error"] = f"{type(exc).__name__}: {exc}"
            rows.append(row)
            if "error" in row:
                print(f"{label:9} {noise:5g} {variant:19} failed: {row['error'][:80]}")
            else:
                print(
                    f"{label:9} {noise:5g} {variant:19} {_f(100 * row['ate_rel_path'], 9, 3)} "
                    f"{_f(100 * row['posed_fraction'], 6, 1)}% {_f(row['line_recall_1pct'], 6, 3)} "
                    f"{_f(row['line_recall_visible_1pct'], 7, 3)} {_f(row['line_precision_1pct'], 6, 3)} "
                    f"{_f(row['vertical_err_deg'], 8, 2)} "
                    f"{_f(row['map_s'], 6, 1)}"
                )
    if not args.no_write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps(
                {
                    "benchmark": "accuracy",
                    "seconds_per_recording": args.seconds,
                    "source": args.source,
                    "rows": rows,
                    "machine": {
                        "nproc": os.cpu_count(),
                        "loadavg_1m_at_end": round(os.getloadavg()[0], 2),
                        "python": platform.python_version(),
                        "numpy": np.__version__,
                    },
                    "commit": _commit(),
                },
                indent=1,
                default=float,
            )
        )
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
