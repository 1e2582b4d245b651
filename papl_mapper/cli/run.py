"""`papl-map run VIDEO --out DIR`: map a recorded walkthrough (video file or image folder)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from papl_mapper.cli.progress import progress_bar
from papl_mapper.config import load_config
from papl_mapper.errors import InputError

if TYPE_CHECKING:
    from papl_mapper.pipelines.run import RunResult


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="map a recording: anchored line map, trajectories, summary",
        description=__doc__,
        epilog="Outputs in DIR: map.papl, trajectory.tum (every frame), keyframes.tum, config.toml, "
        "summary.json, log.txt; with --export/--render/--report also those; a tracking segment that "
        "could not be joined to the map gets its own map, trajectories and exports in "
        "DIR/segments/FIRST-LAST/; "
        "manifest.json lists them. "
        "A rerun into DIR removes the files the previous run's manifest lists and the new run does not "
        "write (nothing else). Options, paths and export targets are checked before the first frame. "
        "Finished stages are "
        "checkpointed in DIR/.checkpoint: after Ctrl-C the outputs of a previous run are unchanged and "
        "--resume continues after the latest finished stage (with any settings: a stage reruns when "
        "its settings changed). config.toml holds every setting, the camera file and frame range "
        "included: `run --config DIR/config.toml VIDEO` maps the same recording the same way.",
    )
    p.add_argument(
        "recording",
        help="video file (anything OpenCV's FFmpeg reads) or a folder of images, timed by its "
        "timestamps.txt, else by image names that are Unix times (TUM, EuRoC), else by KITTI's "
        "times.txt beside it, else at 30 fps",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (created if missing)")
    p.add_argument(
        "--camera",
        type=Path,
        help="intrinsics: camera.json, OpenCV YAML/JSON, COLMAP cameras.txt, KITTI calib.txt, "
        "EuRoC sensor.yaml, Kalibr camchain, ORB-SLAM settings (default: guessed from hfov_deg, with a "
        "warning)",
    )
    p.add_argument(
        "--preset",
        default="full",
        help="ablation preset: full, hard-association, no-axis-management, no-vertical-prior, "
        "no-vp-refinement, points-only, orthonormal-lines, no-revisit, paper-anchors, no-final-completion",
    )
    p.add_argument("--config", type=Path, help="TOML file with RunConfig fields")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--start", type=float, help="start time in seconds from the first frame")
    p.add_argument("--end", type=float, help="end time in seconds from the first frame")
    p.add_argument("--step", type=int, help="use every STEP-th frame (default 1)")
    p.add_argument("--max-size", type=int, help="downscale so the longer image side is at most this")
    p.add_argument("--seed", type=int, help="seed for random choices (default 0)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue after the latest checkpointed stage (frontend, registration, points BA, full BA) "
        "whose input and settings are unchanged",
    )
    p.add_argument(
        "--export", help="comma-separated export formats written beside the map, e.g. ply,glb,usdc"
    )
    p.add_argument("--render", action="store_true", help="also write PNG previews into DIR/previews")
    p.add_argument("--report", action="store_true", help="also write DIR/report.html")
    p.add_argument("--gt", type=Path, help="ground-truth folder for the report and eval.json")
    p.add_argument(
        "--marker",
        action="append",
        default=[],
        metavar="aruco:DICT:ID=SIZE_M",
        help="scale the map to metres from an ArUco marker of known side (repeatable)",
    )
    p.add_argument(
        "--camera-height",
        type=float,
        metavar="METRES",
        help="scale the map from the camera height above the floor",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from papl_mapper.pipelines.config import PRESETS, RunConfig, with_extras, with_input
    from papl_mapper.pipelines.run import ExtrasInterrupted, RunInterrupted
    from papl_mapper.pipelines.run import run as run_pipeline

    if args.preset not in PRESETS:
        raise InputError(f"unknown preset {args.preset!r}; known: {', '.join(PRESETS)}")
    overrides = list(PRESETS[args.preset]) + list(args.set)
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.export:
        overrides.append(f"output.export={args.export}")
    if args.marker:
        overrides.append(f"scale.markers={','.join(args.marker)}")
    if args.camera_height is not None:
        overrides.append(f"scale.camera_height={args.camera_height}")
    cfg = load_config(RunConfig, args.config, overrides)
    cfg = with_input(
        cfg, camera=args.camera, start_s=args.start, end_s=args.end, step=args.step, max_size=args.max_size
    )
    cfg = with_extras(cfg, render=args.render, report=args.report, gt=args.gt)
    try:
        result = run_pipeline(args.recording, args.out, cfg, resume=args.resume, progress=progress_bar)
    except RunInterrupted as exc:
        from papl_mapper.cli import Terminated

        term = isinstance(exc.__cause__, Terminated)
        print(f"papl-map run: {'SIGTERM: ' if term else ''}{exc.message()}", file=sys.stderr)
        return 143 if term else 130
    except ExtrasInterrupted:
        print(
            f"papl-map run: interrupted after the run: {args.out} holds the new map and its outputs; "
            "exports, previews, report or evaluation may be missing",
            file=sys.stderr,
        )
        return 130
    _print_result(args.out, result)
    return 0


def _print_result(out: Path, result: RunResult) -> None:
    """The one-line result, then what the extras wrote."""
    s = result.summary
    c = s.counts or {}
    print(
        f"{out}: {c.get('keyframes', 0)} keyframes, {c.get('points', 0)} points, "
        f"{c.get('lines', 0)} lines "
        f"({100 * c.get('anchored_fraction', 0):.0f}% anchored), {len(result.map.axes)} axes; "
        f"{s.frames_lost} of {s.recording.frames} frames without a pose"
    )
    x = result.extras
    for path in x.exports:
        print(f"wrote {path}")
    if x.evaluation is not None:
        print(x.evaluation.table())
    if x.previews is not None:
        print(f"wrote {len(x.previews)} previews into {out / 'previews'}")
    if x.report is not None:
        print(f"wrote {x.report}")
