"""Keyframe registration's time against the recording's length, this checkout against another.

Registration (PnP, triangulation, revisits and loop closures, the windowed BA) runs once per keyframe,
so its time should grow with the length of the recording, not with its square. For each length the
frontend's tracks of the recording's first `end` seconds are made once (cached under --cache, by this
checkout), then `register_keyframes` runs on them in a child process with this checkout's papl_mapper
and, with --against, with another checkout's, and the two registrations are compared pose by pose.
Prints a table and writes benchmarks/results/registration_scale.json. Make the recording first, e.g.

    papl-map synth corridor --out /tmp/corr_long --seconds 180 --noise 1 --supersample 1 --msaa
    .venv/bin/python benchmarks/registration_scale.py --recording /tmp/corr_long --ends 60,180 \\
        --against /tmp/main_before
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine_info  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "registration_scale.json"
ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import dataclasses, json, sys, time
import numpy as np
checkout, tracks_file, out = sys.argv[1:4]
# that checkout's papl_mapper, not the editable install's: its package and its top-level pipelines/
finders = sys.meta_path
sys.meta_path = [f for f in finders if "editable" not in (type(f).__module__ + type(f).__name__).lower()]
sys.path.insert(0, checkout)
import papl_mapper
papl_mapper.__path__.append(checkout)
from papl_mapper.mapping import incremental as inc
from papl_mapper.mapping.windowed import WindowedRefiner
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.tracks import Tracks
assert inc.__file__.startswith(checkout), inc.__file__
tracks, cfg = Tracks.load(tracks_file), RunConfig()
local = dataclasses.replace(cfg.ba, relative_error_tol=cfg.local_ba_relative_error_tol)
refine = WindowedRefiner(tracks, local, cfg.local_ba_window, cfg.max_point_error_px)
t = time.perf_counter()
reg = inc.register_keyframes(tracks, cfg.mapping, None, refine, cfg.seed)
wall = time.perf_counter() - t
poses = reg.poses()
frames = sorted(poses)
np.savez(out, frames=np.array(frames), T_cw=np.stack([poses[f] for f in frames]))
print(json.dumps({"registration_s": wall, "keyframes": len(reg.frames), "points": len(reg.points_w),
                  "revisits": len(reg.revisits), "frames_posed": len(frames)}))
"""


def _tracks(recording: Path, end: float, cache: Path) -> Path:
    """The frontend's tracks of the recording's first `end` seconds (made once)."""
    path = cache / f"{recording.name}_{end:g}s_tracks.npz"
    if not path.exists():
        from papl_mapper.frontend import FrontendStats, process
        from papl_mapper.frontend.camera import camera_for_recording
        from papl_mapper.frontend.video import open_recording
        from papl_mapper.pipelines.config import RunConfig

        cfg = RunConfig()
        rec = open_recording(recording / "video.mp4", 1, None, end, None)
        cam = camera_for_recording(recording / "camera.json", rec.width, rec.height, cfg.hfov_deg)
        process(rec, cam.camera, cfg.frontend, stats=FrontendStats()).save(path)
    return path


def _register(checkout: Path, tracks: Path, poses: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(checkout), str(tracks), str(poses)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _pose_difference(a: Path, b: Path) -> float | None:
    """Largest difference of any T_cw entry between two registrations (None: different frames)."""
    with np.load(a) as x, np.load(b) as y:
        if not np.array_equal(x["frames"], y["frames"]):
            return None
        return float(np.abs(x["T_cw"] - y["T_cw"]).max())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recording", type=Path, required=True, help="a `papl-map synth` folder")
    ap.add_argument("--ends", default="60,180", help="comma-separated lengths in seconds from the start")
    ap.add_argument("--against", type=Path, help="another checkout to time the same registrations with")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/papl_registration_scale"))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for end in (float(e) for e in args.ends.split(",")):
            tracks = _tracks(args.recording, end, args.cache)
            row = {"seconds": end, **_register(ROOT, tracks, Path(tmp, "this.npz"))}
            if args.against:
                base = _register(args.against.resolve(), tracks, Path(tmp, "base.npz"))
                row["baseline_s"] = base["registration_s"]
                row["ratio"] = row["registration_s"] / base["registration_s"]
                row["max_pose_difference"] = _pose_difference(Path(tmp, "this.npz"), Path(tmp, "base.npz"))
            row["ms_per_keyframe"] = 1000 * row["registration_s"] / row["keyframes"]
            rows.append(row)
            base_txt = f"{row['baseline_s']:9.1f} {row['ratio']:6.2f}" if args.against else ""
            print(
                f"{end:5.0f} s {row['frames_posed']:6d} posed {row['keyframes']:5d} kf {row['revisits']:4d} "
                f"revisits {row['registration_s']:8.1f} s {row['ms_per_keyframe']:6.0f} ms/kf {base_txt}",
                flush=True,
            )
    result = {
        "benchmark": "registration_scale",
        "machine": machine_info(),
        "recording": str(args.recording),
        "against": str(args.against) if args.against else None,
        "runs": rows,
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
