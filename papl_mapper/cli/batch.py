"""`papl-map batch INPUT... --out DIR`: map many recordings, on local worker processes or with Ray.

An INPUT is a recording (video file or image folder), a folder of recordings, or a manifest (.toml
or .csv: path, camera, start/end/step/max_size, preset, config, set, gt, name per recording).
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from papl_mapper.cli.progress import progress_bar

EPILOG = """\
Outputs: DIR/<name>/ per recording, holding what `papl-map run` writes (map.papl, trajectory.tum,
keyframes.tum, config.toml, summary.json, log.txt, and the --export/--render/--report files; eval.json
with a ground-truth folder), then DIR/batch.json and DIR/index.html with one row per recording.
Names come from the file names (parent folders in front where two collide) or the manifest.

A failed recording (bad file, cannot initialise, its worker crashed or passed --memory-limit) is
marked with its error; the others go on. Exit code 0 when every recording mapped, 1 when any failed,
130 after Ctrl-C. Rerunning the same batch skips finished recordings whose input and settings are
unchanged and resumes half-finished ones from their checkpoints.

Manifest (TOML; paths relative to it):
  [defaults]
  camera = "camera.json"
  [[recording]]
  path = "walks/monday.mp4"
  end = 60.0
  set = ["ba.max_iterations=10"]
  gt = "walks/monday_gt"
CSV: a header row (path,camera,start,end,step,max_size,preset,config,set,gt,name; path required),
one row per recording, several set overrides separated by ";".
"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="map many recordings (folders, manifests) on local workers or a Ray cluster",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="recording, folder of recordings, or manifest")
    p.add_argument("--out", required=True, type=Path, help="output folder of the batch (created if missing)")
    p.add_argument(
        "--camera",
        type=Path,
        help="intrinsics for recordings without their own (a manifest's camera, or camera.json beside them)",
    )
    p.add_argument("--preset", default="full", help="ablation preset for every recording (see `run --help`)")
    p.add_argument("--config", type=Path, help="TOML file with RunConfig fields for every recording")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key for every recording (a manifest's own set comes after)",
    )
    p.add_argument("--seed", type=int, help="seed for random choices (default 0)")
    p.add_argument(
        "--start", type=float, help="start time in seconds from the first frame (unless a manifest gives one)"
    )
    p.add_argument(
        "--end", type=float, help="end time in seconds from the first frame (unless a manifest gives one)"
    )
    p.add_argument(
        "--step", type=int, default=1, help="use every STEP-th frame (unless a manifest gives one)"
    )
    p.add_argument("--max-size", type=int, help="downscale so the longer image side is at most this")
    p.add_argument("--export", help="comma-separated export formats per recording, e.g. ply,glb,usdc")
    p.add_argument("--render", action="store_true", help="also write PNG previews per recording")
    p.add_argument(
        "--report", action="store_true", help="also write report.html per recording (linked from the index)"
    )
    p.add_argument("--force", action="store_true", help="recompute every recording from scratch")
    p.add_argument(
        "--workers",
        type=int,
        help="local worker processes at once (default: one per core, fewer if the memory does not hold "
        "--memory for each)",
    )
    p.add_argument(
        "--threads",
        type=int,
        help="CPU threads per recording: its OpenCV and BLAS pools, and Ray's num_cpus (default: "
        "cores / workers locally, 1 on Ray)",
    )
    p.add_argument(
        "--memory",
        type=float,
        default=2.0,
        metavar="GIB",
        help="memory one recording needs: sizes the default --workers and Ray's memory request (default 2)",
    )
    p.add_argument(
        "--memory-limit",
        type=float,
        metavar="GIB",
        help="local: a worker whose resident memory passes this is stopped and its recording marked "
        "failed (default: the available memory / workers)",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the recordings as Ray tasks: on a local Ray started for the batch, or on the running "
        "cluster at ADDRESS (HOST:PORT; write --ray=ADDRESS before the inputs). Needs papl-mapper[ray]",
    )
    p.add_argument("--retries", type=int, default=2, help="Ray: retries of a recording whose worker died")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.pipelines.batch import BatchInterrupted, BatchOptions, EngineOptions, run_batch

    inputs = list(args.inputs)
    if args.ray not in (None, "local", "auto") and Path(args.ray).exists() and not args.ray.count(":"):
        inputs.insert(0, args.ray)  # `--ray a.mp4 b.mp4`: the path was an INPUT, not an address
        args.ray = "local"
    options = BatchOptions(
        camera=args.camera,
        preset=args.preset,
        config=args.config,
        set=list(args.set),
        seed=args.seed,
        start=args.start,
        end=args.end,
        step=args.step,
        max_size=args.max_size,
        export=args.export,
        render=args.render,
        report=args.report,
        force=args.force,
    )
    engine = EngineOptions(
        workers=args.workers,
        threads=args.threads,
        memory_gib=args.memory,
        memory_limit_gib=args.memory_limit,
        ray=args.ray,
        retries=args.retries,
    )

    def on_row(row: dict) -> None:
        if row["status"] in ("ok", "failed"):
            print(_row_line(row), flush=True)

    previous = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, _sigterm)  # stop like Ctrl-C: running recordings keep their checkpoints
    try:
        with progress_bar("recordings") as cb:
            result = run_batch(inputs, args.out, options, engine, on_row=on_row, progress=cb)
    except BatchInterrupted as exc:
        r = exc.result
        print(
            f"papl-map batch: interrupted: {r.count('ok')} of {len(r.rows)} recordings finished "
            f"(see {r.out / 'batch.json'}); rerun the same command to continue",
            file=sys.stderr,
        )
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    failed = result.failed
    print(
        f"{result.out}: {result.count('ok')} of {len(result.rows)} recordings mapped"
        + (f", {len(failed)} failed ({', '.join(r['name'] for r in failed)})" if failed else "")
        + f"; {result.out / 'index.html'}"
    )
    return 1 if failed else 0


def _sigterm(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _row_line(row: dict) -> str:
    if row["status"] == "failed":
        return f"{row['name']}: failed: {row.get('error')}"
    reused = " (reused)" if row.get("reused") else ""
    return (
        f"{row['name']}: {row.get('frames_posed')} of {row.get('frames')} frames posed, "
        f"{row.get('keyframes')} keyframes, {row.get('lines')} lines "
        f"({100 * (row.get('anchored_fraction') or 0):.0f}% anchored){reused}"
    )
