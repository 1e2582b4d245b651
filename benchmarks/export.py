"""Benchmark: export a map of 1,000,000 segments and 1,000,000 points to every registered format.

Each format runs in a fresh subprocess that loads the map, then times `export()` (select, check,
encode, atomic write with fsync) and reads its peak resident memory (VmHWM from /proc/self/status)
before and after. Prints a table and writes benchmarks/results/export.json.
Goal: PLY, GLB and USDC each under 5 s and under 2 GB peak; DXF and OBJ are reported.
Usage: .venv/bin/python benchmarks/export.py [--segments N] [--points N] [--formats .ply,.glb]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOAL_S = 5.0
GOAL_PEAK_MB = 2048.0
GOAL_FORMATS = (".ply", ".glb", ".usdc")
# one suffix per format (aliases such as .tum.txt or .txt write the same bytes)
ALIASES = (".tum.txt", ".kitti.txt", ".txt")


def synthetic_map(n_segments: int, n_points: int, n_keyframes: int = 500, seed: int = 0):
    """Segments along three orthogonal axes (10 % unanchored) in a 50-unit box, points with two
    observations each, keyframes along a walk; every line observed once."""
    from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points

    rng = np.random.default_rng(seed)
    axes = Axes(np.eye(3)[[2, 0, 1]], vertical_index=0)
    lab = rng.integers(0, 3, n_segments)
    lab[rng.random(n_segments) < 0.1] = -1
    d = np.where(lab[:, None] >= 0, axes.directions[np.maximum(lab, 0)], rng.normal(size=(n_segments, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mid = rng.uniform(0, 50, (n_segments, 3))
    half = rng.uniform(0.1, 1.0, (n_segments, 1))
    ends = np.stack([mid - half * d, mid + half * d], axis=1)
    w = np.zeros((n_segments, 3))
    w[lab >= 0, lab[lab >= 0]] = 1.0
    state = np.where(lab >= 0, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8)
    T = np.repeat(np.eye(4)[None], n_keyframes, axis=0)
    T[:, :3, 3] = np.stack(
        [np.linspace(0, 50, n_keyframes), np.full(n_keyframes, 25.0), np.full(n_keyframes, 1.6)], 1
    )
    kf_ids = np.arange(n_keyframes, dtype=np.int64)
    kf = Keyframes(kf_ids, kf_ids * 5, kf_ids / 6.0, T)
    lids = np.arange(n_segments, dtype=np.int64)
    lines = Lines(
        lids, ends, w, state,
        np.where(lab >= 0, 0, -1).astype(np.int64), np.where(lab >= 0, 0.2, np.nan),
        np.stack([lids, rng.integers(0, n_keyframes, n_segments)], axis=1),
        rng.uniform(0, 480, (n_segments, 4)),
    )  # fmt: skip
    pids = np.arange(n_points, dtype=np.int64)
    obs = np.stack([np.repeat(pids, 2), rng.integers(0, n_keyframes, 2 * n_points)], axis=1)
    pts = Points(
        pids, rng.uniform(0, 50, (n_points, 3)), rng.integers(0, 255, (n_points, 3), dtype=np.uint8),
        obs, rng.uniform(0, 480, (2 * n_points, 2)),
    )  # fmt: skip
    cam = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
    return Map(cam, kf, pts, lines, axes, {"units": "arbitrary"})


def _vmhwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def child(map_path: str, out_path: str) -> None:
    """Runs in the subprocess: load, export once, print one JSON line."""
    from papl_mapper.exporters import export
    from papl_mapper.map import Map

    m = Map.load(map_path)
    base = _vmhwm_mb()
    t0 = time.perf_counter()
    paths = export(m, out_path)
    seconds = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in paths)
    print(json.dumps({"seconds": seconds, "peak_mb": _vmhwm_mb(), "map_loaded_mb": base, "bytes": size}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--segments", type=int, default=1_000_000)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--formats", help="comma-separated suffixes (default: every registered format)")
    ap.add_argument("--timeout", type=float, default=600.0)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from papl_mapper.exporters import supported_suffixes

    formats = (
        args.formats.split(",") if args.formats else [s for s in supported_suffixes() if s not in ALIASES]
    )
    rows = {}
    load_start = round(os.getloadavg()[0], 2)
    with tempfile.TemporaryDirectory(prefix="papl-bench-export-") as tmp:
        map_path = Path(tmp) / "bench.papl"
        t0 = time.perf_counter()
        synthetic_map(args.segments, args.points).save(map_path)
        build_s = time.perf_counter() - t0
        print(f"map: {args.segments:,} segments, {args.points:,} points ({build_s:.1f} s to build)")
        print(f"{'format':<11} {'seconds':>8} {'peak MB':>8} {'map MB':>7} {'size MB':>8}  goal")
        for suffix in formats:
            out = Path(tmp) / f"out{suffix}"
            cmd = [sys.executable, __file__, "--child", str(map_path), str(out)]
            try:
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, cwd=ROOT)
            except subprocess.TimeoutExpired:
                rows[suffix] = {"error": f"timed out after {args.timeout:.0f} s"}
                print(f"{suffix:<11} timed out")
                continue
            if res.returncode != 0:
                rows[suffix] = {
                    "error": res.stderr.strip().splitlines()[-1] if res.stderr.strip() else "failed"
                }
                print(f"{suffix:<11} failed: {rows[suffix]['error']}")
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            row = {
                "seconds": round(r["seconds"], 3),
                "peak_rss_mb": round(r["peak_mb"], 1),
                "map_loaded_rss_mb": round(r["map_loaded_mb"], 1),
                "file_size_mb": round(r["bytes"] / 2**20, 2),
            }
            if suffix in GOAL_FORMATS:
                row["meets_goal"] = row["seconds"] < GOAL_S and row["peak_rss_mb"] < GOAL_PEAK_MB
            rows[suffix] = row
            goal = {True: "met", False: "MISSED"}.get(row.get("meets_goal"), "")
            print(
                f"{suffix:<11} {row['seconds']:>8.2f} {row['peak_rss_mb']:>8.0f} "
                f"{row['map_loaded_rss_mb']:>7.0f} {row['file_size_mb']:>8.1f}  {goal}"
            )
            for p in out.parent.glob("out*"):
                if p.is_dir():
                    for q in p.iterdir():
                        q.unlink()
                    p.rmdir()
                else:
                    p.unlink()
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    result = {
        "segments": args.segments,
        "points": args.points,
        "keyframes": 500,
        "goal": {"formats": list(GOAL_FORMATS), "seconds_lt": GOAL_S, "peak_rss_mb_lt": GOAL_PEAK_MB},
        "formats": rows,
        "notes": (
            "seconds: export() wall time in a fresh subprocess after the map is loaded (selection, checks, "
            "encoding, atomic write with fsync). peak_rss_mb: VmHWM of that process, map included; "
            "map_loaded_rss_mb: VmHWM just after loading the map. Other jobs shared the 2 cores (see the "
            "load average), so times are upper bounds."
        ),
        "load_average_1min_start_end": [load_start, round(os.getloadavg()[0], 2)],
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "numpy": np.__version__,
        },
        "git_commit": commit,
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    out_json = ROOT / "benchmarks" / "results" / "export.json"
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out_json}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        sys.path.insert(0, str(ROOT))
        child(sys.argv[2], sys.argv[3])
    else:
        sys.exit(main())
