"""`papl-map scale RUN_DIR ...`: put a finished run in metres, rewriting its outputs atomically.

Sources: a known line length (--length LINE_ID=METRES), two points a known distance apart
(--points ID_A,ID_B=METRES), fiducial markers seen in the recording (--marker aruco:DICT:ID=SIZE_M),
or the camera height above the floor (--camera-height METRES). With several, the best-conditioned
one is used and sources that disagree beyond their uncertainties are refused.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from papl_mapper.errors import InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "scale",
        help="put a finished run in metres (known length, points, marker, camera height)",
        description=__doc__,
        epilog="Rewrites map.papl, trajectory.tum, keyframes.tum, summary.json and the map.* exports "
        "in RUN_DIR (then the previews and report.html when present); nothing changes when an input "
        "is bad.",
    )
    p.add_argument("run_dir", type=Path, help="the --out folder of a finished `papl-map run`")
    p.add_argument(
        "--length", action="append", default=[], metavar="LINE_ID=METRES", help="a known line length"
    )
    p.add_argument(
        "--points",
        action="append",
        default=[],
        metavar="ID_A,ID_B=METRES",
        help="two points a known distance apart",
    )
    p.add_argument(
        "--marker", action="append", default=[], metavar="aruco:DICT:ID=SIZE_M", help="a fiducial marker"
    )
    p.add_argument(
        "--camera-height", type=float, default=0.0, metavar="METRES", help="camera height above the floor"
    )
    p.add_argument(
        "--recording", type=Path, help="the recording, for --marker (default: the map's source_path)"
    )
    p.add_argument("--dry-run", action="store_true", help="print the estimates, write nothing")
    p.set_defaults(func=run)


def _pair(text: str, option: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    try:
        metres = float(value)
    except ValueError:
        metres = float("nan")
    if not sep or not key.strip() or metres != metres:
        raise InputError(f"{option} {text!r}: expected {option[2:].upper()}=METRES, e.g. {option} 12=2.0")
    return key.strip(), metres


def _int(text: str, option: str, whole: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise InputError(f"{option} {whole!r}: {text!r} is not an id (an integer)") from None


def run(args: argparse.Namespace) -> int:
    from papl_mapper.map import Map
    from papl_mapper.scale import (
        ScaleConfig,
        check_config,
        estimate_scale,
        line_length_scale,
        point_distance_scale,
    )
    from papl_mapper.scale.run_dir import rescale_run, run_map_path

    cfg = ScaleConfig(markers=list(args.marker), camera_height=args.camera_height)
    check_config(cfg)  # a bad --marker or --camera-height is refused before anything is read
    parsed_len = [(_pair(t, "--length"), t) for t in args.length]
    parsed_pts = [(_pair(t, "--points"), t) for t in args.points]
    if not (parsed_len or parsed_pts or cfg.enabled):
        raise InputError("give a scale source: --length, --points, --marker or --camera-height")
    m = Map.load(run_map_path(args.run_dir))
    extra = []
    for (key, metres), whole in parsed_len:
        extra.append(line_length_scale(m, _int(key, "--length", whole), metres))
    for (key, metres), whole in parsed_pts:
        ids = key.split(",")
        if len(ids) != 2:
            raise InputError(f"--points {whole!r}: expected two point ids, ID_A,ID_B=METRES")
        extra.append(point_distance_scale(m, *(_int(i, "--points", whole) for i in ids), metres))
    frames = None
    if cfg.markers:
        frames = _frames_of(args.recording, m)
    est = estimate_scale(m, cfg, frames, extra)
    sigma = f"±{100 * est.rel_sigma:.2g}%" if est.rel_sigma != float("inf") else "uncertainty unknown"
    print(f"scale: {est.scale:.6g} m per map unit ({sigma}) from {est.description}")
    if args.dry_run:
        return 0
    scaled, written = rescale_run(args.run_dir, est, m)
    for p in written:
        print(f"wrote {p}")
    previews = args.run_dir / "previews"
    if previews.is_dir():  # the previews there again: their titles say the units
        from papl_mapper.gui.preview import VIEWS, PreviewOptions, render_views

        views = tuple(v for v in VIEWS if (previews / f"{v}.png").exists())
        if views:
            res = render_views(scaled, previews, PreviewOptions(views=views))
            print(f"wrote {len(res.paths)} previews into {previews}")
    report = args.run_dir / "report.html"
    if report.exists():
        from papl_mapper.gui.report import write_report

        print(f"wrote {write_report(args.run_dir, report)}")
    return 0


def _frames_of(recording: Path | None, m):
    """A function decoding the recording the map was made from, with the run's frame size."""
    from papl_mapper.frontend.video import open_recording

    path = recording or m.metadata.get("source_path")
    if not path:
        raise InputError("--marker: the map does not name its recording; give it with --recording")
    path = Path(path)
    if not path.exists():
        raise InputError(f"--marker: the recording {path} is not there; give it with --recording")
    cam = m.camera
    max_size = max(cam.width, cam.height)

    def frames():
        rec = open_recording(path, max_size=max_size)
        if (rec.width, rec.height) != (cam.width, cam.height):
            raise InputError(
                f"{path}: frames are {rec.width}x{rec.height}, the map's camera {cam.width}x{cam.height}"
            )
        return rec.frames()

    return frames
