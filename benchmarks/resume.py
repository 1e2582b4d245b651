"""Stage checkpoints of `papl-map run` on a recording (default: the bundled demo): their size and write
time, and the time a `--resume` saves after a real Ctrl-C (SIGINT) in the full BA.

Four `papl-map run` processes, each timed from start to exit:
  fresh        a run from scratch, every checkpoint written;
  interrupted  a run from scratch that gets SIGINT shortly after its log says the full BA starts;
  resumed      `--resume` of the interrupted run (continues after the points BA);
  tracks only  `--resume` with only the frontend checkpoint, as `--resume` did before stage checkpoints.
The resumed map is compared with the fresh one. Other processes on the machine disturb the times;
the times of one table come from the same invocation.

    .venv/bin/python benchmarks/resume.py [--recording samples/demo] [--work /tmp/resume_demo]
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import ROOT, machine_info

from papl_mapper.map import Map

OUT = ROOT / "benchmarks" / "results" / "resume.json"
PAPL_MAP = Path(sys.executable).parent / "papl-map"
FULL_BA_STARTS = "BA (points + lines): culled"  # logged just before the full BA's first iteration


def papl_map(
    recording: Path, out: Path, resume: bool, sigint_after: float | None = None
) -> tuple[float, int, str]:
    """Run `papl-map -q run` into `out`; with `sigint_after`, send SIGINT that many seconds after the
    log says the full BA starts. Returns (wall seconds, exit code, stderr)."""
    args = [str(PAPL_MAP), "-q", "run", str(recording / "video.mp4"), "--out", str(out)]
    args += ["--camera", str(recording / "camera.json")] + (["--resume"] if resume else [])
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if sigint_after is not None:
        log = out / ".checkpoint" / "log.txt"
        while proc.poll() is None and not (log.exists() and FULL_BA_STARTS in log.read_text()):
            time.sleep(0.01)
        time.sleep(sigint_after)
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate()
    return time.perf_counter() - t0, proc.returncode, err.strip()


def max_pose_diff(a: Path, b: Path) -> float:
    ma, mb = Map.load(a / "map.papl"), Map.load(b / "map.papl")
    if not np.array_equal(ma.keyframes.ids, mb.keyframes.ids):
        return float("inf")
    return float(np.abs(ma.keyframes.T_wc - mb.keyframes.T_wc).max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", type=Path, default=ROOT / "samples" / "demo")
    ap.add_argument("--work", type=Path, default=Path("/tmp/resume_demo"))
    ap.add_argument("--sigint-after", type=float, default=0.5, help="seconds after the full BA starts")
    args = ap.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    runs = {name: args.work / name for name in ("fresh", "interrupted", "tracks_only")}
    for folder in runs.values():
        folder.mkdir(parents=True)

    print("fresh run ...", flush=True)
    t_fresh, code, err = papl_map(args.recording, runs["fresh"], resume=False)
    assert code == 0, err
    summary = json.loads((runs["fresh"] / "summary.json").read_text())
    written = summary["checkpoints_written"]
    timings = summary["timings_s"]

    print("interrupted run ...", flush=True)
    t_interrupted, interrupted_code, message = papl_map(
        args.recording, runs["interrupted"], False, args.sigint_after
    )
    print(f"  exit {interrupted_code}: {message}")
    before = {p.name: p.read_bytes() for p in runs["interrupted"].iterdir() if p.is_file()}

    print("resumed run ...", flush=True)
    t_resumed, code, err = papl_map(args.recording, runs["interrupted"], resume=True)
    assert code == 0, err
    resumed = json.loads((runs["interrupted"] / "summary.json").read_text())["resumed"]

    print("resume with only the frontend checkpoint ...", flush=True)
    frontend = next((runs["fresh"] / ".checkpoint").glob("frontend-*"))
    shutil.copytree(frontend, runs["tracks_only"] / ".checkpoint" / frontend.name)
    t_tracks_only, code, err = papl_map(args.recording, runs["tracks_only"], resume=True)
    assert code == 0, err

    stage_rows = [
        {
            "stage": stage,
            "checkpoint_MiB": round(w["bytes"] / 2**20, 3),
            "write_s": w["write_s"],
            "stage_s": timings.get(stage),  # ba_full: both full BAs (before and after the axis update)
        }
        for stage, w in written.items()
    ]
    total_run_s = sum(timings.values())
    figures = {
        "checkpoints_total_MiB": round(sum(w["bytes"] for w in written.values()) / 2**20, 3),
        "checkpoints_write_total_s": round(sum(w["write_s"] for w in written.values()), 4),
        "checkpoints_write_share_of_stage_time_pct": round(
            100 * sum(w["write_s"] for w in written.values()) / total_run_s, 2
        ),
        "fresh_run_s": round(t_fresh, 2),
        "interrupted_run_s": round(t_interrupted, 2),
        "interrupted_exit_code": interrupted_code,
        "interrupt_message": message,
        "resumed_from": resumed["stage"] if resumed else None,
        "resumed_run_s": round(t_resumed, 2),
        "tracks_only_resume_s": round(t_tracks_only, 2),
        "saved_vs_tracks_only_s": round(t_tracks_only - t_resumed, 2),
        "saved_vs_fresh_s": round(t_fresh - t_resumed, 2),
        "resumed_vs_fresh_max_pose_diff": max_pose_diff(runs["fresh"], runs["interrupted"]),
        "interrupted_left_no_outputs": not any(n in before for n in ("map.papl", "summary.json")),
    }
    print()
    print(f"{'stage':<14}{'checkpoint MiB':>16}{'write s':>10}{'stage s':>10}")
    for r in stage_rows:
        print(f"{r['stage']:<14}{r['checkpoint_MiB']:>16.3f}{r['write_s']:>10.4f}{r['stage_s'] or 0:>10.3f}")
    print()
    width = max(len(k) for k in figures)
    for k, v in figures.items():
        print(f"{k:<{width}}  {v}")
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(
        json.dumps(
            {
                "benchmark": "resume",
                "recording": str(args.recording),
                "machine": machine_info(),
                "stages": stage_rows,
                "stage_timings_fresh_s": timings,
                **figures,
            },
            indent=1,
        )
    )
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
