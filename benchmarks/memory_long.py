"""Peak memory and wall time per stage of the whole job on a long 1280x720 recording, with and without
redundant keyframe culling (issue #5: a 5-minute 720p recording under 4 GB).

Each (length, variant) runs `papl_mapper.pipelines.run.run` in a fresh child process, so its peak
resident set size (getrusage ru_maxrss) is that job's alone; the child also records the peak so far
after every stage. The `cull` variants turn on redundant keyframe culling (`cull.enabled`). With
`--reuse-frontend` a later variant of the same length resumes from the first one's frontend
checkpoint, so its peak leaves out the frontend (the table says so). Make the recording first, e.g.

    papl-map synth corridor --out /tmp/corr720_5min --width 1280 --height 720 --seconds 300 \
        --supersample 1 --noise 1

Usage: python benchmarks/memory_long.py --recording /tmp/corr720_5min --ends 60,300 --variants cull,base
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine_info  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "memory_long.json"
CULL_VARIANTS = {
    "cull": [],
    "cull_lines1": ["cull.min_line_views=1"],
    "cull_views5": ["cull.min_other_views=5"],
}
"""Variant name -> RunConfig overrides with culling on; "base" runs the defaults."""


def _rss_mib() -> tuple[float, float]:
    """(current, peak) resident set size of this process in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        cur = pages * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        cur = float("nan")
    return cur, peak


def child(args: argparse.Namespace) -> None:
    """One job in this process: run, record peak memory per stage, evaluate against the ground truth."""
    import contextlib

    import papl_mapper.pipelines.run as pipeline
    from papl_mapper.config import load_config
    from papl_mapper.eval import evaluate
    from papl_mapper.pipelines.config import RunConfig, with_input

    memory: dict[str, dict[str, float]] = {}
    stage = pipeline._Timer.stage

    @contextlib.contextmanager
    def stage_with_memory(self, name):  # noqa: ANN001, ANN202
        with stage(self, name):
            yield
        cur, peak = _rss_mib()
        memory[name] = {"rss_after_MiB": round(cur, 1), "peak_so_far_MiB": round(peak, 1)}

    pipeline._Timer.stage = stage_with_memory
    overrides = ["cull.enabled=true", *CULL_VARIANTS[args.variant]] if args.variant in CULL_VARIANTS else []
    rec = Path(args.recording)
    t0 = time.perf_counter()
    res = pipeline.run(
        rec / "video.mp4",
        args.out,
        with_input(load_config(RunConfig, None, overrides), camera=rec / "camera.json", end_s=args.end),
        resume=args.resume,
    )
    wall = time.perf_counter() - t0
    _, peak = _rss_mib()
    s = res.summary.to_dict()
    ev = evaluate(rec, res.map, Path(args.out) / "trajectory.tum")
    out = {
        "variant": args.variant,
        "seconds": args.end,
        "frames": s["recording"]["frames"],
        "frontend_reused": bool(args.resume),
        "peak_rss_MiB": round(peak, 1),
        "wall_s": round(wall, 1),
        "timings_s": s["timings_s"],
        "memory_after_stage": memory,
        "keyframes": int(s["counts"]["keyframes"]),
        "frontend_keyframes": int(s.get("frontend", {}).get("keyframes", -1)),
        "keyframes_registered": int(s.get("keyframes_registered", -1)),
        "culling": s.get("culling") if args.variant in CULL_VARIANTS else None,
        "points": int(s["counts"]["points"]),
        "lines": int(s["counts"]["lines"]),
        "frames_lost": int(s["frames_lost"]),
        "ate_rmse_rel_path_pct": round(100 * ev.ate_rmse_rel_path, 4),
        "line_recall_1pct": round(ev.line_recall.get("1%", float("nan")), 4),
        "line_precision_1pct": round(ev.line_precision.get("1%", float("nan")), 4),
    }
    (Path(args.out) / "bench.json").write_text(json.dumps(out, indent=1))


