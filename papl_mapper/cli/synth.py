"""`papl-map synth SCENE --out DIR`: render a synthetic walkthrough with ground truth."""

from __future__ import annotations

import argparse

from papl_mapper.cli.progress import progress_bar
from papl_mapper.synth.generate import SynthConfig, generate
from papl_mapper.synth.scenes import SCENES


def add_parser(sub: argparse._SubParsersAction) -> None:
    d = SynthConfig()
    p = sub.add_parser("synth", help="render a synthetic walkthrough with ground truth", description=__doc__)
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
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """The SynthConfig the parsed command line asks for."""
    return SynthConfig(
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
    )


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    config.validate()
    with progress_bar(f"synth {config.scene}") as cb:
        out = generate(config, args.out, progress=cb)
    print(f"wrote {config.n_frames} frames of {config.scene} to {out}")
    return 0
