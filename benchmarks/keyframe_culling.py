"""Keyframe culling's effect on accuracy and time: the mapping stages with and without culling on the
same frontend tracks of synthetic recordings with ground truth.

For each recording folder (papl-map synth output) the frontend runs once (or its tracks are read from
`--tracks-dir/<folder name>.npz` when present, and written there otherwise); then
`papl_mapper.pipelines.run.map_tracks` runs as is ("base") and with `register_keyframes` wrapped by
`cull_keyframes` ("cull"), and `evaluate` scores every frame's trajectory and the lines. Times share
one machine with other jobs: compare the two variants of a row, measured minutes apart.

Usage: python benchmarks/keyframe_culling.py /tmp/papl_accuracy/corridor_noise3_10s ... [--tracks-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine_info  # noqa: E402

import papl_mapper.pipelines.run as pipeline  # noqa: E402
from papl_mapper.eval import evaluate  # noqa: E402
from papl_mapper.frontend import process  # noqa: E402
from papl_mapper.frontend.camera import camera_for_recording  # noqa: E402
from papl_mapper.frontend.video import open_recording  # noqa: E402
from papl_mapper.mapping.culling import CullConfig, CullStats, cull_keyframes  # noqa: E402
from papl_mapper.pipelines.config import RunConfig  # noqa: E402
from papl_mapper.tracks import Tracks  # noqa: E402
from papl_mapper.trajectory_io import write_tum  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "keyframe_culling.json"
DEFAULT = [f"/tmp/papl_accuracy/{s}_noise3_10s" for s in ("corridor", "atlanta", "garage")]


def _tracks(folder: Path, cache: Path) -> Tracks:
    path = cache / f"{folder.name}.npz"
    if path.exists():
        return Tracks.load(path)
    cfg = RunConfig()
    rec = open_recording(folder / "video.mp4")
    cam = camera_for_recording(folder / "camera.json", rec.width, rec.height, cfg.hfov_deg).camera
    tracks = process(rec, cam, cfg.frontend)
    cache.mkdir(parents=True, exist_ok=True)
    tracks.save(path)
    return tracks


def _run(tracks: Tracks, folder: Path, cull: CullConfig | None) -> dict:
    register = pipeline.register_keyframes
    stats = CullStats()
    if cull is not None:
        pipeline.register_keyframes = lambda tr, *a, **kw: cull_keyframes(
            tr, register(tr, *a, **kw), cull, stats
        )
    try:
        cfg = RunConfig()
        timer = pipeline._Timer()
        t0 = time.perf_counter()
        m, _ = pipeline.map_tracks(tracks, cfg, timer)
        traj = pipeline.frame_trajectory(tracks, m, cfg)
        wall = time.perf_counter() - t0
    finally:
        pipeline.register_keyframes = register
    with tempfile.TemporaryDirectory() as tmp:
        write_tum(Path(tmp) / "trajectory.tum", traj)
        ev = evaluate(folder, m, Path(tmp) / "trajectory.tum")
    return {
        "keyframes": len(m.keyframes),
        "culling": stats.as_dict() if cull is not None else None,
        "frames_posed": len(traj),
        "frames": len(tracks),
        "mapping_wall_s": round(wall, 2),
        "timings_s": timer.times,
        "ate_rmse_rel_path_pct": round(100 * ev.ate_rmse_rel_path, 4),
        "line_recall_1pct": round(ev.line_recall["1%"], 4),
        "line_precision_1pct": round(ev.line_precision["1%"], 4),
        "lines": len(m.lines),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="*", default=DEFAULT, help="synth folders (video.mp4, camera.json, gt/)")
    ap.add_argument("--tracks-dir", default="/tmp/keyframe_culling_tracks", help="frontend tracks cache")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args()
    rows = []
    head = (
        f"{'recording':<24} {'variant':>7} {'kf':>5} {'posed':>7} {'map s':>6} {'ba_full s':>9} "
        f"{'ATE %path':>9} {'recall':>6} {'prec':>6}"
    )
    print(head)
    for folder in map(Path, args.folders):
        tracks = _tracks(folder, Path(args.tracks_dir))
        for variant, cull in (("base", None), ("cull", CullConfig())):
            r = {"recording": folder.name, "variant": variant, **_run(tracks, folder, cull)}
            rows.append(r)
            print(
                f"{r['recording']:<24} {variant:>7} {r['keyframes']:>5} "
                f"{r['frames_posed']:>3}/{r['frames']:<3} "
                f"{r['mapping_wall_s']:>6.1f} {r['timings_s'].get('ba_full', 0):>9.1f} "
                f"{r['ate_rmse_rel_path_pct']:>9.3f} {r['line_recall_1pct']:>6.3f} "
                f"{r['line_precision_1pct']:>6.3f}",
                flush=True,
            )
    out = Path(args.results)
    out.parent.mkdir(exist_ok=True)
    out.write_text(
        json.dumps({"benchmark": "keyframe_culling", "machine": machine_info(), "runs": rows}, indent=1)
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