def _table(rows: list[dict]) -> str:
    head = (
        f"{'length':>7} {'variant':>7} {'frames':>6} {'kf':>5} {'peak GiB':>8} {'wall s':>7} "
        f"{'frontend':>8} {'registr':>7} {'ba_pts':>6} {'lines':>6} {'ba_full':>7} "
        f"{'ATE %path':>9} {'recall':>6} {'prec':>6}"
    )
    out = [head]
    for r in rows:
        t = r["timings_s"]
        fe = "reused" if r["frontend_reused"] else f"{t.get('frontend', 0):.0f}"
        out.append(
            f"{r['seconds']:>6.0f}s {r['variant']:>7} {r['frames']:>6} {r['keyframes']:>5} "
            f"{r['peak_rss_MiB'] / 1024:>8.2f} {r['wall_s']:>7.0f} {fe:>8} {t.get('registration', 0):>7.0f} "
            f"{t.get('ba_points', 0):>6.0f} {t.get('lines', 0):>6.0f} {t.get('ba_full', 0):>7.0f} "
            f"{r['ate_rmse_rel_path_pct']:>9.3f} {r['line_recall_1pct']:>6.3f} "
            f"{r['line_precision_1pct']:>6.3f}"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--recording", default="/tmp/corr720_5min", help="synth folder: video.mp4, camera.json, gt/"
    )
    ap.add_argument("--ends", default="60,300", help="comma-separated lengths in seconds from the start")
    ap.add_argument("--variants", default="cull,base", help="base, or culled: " + ", ".join(CULL_VARIANTS))
    ap.add_argument("--work", default="/tmp/memory_long", help="folder for the runs' outputs")
    ap.add_argument("--reuse-frontend", action="store_true", help="later variants resume the first's tracks")
    ap.add_argument("--frontend-from", help="run folder whose frontend checkpoint every variant resumes")
    ap.add_argument("--results", default=str(RESULTS), help="JSON to write (runs of other lengths are kept)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--variant", help=argparse.SUPPRESS)
    ap.add_argument("--end", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--resume", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    rec = Path(args.recording)
    if not (rec / "video.mp4").exists():
        sys.exit(f"{rec / 'video.mp4'} not found: make it with papl-map synth (see this script's docstring)")
    results = Path(args.results)
    rows = []
    for end in [float(e) for e in args.ends.split(",")]:
        first_out = None
        for variant in args.variants.split(","):
            out = Path(args.work) / f"{int(end)}s_{variant}"
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir(parents=True)
            resume = False
            source = Path(args.frontend_from) if args.frontend_from else None
            if args.reuse_frontend and first_out is not None:
                source = first_out
            if source is not None:
                # only the frontend's tracks: later stages depend on the variant
                stages = shutil.ignore_patterns("registration-*", "ba_points-*", "ba_full-*", "log.txt")
                shutil.copytree(source / ".checkpoint", out / ".checkpoint", ignore=stages)
                resume = True
            cmd = [sys.executable, __file__, "--child", "--recording", str(rec), "--variant", variant]
            cmd += ["--end", str(end), "--out", str(out)] + (["--resume"] if resume else [])
            print(f"running {end:.0f} s, {variant} ...", flush=True)
            with open(out / "bench.log", "w") as log:
                subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
            row = json.loads((out / "bench.json").read_text())
            row["recording"] = str(rec)
            rows.append(row)
            first_out = first_out or out
            print(_table([row]).splitlines()[1], flush=True)
    print(_table(rows))
    # read just before writing: runs of other lengths or variants may have finished meanwhile
    previous = json.loads(results.read_text()).get("runs", []) if results.exists() else []
    done = {(x["recording"], x["seconds"], x["variant"]) for x in rows}
    keep = [r for r in previous if (r.get("recording"), r["seconds"], r["variant"]) not in done]
    results.parent.mkdir(exist_ok=True)
    results.write_text(
        json.dumps(
            {
                "benchmark": "memory_long",
                "machine": machine_info(),
                "goal_peak_rss_GiB": 4.0,
                "runs": sorted(keep + rows, key=lambda r: (r["seconds"], r["variant"])),
            },
            indent=1,
        )
    )
    print(f"wrote {results}")


if __name__ == "__main__":
    main()
