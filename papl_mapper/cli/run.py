"""`papl-map run VIDEO --out DIR`: map a recorded walkthrough (video file or image folder)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from papl_mapper.atomic import atomic_path, check_output_dir, move_into_place
from papl_mapper.cli.progress import progress_bar
from papl_mapper.config import load_config
from papl_mapper.errors import InputError, OutputError, PaplError
from papl_mapper.outputs import add_outputs
from papl_mapper.pipelines.logfile import close_log, file_log
from papl_mapper.scale import check_config as check_scale_config

if TYPE_CHECKING:
    from papl_mapper.pipelines.run import RunInterrupted

log = logging.getLogger("papl_mapper")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="map a recording: anchored line map, trajectories, summary",
        description=__doc__,
        epilog="Outputs in DIR: map.papl, trajectory.tum (every frame), keyframes.tum, config.toml, "
        "summary.json, log.txt; with --export/--render/--report also those; manifest.json lists them. "
        "A rerun into DIR removes the files the previous run's manifest lists and the new run does not "
        "write (nothing else). Options, paths and export targets are checked before the first frame. "
        "Finished stages are "
        "checkpointed in DIR/.checkpoint: after Ctrl-C the outputs of a previous run are unchanged and "
        "--resume continues after the latest finished stage (with any settings: a stage reruns when "
        "its settings changed).",
    )
    p.add_argument("recording", help="video file (anything OpenCV's FFmpeg reads) or a folder of images")
    p.add_argument("--out", required=True, type=Path, help="output folder (created if missing)")
    p.add_argument(
        "--camera",
        type=Path,
        help="intrinsics: camera.json, OpenCV YAML/JSON, COLMAP cameras.txt, "
        "KITTI calib.txt (default: guessed from hfov_deg, with a warning)",
    )
    p.add_argument(
        "--preset",
        default="full",
        help="ablation preset: full, hard-association, no-axis-management, no-vertical-prior, "
        "no-vp-refinement, points-only, orthonormal-lines, no-revisit, paper-anchors, no-final-completion",
    )
    p.add_argument("--config", type=Path, help="TOML file with RunConfig fields")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--start", type=float, help="start time in seconds")
    p.add_argument("--end", type=float, help="end time in seconds")
    p.add_argument("--step", type=int, default=1, help="use every STEP-th frame (default 1)")
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
    from papl_mapper.pipelines.config import PRESETS, RunConfig
    from papl_mapper.pipelines.run import RunInterrupted
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
    _check_before_work(args, cfg)
    # the log of an unfinished run stays beside the checkpoints (a resumed run appends to it) and
    # replaces log.txt when the run's outputs are written, so log.txt always belongs to map.papl
    running_log = args.out / ".checkpoint" / "log.txt"
    try:
        running_log.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{args.out}: cannot create the output folder ({exc.strerror or exc})") from exc
    handler = file_log(running_log, "a" if args.resume else "w")
    try:
        result = run_pipeline(
            args.recording,
            args.out,
            cfg,
            camera_file=args.camera,
            start_s=args.start,
            end_s=args.end,
            step=args.step,
            max_size=args.max_size,
            resume=args.resume,
            progress=progress_bar,
        )
    except RunInterrupted as exc:
        from papl_mapper.cli import Terminated

        term = isinstance(exc.__cause__, Terminated)
        message = f"papl-map run: {'SIGTERM: ' if term else ''}{_interrupted(exc, args.out)}"
        handler.handle(log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None))
        print(message, file=sys.stderr)
        return 143 if term else 130
    except PaplError as exc:  # the running log keeps why the run failed
        handler.handle(log.makeRecord(log.name, logging.ERROR, __file__, 0, f"error: {exc}", None, None))
        raise
    finally:
        close_log(handler)
    move_into_place(running_log, args.out / "log.txt")
    add_outputs(args.out, [args.out / "log.txt"])
    handler = file_log(args.out / "log.txt", "a")  # exports, previews and the report log there too
    try:
        _finish(args, cfg, result)
    except KeyboardInterrupt:
        print(
            f"papl-map run: interrupted after the run: {args.out} holds the new map and its outputs; "
            "exports, previews, report or evaluation may be missing",
            file=sys.stderr,
        )
        return 130
    finally:
        close_log(handler)
    return 0


def _check_before_work(args: argparse.Namespace, cfg) -> None:
    """Every option and path that can be checked before the first frame: the output folder, the time
    range, the export formats and their targets, the ground-truth folder, the scale settings."""
    from papl_mapper.exporters import check_target, suffix_of
    from papl_mapper.pipelines.run import check_range

    check_output_dir(args.out)
    check_range(args.start, args.end)
    if args.step < 1:
        raise InputError(f"--step {args.step}: give 1 or more")
    if args.max_size is not None and args.max_size < 16:
        raise InputError(f"--max-size {args.max_size}: give 16 pixels or more")
    for fmt in cfg.output.export:
        target = args.out / f"map.{fmt.strip().lstrip('.')}"
        if args.out.is_dir():
            check_target(target)
        else:
            suffix_of(target)
    if args.gt is not None and not args.gt.is_dir():
        raise InputError(f"--gt {args.gt}: no such ground-truth folder")
    check_scale_config(cfg.scale)  # a bad --marker or --camera-height fails before any work


def _interrupted(exc: RunInterrupted, out: Path) -> str:
    """The one line saying which stage Ctrl-C stopped and where --resume continues."""
    from papl_mapper.pipelines.checkpoint import TITLES

    if exc.resume_from is None:
        then = "nothing was checkpointed yet, so --resume starts from the beginning"
    else:
        then = f"rerun with --resume to continue from the {TITLES[exc.resume_from]} checkpoint"
    return f"interrupted in {exc.stage}: the outputs in {out} are unchanged; {then}"


def _finish(args: argparse.Namespace, cfg, result) -> None:
    """The one-line result, then the extras."""
    s = result.summary
    c = s["counts"]
    print(
        f"{args.out}: {c.get('keyframes', 0)} keyframes, {c.get('points', 0)} points, "
        f"{c.get('lines', 0)} lines "
        f"({100 * c.get('anchored_fraction', 0):.0f}% anchored), {len(result.map.axes)} axes; "
        f"{s['frames_lost']} of {s['recording']['frames']} frames without a pose"
    )
    _extras(args, cfg, result)


def _extras(args: argparse.Namespace, cfg, result) -> None:
    """Exports, previews, report and evaluation asked for on the command line."""
    out: Path = args.out
    for fmt in cfg.output.export:
        from papl_mapper.exporters import export

        paths = export(result.map, out / f"map.{fmt.strip().lstrip('.')}")
        add_outputs(out, paths)
        for path in paths:
            print(f"wrote {path}")
    if args.gt is not None:
        import json

        from papl_mapper.eval import evaluate

        ev = evaluate(args.gt, result.map, out / "trajectory.tum")
        with atomic_path(out / "eval.json") as tmp:
            tmp.write_text(json.dumps(ev.to_dict(), indent=1))
        add_outputs(out, [out / "eval.json"])
        print(ev.table())
    if args.render or cfg.output.render:
        from papl_mapper.gui.preview import render_views

        with progress_bar("previews") as cb:
            res = render_views(result.map, out / "previews", progress=cb)
        add_outputs(out, res.paths + ([res.turntable] if res.turntable else []))
        print(f"wrote {len(res.paths)} previews into {out / 'previews'}")
    if args.report or cfg.output.report:
        from papl_mapper.gui.report import write_report

        path = write_report(out, out / "report.html", gt_dir=args.gt)
        add_outputs(out, [path])
        print(f"wrote {path}")
