"""Benchmark: synthetic rendering speed per scene at 640x480 and 1280x720, on one core.

Renders frames spread along each scene's walkthrough with OpenCV limited to one thread: no
supersampling, 2x supersampling, and 2x multisampling (coverage per sample, textures per pixel).
Times one full `generate` (render, blur/noise/exposure, mp4 encode, ground truth) at 640x480.
Reports wall-clock and process-CPU frames per second: the machine is shared, so CPU time is the
steadier figure. Prints a table, writes benchmarks/results/synth_render.json.
Usage: .venv/bin/python benchmarks/synth_render.py [--frames N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from machine import git_commit

from papl_mapper.synth import SynthConfig, generate, make_scene, walkthrough
from papl_mapper.synth.render import Renderer

ROOT = Path(__file__).resolve().parents[1]

SIZES = ((640, 480), (1280, 720))
MODES = ((1, False), (2, False), (2, True))  # (supersample, msaa)


def _commit() -> str:
    return git_commit()


def bench_render(scene_name: str, width: int, height: int, ss: int, msaa: bool, n_frames: int) -> dict:
    cfg = SynthConfig(scene=scene_name, width=width, height=height, seconds=20.0, supersample=ss)
    t0 = time.perf_counter()
    scene = make_scene(scene_name, 0)
    cam = cfg.camera()
    renderer = Renderer(scene, cam, ss, msaa=msaa)
    setup_s = time.perf_counter() - t0
    _, T = walkthrough(scene, cfg.n_frames, cfg.fps, 0)
    idx = np.linspace(0, len(T) - 1, n_frames).round().astype(int)
    renderer.render(T[idx[0]])  # warm-up
    wall_ms, cpu_ms = [], []
    for i in idx:
        w0, c0 = time.perf_counter(), time.process_time()
        renderer.render(T[i])
        wall_ms.append(1000 * (time.perf_counter() - w0))
        cpu_ms.append(1000 * (time.process_time() - c0))
    wall, cpu = sum(wall_ms) / 1000, sum(cpu_ms) / 1000
    return {
        "scene": scene_name,
        "width": width,
        "height": height,
        "supersample": ss,
        "msaa": msaa,
        "frames": int(n_frames),
        "render_fps_wall": round(n_frames / wall, 2),
        "render_fps_cpu": round(n_frames / cpu, 2),
        "ms_per_frame_cpu": round(1000 * cpu / n_frames, 2),
        "ms_per_frame_cpu_median": round(float(np.median(cpu_ms)), 2),
        "ms_per_frame_wall_median": round(float(np.median(wall_ms)), 2),
        "render_fps_cpu_median": round(1000 / float(np.median(cpu_ms)), 2),
        "setup_s": round(setup_s, 3),
    }


def bench_generate(seconds: float) -> dict:
    cfg = SynthConfig(
        scene="corridor", seconds=seconds, noise_sigma=1.0, motion_blur=0.25, exposure_jitter=0.15
    )
    with tempfile.TemporaryDirectory() as tmp:
        w0, c0 = time.perf_counter(), time.process_time()
        out = generate(cfg, Path(tmp) / "run")
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        video_mb = (out / "video.mp4").stat().st_size / 1e6
    n = cfg.n_frames
    return {
        "what": "generate corridor 640x480, supersample 2, noise 1, blur 0.25, exposure 0.15",
        "frames": n,
        "generate_s_wall": round(wall, 2),
        "generate_fps_wall": round(n / wall, 2),
        "generate_fps_cpu": round(n / cpu, 2),
        "video_mb_per_s": round(video_mb / seconds, 3),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40, help="frames per measurement (default 40)")
    parser.add_argument("--generate-seconds", type=float, default=5.0, help="length of the generate run")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rows = []
    for name in ("corridor", "atlanta", "garage"):
        for w, h in SIZES:
            for ss, msaa in MODES:
                rows.append(bench_render(name, w, h, ss, msaa, args.frames))
                r = rows[-1]
                print(
                    f"{name:<9} {w}x{h:<5} ss={ss}{' msaa' if msaa else '     '}  "
                    f"{r['render_fps_wall']:7.1f} fps wall  "
                    f"{r['render_fps_cpu']:7.1f} fps cpu  "
                    f"(median {r['ms_per_frame_cpu_median']:.1f} ms cpu/frame, "
                    f"{r['render_fps_cpu_median']:.1f} fps)",
                    flush=True,
                )
    gen = bench_generate(args.generate_seconds)
    print(
        f"generate  {gen['frames']} frames 640x480 ss=2: {gen['generate_fps_wall']:.1f} fps wall, "
        f"{gen['generate_fps_cpu']:.1f} fps cpu, video {gen['video_mb_per_s']:.2f} MB/s"
    )
    load = os.getloadavg()
    result = {
        "benchmark": "synth_render",
        "render": rows,
        "generate": gen,
        "opencv_threads": 1,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "load_average_1_5_15": [round(x, 2) for x in load],
            "opencv": cv2.__version__,
            "numpy": np.__version__,
        },
        "git_commit": _commit(),
        "note": (
            "shared 2-core machine: wall-clock figures are disturbed by other jobs; "
            "cpu figures are process CPU time"
        ),
    }
    out = ROOT / "benchmarks" / "results" / "synth_render.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
