"""Metric scale against ground truth: markers, camera height and a known length on the synthetic
scenes (two image-noise levels), camera height on KITTI, and the demo plan's wall traces.

For each scene and noise level a 10 s walkthrough with one 0.2 m ArUco marker is rendered (cached
under --cache) and mapped once without scale. The true scale is the Umeyama Sim(3) scale between
the keyframe centres and the ground-truth trajectory; each source's error is its scale over that,
minus one; "local" columns compare with the map's own scale where the source is (Sim(3) of the
keyframes within 2 s of those that saw it), since a monocular map's scale drifts along the walk. The
known length is the estimated line whose two ends lie within 5% of a ground-truth segment's ends
(after that local Sim(3)) with the segment length nearest 2 m. KITTI 06 (frames 0-50) is
mapped with `--camera-height 1.65`. The demo is mapped with `--camera-height 1.6` (the walker's eye
height), aligned rigidly (no scale) to its ground truth, and the plan view's wall traces (sampled
every 5 cm) are measured against the ground-truth wall footprints. Prints a table, writes
benchmarks/results/scale.json.

    .venv/bin/python benchmarks/scale.py
    .venv/bin/python benchmarks/scale.py --scenes corridor --noise 0 --no-kitti --no-demo
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import machine_info

from papl_mapper.eval.lines import point_segment_distance, read_segments
from papl_mapper.eval.trajectory import associate_trajectories
from papl_mapper.exporters import ExportOptions, prepare
from papl_mapper.exporters.views import plan_view
from papl_mapper.frontend.video import open_recording
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Map
from papl_mapper.scale import (
    camera_height_scale,
    detect_markers,
    keyframe_images,
    line_length_scale,
    marker_scale,
    parse_marker_spec,
)
from papl_mapper.synth import SynthConfig, generate
from papl_mapper.synth.scenes import make_scene
from papl_mapper.trajectory_io import Trajectory, read_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "scale.json"
KITTI = ROOT.parent / "shared" / "data" / "real" / "kitti06_0000_0050"
if not KITTI.exists():
    KITTI = Path("/work/shared/data/real/kitti06_0000_0050")
MARKER = "aruco:4X4_50:0=0.2"
KNOWN_LENGTH_M = 2.0


def papl(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "papl_mapper.cli", "-q", *args], check=True)


def true_scale(m: Map, gt: Trajectory) -> float:
    """Ground-truth metres per map unit: the Umeyama Sim(3) scale of the keyframe centres."""
    est = Trajectory(m.keyframes.timestamp, m.keyframes.T_wc, "keyframes")
    i, j = associate_trajectories(gt, est, 0.01)
    return umeyama(est.positions[j], gt.positions[i]).scale


def sim3_to_gt(m: Map, gt: Trajectory, with_scale: bool = True):
    est = Trajectory(m.keyframes.timestamp, m.keyframes.T_wc, "keyframes")
    i, j = associate_trajectories(gt, est, 0.01)
    return umeyama(est.positions[j], gt.positions[i], with_scale=with_scale)


def local_scale(m: Map, gt: Trajectory, rows: np.ndarray):
    """The Sim(3) to the ground truth of the keyframes within 2 s of keyframe rows `rows`."""
    t = m.keyframes.timestamp
    near = (t >= t[rows].min() - 2) & (t <= t[rows].max() + 2)
    local = Trajectory(t[near], m.keyframes.T_wc[near], "local")
    i, j = associate_trajectories(gt, local, 0.01)
    return umeyama(local.positions[j], gt.positions[i])


def known_line(m: Map, gt_dir: Path, target_m: float) -> tuple[int, float, float] | None:
    """(line id, ground-truth length, local GT metres per unit) of the estimated line whose ends lie
    within 5% of a ground-truth segment's ends, after the Sim(3) of the keyframes that saw it (the map
    drifts: the global one misplaces lines by more), with the segment length nearest target_m."""
    gt = read_tum(gt_dir / "trajectory.tum")
    seg = read_segments(gt_dir / "segments.txt")
    gl = seg.lengths()
    row_of = {int(k): r for r, k in enumerate(m.keyframes.ids)}
    best = None
    for k, lid in enumerate(m.lines.ids):
        seen = m.lines.obs_ids[m.lines.obs_ids[:, 0] == lid, 1]
        rows = np.array([row_of[int(f)] for f in seen if int(f) in row_of])
        if len(rows) < 2:
            continue
        sim = local_scale(m, gt, rows)
        e = sim.apply(m.lines.endpoints_w[k])
        d = np.minimum(
            np.linalg.norm(seg.endpoints - e[None], axis=2).max(axis=1),
            np.linalg.norm(seg.endpoints[:, ::-1] - e[None], axis=2).max(axis=1),
        )
        for s_ in np.flatnonzero((d <= 0.05 * gl) & (seg.axis >= 0)):
            score = abs(gl[s_] - target_m)
            if best is None or score < best[0]:
                best = (score, int(lid), float(gl[s_]), float(sim.scale))
    return None if best is None else best[1:]


def recording(cache: Path, scene: str, noise: float, seconds: float) -> Path:
    out = cache / f"{scene}-noise{noise:g}-{seconds:g}s"
    cfg = SynthConfig(scene=scene, seconds=seconds, markers=1, marker_size=0.2, noise_sigma=noise)
    if noise > 0:
        cfg = SynthConfig(**{**cfg.__dict__, "motion_blur": 0.25, "exposure_jitter": 0.15})
    stamp = out / "scene.json"
    if not (stamp.exists() and json.loads(stamp.read_text())["config"] == cfg.to_dict()):
        generate(cfg, out)
    return out


def synthetic_row(cache: Path, scene: str, noise: float, seconds: float) -> dict:
    rec = recording(cache, scene, noise, seconds)
    run = rec / "run"
    map_s = None  # a cached run's time is not measured again
    if not (run / "map.papl").exists():
        t0 = time.perf_counter()
        papl("run", str(rec / "video.mp4"), "--camera", str(rec / "camera.json"), "--out", str(run))
        map_s = round(time.perf_counter() - t0, 1)
    m = Map.load(run / "map.papl")
    gt = read_tum(rec / "gt" / "trajectory.tum")
    s_true = true_scale(m, gt)
    row: dict = {"scene": scene, "noise": noise, "keyframes": len(m.keyframes), "map_s": map_s}
    row["true_metres_per_unit"] = s_true
    # marker
    spec = parse_marker_spec(MARKER)
    frames = open_recording(rec / "video.mp4").frames()
    found = detect_markers(keyframe_images(frames, m), [spec])[spec]
    truth = json.loads((rec / "gt" / "markers.json").read_text())[0]
    centre = np.mean(truth["corners_w"], axis=0)
    try:
        est = marker_scale(m, spec, found)
        kf_rows = np.array([r for r, _ in found])
        cams = sim3_to_gt(m, gt).apply(m.keyframes.T_wc[kf_rows, :3, 3])
        dist = np.linalg.norm(cams - centre, axis=1)
        # the map's own scale where the marker is: Sim(3) over the keyframes within 4 s of its views
        s_local = local_scale(m, gt, kf_rows).scale
        row |= {
            "marker_err_pct": 100 * (est.scale / s_true - 1),
            "marker_err_vs_local_pct": 100 * (est.scale / s_local - 1),
            "local_over_global_scale_pct": 100 * (s_local / s_true - 1),
            "marker_sigma_pct": 100 * est.rel_sigma,
            "marker_views": est.detail["views"],
            "marker_view_distance_m": [round(float(dist.min()), 2), round(float(dist.max()), 2)],
        }
    except Exception as exc:  # noqa: BLE001 - the benchmark records why a source failed
        row["marker_error"] = str(exc)
    # camera height: the walker's true median eye height above the floor (z = 0)
    height = float(np.median(gt.positions[:, 2]))
    est = camera_height_scale(m, height)
    row |= {
        "camera_height_m": round(height, 4),
        "camera_height_err_pct": 100 * (est.scale / s_true - 1),
        "camera_height_sigma_pct": 100 * est.rel_sigma,
    }
    hit = known_line(m, rec / "gt", KNOWN_LENGTH_M)
    if hit is None:
        row["length_error"] = "no estimated line matches a ground-truth segment end to end"
    else:
        line_id, length, s_local = hit
        est = line_length_scale(m, line_id, length)
        row |= {
            "length_line_id": line_id,
            "length_gt_m": round(length, 4),
            "length_err_pct": 100 * (est.scale / s_true - 1),
            "length_err_vs_local_pct": 100 * (est.scale / s_local - 1),
            "length_sigma_pct": 100 * est.rel_sigma,
        }
    return row


def kitti_row(cache: Path) -> dict:
    out = cache / "kitti06"
    t0 = time.perf_counter()
    papl("run", str(KITTI / "images"), "--camera", str(KITTI / "calib.txt"), "--out", str(out),
         "--camera-height", "1.65")  # fmt: skip
    m = Map.load(out / "map.papl")
    gt = read_tum(KITTI / "groundtruth.tum")
    i, j = associate_trajectories(gt, read_tum(out / "trajectory.tum"), 0.01)
    s = umeyama(read_tum(out / "trajectory.tum").positions[j], gt.positions[i]).scale  # GT m per our m
    return {
        "sequence": "kitti06_0000_0050",
        "camera_height_m": 1.65,
        "scale_err_pct": 100 * (1 / s - 1),
        "scale_sigma_pct": 100 * m.metadata["scale"]["rel_sigma"],
        "run_s": round(time.perf_counter() - t0, 1),
    }


def demo_plan_row(cache: Path) -> dict:
    demo = ROOT / "samples" / "demo"
    out = cache / "demo"
    papl("run", str(demo / "video.mp4"), "--camera", str(demo / "camera.json"), "--out", str(out),
         "--camera-height", "1.6")  # fmt: skip
    m = Map.load(out / "map.papl")
    gt = read_tum(demo / "gt" / "trajectory.tum")
    rigid = sim3_to_gt(m, gt, with_scale=False)  # the metric map as it is: no scale fitted
    m.lines.endpoints_w = rigid.apply(m.lines.endpoints_w)
    m.keyframes.T_wc = rigid.apply_poses(m.keyframes.T_wc)
    m.axes.directions = m.axes.directions @ rigid.R.T
    view = plan_view(prepare(m, ExportOptions()), ExportOptions())
    scene = make_scene("corridor", json.loads((demo / "scene.json").read_text())["seed"])
    walls = []
    for c in scene.quad_corners:
        n = np.cross(c[1] - c[0], c[3] - c[0])
        if abs(n[2]) < 0.05 * np.linalg.norm(n) and c[:, 2].min() < 0.05:
            bottom = c[np.argsort(c[:, 2])[:2]]
            walls.append(view.to_2d(bottom))
    walls = np.array(walls)  # (W, 2, 2)
    samples = []
    for ly in view.layers:
        if ly.name.startswith("HORIZONTAL"):
            for a, b in ly.segments:
                k = max(2, int(np.ceil(np.linalg.norm(b - a) / 0.05)) + 1)
                samples.append(a + np.linspace(0, 1, k)[:, None] * (b - a))
    p = np.concatenate(samples)
    pad = lambda x: np.concatenate([x, np.zeros(x.shape[:-1] + (1,))], axis=-1)  # noqa: E731
    d = point_segment_distance(pad(p)[:, None], pad(walls[:, 0])[None], pad(walls[:, 1])[None]).min(axis=1)
    return {
        "wall_traces": int(sum(len(ly.segments) for ly in view.layers if ly.name.startswith("HORIZONTAL"))),
        "trace_samples": int(len(p)),
        "median_cm": 100 * float(np.median(d)),
        "p90_cm": 100 * float(np.percentile(d, 90)),
        "within_10cm_pct": 100 * float((d <= 0.10).mean()),
        "scale": m.metadata["scale"]["description"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="corridor,atlanta,garage")
    ap.add_argument(
        "--noise", default="0,1", help="image noise sigmas (grey levels); 1 adds blur and exposure"
    )
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_scale_bench"))
    ap.add_argument("--no-kitti", action="store_true")
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = [
        synthetic_row(args.cache, s, float(n), args.seconds)
        for s in args.scenes.split(",")
        for n in args.noise.split(",")
    ]
    print(f"{'scene':<9} {'noise':>5} {'marker %':>9} {'local':>6} {'±':>6} {'views':>5} {'cam-h %':>8} "
          f"{'±':>6} {'line %':>7} {'local':>6} {'±':>6} {'GT len':>6}")  # fmt: skip
    for r in rows:

        def f(key: str, r: dict = r) -> str:
            if key not in r:
                return "-"
            return f"{r[key]:.2f}" if key.endswith("sigma_pct") else f"{r[key]:+.2f}"

        print(
            f"{r['scene']:<9} {r['noise']:>5g} {f('marker_err_pct'):>9} {f('marker_err_vs_local_pct'):>6} "
            f"{f('marker_sigma_pct'):>6} "
            f"{r.get('marker_views', '-'):>5} {f('camera_height_err_pct'):>8} "
            f"{f('camera_height_sigma_pct'):>6} "
            f"{f('length_err_pct'):>7} {f('length_err_vs_local_pct'):>6} {f('length_sigma_pct'):>6} "
            f"{r.get('length_gt_m', '-'):>6}"
        )
    result: dict = {
        "benchmark": "scale",
        "definition": "error = estimated metres per map unit / ground-truth metres per map unit - 1, in %; "
        "the ground truth is the Umeyama Sim(3) scale of the keyframe centres (KITTI: of the trajectory). "
        "marker_err_vs_local_pct: against the map's own scale near the marker (Sim(3) over the keyframes "
        "within 2 s of its views), which a drifting map makes differ from the global one "
        "(local_over_global_scale_pct). sigma = the estimator's own relative standard uncertainty, in %.",
        "seconds_per_recording": args.seconds,
        "marker": MARKER,
        "synthetic": rows,
        "machine": machine_info(),
    }
    if not args.no_kitti and KITTI.exists():
        result["kitti"] = kitti_row(args.cache)
        k = result["kitti"]
        print(
            f"KITTI 06 --camera-height 1.65: scale error {k['scale_err_pct']:+.2f}% "
            f"(±{k['scale_sigma_pct']:.2f}%)"
        )
    if not args.no_demo:
        result["demo_plan"] = p = demo_plan_row(args.cache)
        print(
            f"demo plan: {p['wall_traces']} wall traces, median {p['median_cm']:.1f} cm from the "
            f"ground-truth walls (90% {p['p90_cm']:.1f} cm, {p['within_10cm_pct']:.0f}% within 10 cm)"
        )
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
