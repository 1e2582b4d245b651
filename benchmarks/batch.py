"""Throughput of `papl-map batch`: 4 copies of a short recording with 1 and 2 local workers and through a
one-machine Ray cluster (started here on 127.0.0.1), Ray's overhead per recording against the local
pool, peak memory per worker, the cost of a rerun that skips finished recordings, and the driver's
cost of rewriting batch.json and index.html for 10,000 recordings.

Recordings: `papl-map synth corridor --seconds 3` (640x480, 90 frames; rendered once into --work) and
samples/tiny (75 frames), each copied 4 times into a folder with its camera.json. Every batch is one
`papl-map -q batch` process timed from start to exit; Ray batches connect to the running cluster
(`--ray=ADDRESS`), whose start is timed separately. Other processes on the machine disturb the
times: the load average before and after each run is recorded beside it.

    .venv/bin/python benchmarks/batch.py [--copies 4] [--work /tmp/batch_bench]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from machine import ROOT, machine_info

OUT = ROOT / "benchmarks" / "results" / "batch.json"
PAPL_MAP = Path(sys.executable).parent / "papl-map"
MEMORY_LONG = ROOT / "benchmarks" / "results" / "memory_long.json"


def load() -> float:
    return round(os.getloadavg()[0], 2)


def du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def make_inputs(work: Path, copies: int) -> dict[str, Path]:
    """Folders of `copies` copies of each recording, with camera.json beside them."""
    src = work / "corridor3s_src"
    if not (src / "video.mp4").exists():
        print("rendering the 3 s corridor ...", flush=True)
        subprocess.run(
            [str(PAPL_MAP), "-q", "synth", "corridor", "--seconds", "3", "--out", str(src)], check=True
        )
    sets = {}
    for name, folder in (("corridor3s", src), ("tiny", ROOT / "samples" / "tiny")):
        dst = work / f"in_{name}"
        shutil.rmtree(dst, ignore_errors=True)
        dst.mkdir(parents=True)
        shutil.copy(folder / "camera.json", dst / "camera.json")
        for i in range(copies):
            shutil.copy(folder / "video.mp4", dst / f"walk{i + 1}.mp4")
        sets[name] = dst
    bad = work / "in_corrupt"
    shutil.rmtree(bad, ignore_errors=True)
    bad.mkdir()
    for i in range(8):
        (bad / f"corrupt{i + 1}.mp4").write_bytes(os.urandom(20000))
    sets["corrupt"] = bad
    return sets


def batch(inputs: Path, out: Path, *extra: str, fresh: bool = True, expect: int = 0) -> dict:
    """One `papl-map -q batch` process; its wall time, load and what batch.json says."""
    if fresh:
        shutil.rmtree(out, ignore_errors=True)
    before = load()
    t0 = time.perf_counter()
    proc = subprocess.run(
        [str(PAPL_MAP), "-q", "batch", str(inputs), "--out", str(out), *extra], capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    if proc.returncode != expect:
        raise SystemExit(f"batch {' '.join(extra)} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    doc = json.loads((out / "batch.json").read_text())
    rows = doc["recordings"]
    computed = [r for r in rows if not r.get("reused")]
    if expect == 1:  # the overhead set: every recording fails at once, what is left is the engine's cost
        return {
            "args": list(extra),
            "recordings": len(rows),
            "wall_s": round(wall, 2),
            "wall_s_per_recording": round(wall / len(rows), 3),
            "job_wall_s_mean": round(sum(r["wall_s"] for r in rows) / len(rows), 3),
            "load_before": before,
            "load_after": load(),
        }
    jobs = [r["wall_s"] for r in computed]
    mapping = [sum(r["timings_s"].values()) for r in computed]
    return {
        "args": list(extra),
        "engine": doc["engine"],
        "recordings": len(rows),
        "reused": len(rows) - len(computed),
        "wall_s": round(wall, 2),
        "recordings_per_min": round(60 * len(computed) / wall, 2) if computed else None,
        "job_wall_s_mean": round(sum(jobs) / len(jobs), 2) if jobs else None,
        "mapping_s_mean": round(sum(mapping) / len(mapping), 2) if mapping else None,
        "peak_rss_MiB_max": max((r.get("peak_rss_mib") or 0 for r in computed), default=None),
        "peak_rss_MiB_mean": round(sum(r.get("peak_rss_mib") or 0 for r in computed) / len(computed), 1)
        if computed
        else None,
        "attempts": sum(r.get("attempts") or 0 for r in computed),
        "output_bytes_per_recording": int(sum(du(out / r["name"]) for r in rows) / len(rows)),
        "checkpoint_bytes_per_recording": int(
            sum(du(out / r["name"] / ".checkpoint") for r in rows) / len(rows)
        ),
        "load_before": before,
        "load_after": load(),
    }


def driver_write_cost(sample: dict, n: int = 10_000) -> dict:
    """Seconds to write batch.json and index.html for n recordings like `sample` (the driver rewrites
    them at most every 2 s while a batch runs, and once at the end)."""
    import tempfile

    from papl_mapper.pipelines.batch import _Folder, totals

    rows = [{**sample, "name": f"walk{i:05d}"} for i in range(n)]
    with tempfile.TemporaryDirectory() as tmp:
        doc = {"format": "papl-batch", "recordings": rows, "engine": {"engine": "ray"}, "out": tmp}
        t0 = time.perf_counter()
        doc["totals"] = totals(rows, 1.0)
        _Folder(Path(tmp)).write(doc)
        dt = time.perf_counter() - t0
        size = (Path(tmp) / "batch.json").stat().st_size + (Path(tmp) / "index.html").stat().st_size
    return {"recordings": n, "write_s": round(dt, 3), "bytes": size}


def estimate(results: dict) -> dict:
    """10,000 one-minute walkthroughs on 100 nodes like this one, from the measurements here and the
    60 s 1280x720 run of benchmarks/results/memory_long.json."""
    long = json.loads(MEMORY_LONG.read_text())
    one_min = next(r for r in long["runs"] if r["seconds"] == 60.0)
    c = results["corridor3s"]
    local1, local2 = c["local_1_worker"], c["local_2_workers"]
    o = results["engine_overhead_8_failing_recordings"]
    speedup = local2["recordings_per_min"] / local1["recordings_per_min"]
    # worker-seconds each recording costs Ray beyond the local pool (2 slots), from the failing set
    ray_overhead = 2 * (
        o["ray_2_tasks"]["wall_s_per_recording"] - o["local_2_workers"]["wall_s_per_recording"]
    )
    per_node_per_min_ray = 2 * 60 / (2 * one_min["wall_s"] / speedup + ray_overhead)
    nodes, n = 100, 10_000
    hours = n / (nodes * per_node_per_min_ray) / 60
    out_bytes = c["local_2_workers"]["output_bytes_per_recording"] / 3 * 60  # per second of video, as 60 s
    in_bytes = results["corridor3s_input_bytes"] / 3 * 60
    return {
        "assumptions": "nodes like this one (2 cores, 24 GiB), 2 tasks per node at 1 CPU each, a 60 s "
        "1280x720 walk as in memory_long.json, Ray's per-recording overhead as measured on 8 failing "
        "recordings, "
        "output size scaled linearly from the 3 s 640x480 clip (an underestimate at 720p)",
        "one_minute_walk_wall_s": one_min["wall_s"],
        "one_minute_walk_peak_rss_MiB": one_min["peak_rss_MiB"],
        "two_workers_speedup": round(speedup, 2),
        "recordings_per_min_per_node": round(per_node_per_min_ray, 2),
        "ray_overhead_worker_s_per_recording": round(ray_overhead, 2),
        "cluster_recordings_per_hour": round(nodes * per_node_per_min_ray * 60),
        "hours_for_10000": round(hours, 1),
        "output_GB_for_10000_at_least": round(n * out_bytes / 1e9, 1),
        "input_GB_for_10000_at_least": round(n * in_bytes / 1e9, 1),
        "driver_rewrite_s_10000_rows": results["driver_write_10000"]["write_s"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--copies", type=int, default=4)
    ap.add_argument("--work", type=Path, default=Path("/tmp/batch_bench"))
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    from papl_mapper.pipelines.batch_ray import LocalRayHead

    sets = make_inputs(args.work, args.copies)
    results: dict = {}
    sample: dict = {}
    info = machine_info(load_at_start=load())
    head = LocalRayHead(num_cpus=2)
    t0 = time.perf_counter()
    address = head.start()
    ray_start_s = time.perf_counter() - t0
    try:
        overhead = {}
        for label, extra in (
            ("local_2_workers", ["--workers", "2"]),
            ("ray_2_tasks", [f"--ray={address}", "--threads", "1"]),
        ):
            print(f"corrupt: {label} ...", flush=True)
            overhead[label] = batch(sets["corrupt"], args.work / "out_corrupt" / label, *extra, expect=1)
        results["engine_overhead_8_failing_recordings"] = overhead
        for name, inputs in sets.items():
            if name == "corrupt":
                continue
            runs = {}
            out = args.work / f"out_{name}"
            for label, extra in (
                ("local_1_worker", ["--workers", "1"]),
                ("local_2_workers", ["--workers", "2"]),
                ("ray_1_task", [f"--ray={address}", "--threads", "2"]),
                ("ray_2_tasks", [f"--ray={address}", "--threads", "1"]),
            ):
                print(f"{name}: {label} ...", flush=True)
                runs[label] = batch(inputs, out / label, *extra)
            print(f"{name}: rerun of the finished local_2_workers batch ...", flush=True)
            runs["rerun_skips_all"] = batch(inputs, out / "local_2_workers", "--workers", "2", fresh=False)
            results[name] = runs
            if not sample:
                sample = json.loads((out / "local_2_workers" / "batch.json").read_text())["recordings"][0]
    finally:
        head.stop()
    results["ray_cluster_start_s"] = round(ray_start_s, 2)
    results["driver_write_10000"] = driver_write_cost(sample)
    results["corridor3s_input_bytes"] = (sets["corridor3s"] / "walk1.mp4").stat().st_size
    mapped = [n for n in sets if n != "corrupt"]
    for name in mapped:
        r = results[name]
        for k in (1, 2):
            loc, ray = (
                r["local_1_worker" if k == 1 else "local_2_workers"],
                r["ray_1_task" if k == 1 else "ray_2_tasks"],
            )
            r[f"ray_overhead_s_per_recording_{k}"] = round(
                (ray["wall_s"] - loc["wall_s"]) / loc["recordings"], 2
            )
        r["speedup_2_vs_1_local"] = round(
            r["local_2_workers"]["recordings_per_min"] / r["local_1_worker"]["recordings_per_min"], 2
        )
        r["speedup_2_vs_1_ray"] = round(
            r["ray_2_tasks"]["recordings_per_min"] / r["ray_1_task"]["recordings_per_min"], 2
        )
    results["estimate_100_nodes"] = estimate(results)

    print()
    head_line = f"{'set':<11} {'engine':<16} {'wall s':>7} {'rec/min':>8} {'job s':>6} {'map s':>6}"
    print(f"{head_line} {'peak MiB':>9} {'load':>10}")
    for name in mapped:
        for label, r in results[name].items():
            if not isinstance(r, dict):
                continue
            rate = r["recordings_per_min"] if r["recordings_per_min"] is not None else float("nan")
            print(
                f"{name:<11} {label:<16} {r['wall_s']:>7.1f} {rate:>8.2f} {r['job_wall_s_mean'] or 0:>6.1f} "
                f"{r['mapping_s_mean'] or 0:>6.1f} {r['peak_rss_MiB_max'] or 0:>9.0f} "
                f"{r['load_before']:>4.1f}-{r['load_after']:<4.1f}"
            )
        r = results[name]
        print(
            f"{name:<11} 2 vs 1 worker: local x{r['speedup_2_vs_1_local']}, Ray x{r['speedup_2_vs_1_ray']}; "
            f"Ray minus local per recording: {r['ray_overhead_s_per_recording_1']} s (1 at a time), "
            f"{r['ray_overhead_s_per_recording_2']} s (2 at a time)"
        )
    o = results["engine_overhead_8_failing_recordings"]
    print(
        "engine cost per recording (8 corrupt files, 2 at a time): local "
        f"{o['local_2_workers']['wall_s_per_recording']} s, Ray {o['ray_2_tasks']['wall_s_per_recording']} s "
        f"(job itself {o['local_2_workers']['job_wall_s_mean']} / {o['ray_2_tasks']['job_wall_s_mean']} s)"
    )
    e = results["estimate_100_nodes"]
    print(
        f"Ray cluster start {results['ray_cluster_start_s']} s; batch.json + index.html for 10,000 rows: "
        f"{results['driver_write_10000']['write_s']} s"
    )
    print(
        f"estimate: 100 nodes x 2 tasks, 10,000 one-minute walks: {e['hours_for_10000']} h "
        f"({e['cluster_recordings_per_hour']} per hour), >= {e['output_GB_for_10000_at_least']} GB of outputs"
    )
    doc = {"benchmark": "batch", "machine": {**info, "load_at_end": load()}, "results": results}
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
