"""`papl-map synth SCENE --out DIR`: render a synthetic walkthrough with ground truth."""

from __future__ import annotations

import argparse
import dataclasses

from papl_mapper.cli.progress import progress_bar
from papl_mapper.synth.generate import VARIANTS, SynthConfig, generate, with_variants
from papl_mapper.synth.scenes import SCENES

VARIANT_HELP = """adversarial variants (--variant NAME[,NAME...], combinable):
  rotation-start  stand and pan in place (pure rotation) for --pan-seconds, turning --pan-deg, then walk
  rotation-only   stand at the start and pan back and forth (--pan-deg every --pan-seconds); never translate
  dropped-frames  leave out --drop-fraction of the frames (default 0.1; seeded, some runs of 2-4): the kept
                  frames keep their true times (gaps in timestamps.txt; variable-frame-rate video.mp4)
  photo-set       frames of the walk at --photo-hz (default 1) as DIR/frames/*.png with
                  frames/timestamps.txt, no video: map it with `papl-map run DIR/frames`
  low-texture     blank walls and ceilings, faint floor (same geometry and ground truth)
  hand-held       a hand-held camera's motion blur (half the frame time), exposure changes (0.3 stops
                  RMS) and image noise (2 grey levels): --blur 0.5 --exposure 0.3 --noise 2
not combinable: rotation-start with rotation-only, dropped-frames with photo-set.
example: papl-map synth corridor --variant rotation-start,low-texture --out out/synth-rs"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    d = SynthConfig()
    p = sub.add_parser(
        "synth",
        help="render a synthetic walkthrough with ground truth",
        description=__doc__,
        epilog=VARIANT_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", help=f"scene name: {', '.join(SCENES)}")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--width", type=int, default=d.width, help=f"image width in pixels (default {d.width})")
    p.add_argument(
        "--height", type=int, default=d.height, help=f"image height in pixels (default {d.height})"
    )
    p.add_argument("--fps", type=float, default=d.fps, help=f"frames per second (default {d.fps:g})")
    p.add_argument(
        "--seconds", type=float, default=d.seconds, help=f"length in seconds (default {d.seconds:g})"
    )
    p.add_argument(
        "--hfov", type=float, default=d.hfov_deg, help=f"horizontal field of view, deg ({d.hfov_deg:g})"
    )
    p.add_argument("--noise", type=float, default=d.noise_sigma, help="image noise sigma in grey levels (0)")
    p.add_argument("--blur", type=float, default=d.motion_blur, help="motion blur: shutter fraction 0..1 (0)")
    p.add_argument(
        "--exposure", type=float, default=d.exposure_jitter, help="exposure changes, RMS stops (0)"
    )
    p.add_argument("--seed", type=int, default=d.seed, help=f"random seed (default {d.seed})")
    p.add_argument("--supersample", type=int, default=d.supersample, help="anti-aliasing factor 1..4 (2)")
    p.add_argument("--speed", type=float, default=d.speed, help=f"walking speed m/s (default {d.speed:g})")
    p.add_argument("--msaa", action="store_true", help="textures once per pixel: faster, slightly softer")
    p.add_argument("--frames", action="store_true", help="also write frames/NNNNNN.png")
    p.add_argument(
        "--variant",
        default="",
        metavar="NAMES",
        help=f"comma-separated adversarial variants: {', '.join(VARIANTS)} (see below)",
    )
    p.add_argument(
        "--pan-seconds",
        type=float,
        default=d.pan_seconds,
        help=f"rotation-start: pan time before walking; rotation-only: per sweep (default {d.pan_seconds:g})",
    )
    p.add_argument(
        "--pan-deg", type=float, default=d.pan_deg, help=f"pan angle in degrees (default {d.pan_deg:g})"
    )
    p.add_argument(
        "--drop-fraction",
        type=float,
        help="fraction of frames to drop (0..0.5; implies dropped-frames; default with it 0.1)",
    )
    p.add_argument(
        "--photo-hz", type=float, help="photo set rate in Hz (implies photo-set; default with it 1)"
    )
    p.add_argument("--markers", type=int, default=d.markers, help="ArUco markers on the walls (default 0)")
    p.add_argument(
        "--marker-size", type=float, default=d.marker_size, help=f"marker side in m ({d.marker_size:g})"
    )
    p.add_argument(
        "--marker-dictionary", default=d.marker_dictionary, help=f"ArUco dictionary ({d.marker_dictionary})"
    )
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """The SynthConfig the parsed command line asks for (InputError for an unknown variant)."""
    config = SynthConfig(
        scene=args.scene,
        width=args.width,
        height=args.height,
        fps=args.fps,
        seconds=args.seconds,
        hfov_deg=args.hfov,
        noise_sigma=args.noise,
        motion_blur=args.blur,
        exposure_jitter=args.exposure,
        seed=args.seed,
        write_frames=args.frames,
        supersample=args.supersample,
        speed=args.speed,
        msaa=args.msaa,
        pan_seconds=args.pan_seconds,
        pan_deg=args.pan_deg,
        markers=args.markers,
        marker_size=args.marker_size,
        marker_dictionary=args.marker_dictionary,
    )
    names = [v.strip() for v in args.variant.split(",") if v.strip()]
    config = with_variants(config, *names)
    for name in ("drop_fraction", "photo_hz"):
        if getattr(args, name) is not None:
            config = dataclasses.replace(config, **{name: getattr(args, name)})
    return config


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    config.validate()
    with progress_bar(f"synth {config.scene}") as cb:
        out = generate(config, args.out, progress=cb)
    variants = f" ({', '.join(config.variants)})" if config.variants else ""
    where = f"{out / 'frames'}" if config.photo_hz > 0 else f"{out}"
    print(f"wrote {len(config.frame_indices())} frames of {config.scene}{variants} to {where}")
    return 0
