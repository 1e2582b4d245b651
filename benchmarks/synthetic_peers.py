"""papl-map, COLMAP and GLOMAP on the synthetic video renders of the accuracy suite, in the same run.

Each render (`benchmarks/accuracy.py`'s cache and naming) has its video decoded to PNG frames, the
images papl-map itself reads from the video, and is laid out as a sequence of `benchmarks/real.py`
(images/ with timestamps.txt, groundtruth.tum, camera.json) under --layout; real.py then maps every
sequence three ways exactly as it maps the real data (COLMAP and GLOMAP on one SIFT database,
intrinsics fixed, sequential matching). This says what the peers reach on the scenes whose goals the
issues set (the garage's, for one). A peer that poses only part of a recording is compared on that
part too: papl-map's ATE over the frames the peer posed (`papl_on_<peer>_frames`, the same Sim(3)
alignment over those frames alone). Prints real.py's table and that comparison and writes
benchmarks/results/synthetic_peers.json.

    .venv/bin/python benchmarks/synthetic_peers.py                       # garage, corridor, Atlanta
    .venv/bin/python benchmarks/synthetic_peers.py --scenes garage --seeds 0,1 --ablation points-only
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from accuracy import cached_render
from machine import ROOT
from real import MAX_TIME_DIFF_S, accuracy, discover

from papl_mapper.eval.trajectory import associate_trajectories
from papl_mapper.trajectory_io import read_tum

OUT = ROOT / "benchmarks" / "results" / "synthetic_peers.json"


def layout(render: Path, dst: Path) -> Path:
    """`dst` as a real.py sequence of `render`: its video's frames, timestamps, ground truth, camera."""
    images = dst / "images"
    stamps = (render / "timestamps.txt").read_text().split()
    if (images / "timestamps.txt").is_file() and len(list(images.glob("*.png"))) == len(stamps):
        return dst
    shutil.rmtree(dst, ignore_errors=True)
    images.mkdir(parents=True)
    cap = cv2.VideoCapture(str(render / "video.mp4"), cv2.CAP_FFMPEG)  # as papl-map decodes it
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        cv2.imwrite(str(images / f"{n:06d}.png"), frame)
        n += 1
    cap.release()
    if n != len(stamps):
        raise RuntimeError(f"{render / 'video.mp4'}: {n} frames decoded for {len(stamps)} timestamps")
    (images / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    shutil.copy(render / "gt" / "trajectory.tum", dst / "groundtruth.tum")
    shutil.copy(render / "camera.json", dst / "camera.json")
    return dst


def on_peer_frames(results: Path, data: Path) -> None:
    """Add to each sequence of `results` (real.py's JSON) papl-map's ATE over the frames each peer posed,
    where the peer posed fewer than all, and print them."""
    doc = json.loads(results.read_text())
    seqs = {s.name: s for s in discover(data)}
    for name, entry in doc["sequences"].items():
        papl = entry.get("papl", {})
        if name not in seqs or papl.get("status") != "ok":
            continue
        est = read_tum(papl["trajectory"])
        for peer in ("colmap", "glomap"):
            rec = entry.get(peer, {})
            if rec.get("status") != "ok" or rec.get("frames_posed", 0) >= papl.get("frames_posed", 0):
                continue
            _, rows = associate_trajectories(read_tum(rec["trajectory"]), est, MAX_TIME_DIFF_S)
            ours = accuracy(seqs[name], est.subset(np.sort(rows)))
            entry[f"papl_on_{peer}_frames"] = {"frames": len(rows)} | ours
            print(
                f"{name}: over the {len(rows)} frames {peer} posed: papl-map "
                f"{ours.get('ate_rmse_pct_path', float('nan')):.3f}% of path, {peer} "
                f"{rec.get('ate_rmse_pct_path', float('nan')):.3f}%"
            )
    results.write_text(json.dumps(doc, indent=1, default=float))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="garage,corridor,atlanta")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--noise", default="0", help="image noise levels (grey levels), comma-separated")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_accuracy"), help="accuracy.py's renders")
    ap.add_argument("--layout", type=Path, default=Path("/tmp/papl_synthetic_peers"), help="the sequences")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--ablation", default="", help="passed to real.py")
    args = ap.parse_args()
    data = args.layout / "sequences"
    data.mkdir(parents=True, exist_ok=True)
    names = []
    for scene in args.scenes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for noise in (float(n) for n in args.noise.split(",")):
                render = cached_render(args.cache, scene, noise, args.seconds, seed)
                print("sequence", layout(render, data / render.name))
                names.append(render.name)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "real.py"), "--data", str(data), "--out", str(args.out)]
    cmd += ["--only", ",".join(names)]
    cmd += ["--out-dir", str(args.layout / "runs")] + (["--ablation", args.ablation] if args.ablation else [])
    code = subprocess.run(cmd, cwd=ROOT).returncode
    if code == 0:
        on_peer_frames(args.out, data)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
