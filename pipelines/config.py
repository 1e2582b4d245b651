"""The configuration of one `papl-map run`: every stage's config nested, plus the ablation variant.

Presets name the paper's ablations (and points-only / orthonormal-only lines); a preset is a list
of overrides applied before the user's own `--config` file and `--set` overrides.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

from papl_mapper.axes import AxesConfig
from papl_mapper.backend import BAConfig
from papl_mapper.backend.calibration import FocalCheckConfig
from papl_mapper.errors import InputError
from papl_mapper.frontend import FrontendConfig
from papl_mapper.mapping.culling import CullConfig
from papl_mapper.mapping.incremental import IncrementalConfig
from papl_mapper.mapping.lines import LineInitConfig
from papl_mapper.mapping.reverse_start import ReverseCheckConfig
from papl_mapper.mapping.rotation_averaging import RotationCheckConfig
from papl_mapper.mapping.track_completion import CompletionConfig
from papl_mapper.scale.config import ScaleConfig


@dataclass
class InputConfig:
    """Which frames of the recording are mapped, at what size, with which camera: with the recording
    itself (the run's argument) this fixes the frontend's input, so config.toml reproduces the run."""

    camera: Path | None = None
    """Intrinsics file: camera.json, OpenCV YAML/JSON, COLMAP cameras.txt, KITTI calib.txt, EuRoC
    sensor.yaml, Kalibr camchain, ORB-SLAM settings (none: guessed from `hfov_deg`, with a warning)."""
    start_s: float | None = None
    """Start time in seconds from the first frame (none: the first frame)."""
    end_s: float | None = None
    """End time in seconds from the first frame (none: the last frame)."""
    step: int = 1
    """Use every step-th frame."""
    max_size: int | None = None
    """Downscale so the longer image side is at most this many pixels (none: full size)."""


def check_input(i: InputConfig) -> None:
    """InputError unless the time range is finite, starts at or after 0 and ends after its start, the
    step is 1 or more and the size at least 16 pixels (named by their command-line flags)."""
    for name, value in (("--start", i.start_s), ("--end", i.end_s)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise InputError(f"{name} {value}: give a finite time in seconds, 0 or more")
    if i.start_s is not None and i.end_s is not None and i.end_s <= i.start_s:
        raise InputError(f"--end {i.end_s} s is not after --start {i.start_s} s")
    if i.step < 1:
        raise InputError(f"--step {i.step}: give 1 or more")
    if i.max_size is not None and i.max_size < 16:
        raise InputError(f"--max-size {i.max_size}: give 16 pixels or more")


@dataclass
class VariantConfig:
    """Which map the method builds (the axes' own switches are in `axes`: association, update)."""

    lines: Literal["anchored", "orthonormal", "none"] = "anchored"
    """Anchored structural lines (the method), every line orthonormal, or no lines (points only)."""


@dataclass
class OutputConfig:
    """What the run writes besides the map and trajectories."""

    export: list[str] = field(default_factory=list)
    """Export formats written beside the map (suffixes such as ply, glb, usdc)."""
    render: bool = False
    """Write PNG previews into previews/."""
    report: bool = False
    """Write report.html."""
    gt: Path | None = None
    """Ground-truth folder: write eval.json and compare the map with it in the report."""


@dataclass
class RunConfig:
    """Everything one run depends on; written beside the outputs as config.toml."""

    RENAMED: ClassVar[dict[str, str]] = {
        "local_ba_every": "mapping.refine_every",
        "variant.association": "axes.association",
        "variant.axis_management": "axes.update",
        "axis_min_support_fraction": "axes.min_support_fraction",
        **{
            f"{stage}.seed": "seed"
            for stage in (
                "frontend.vp",
                "frontend.features",
                "mapping.init",
                "mapping.pnp",
                "mapping.relative_pose",
                "focal",
            )
        },
    }
    """Keys (full, dotted) of older config files and where their setting lives now (named in the error)."""

    input: InputConfig = field(default_factory=InputConfig)
    """Frame range, step, size and camera file of the recording."""
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    """Decoding, points, lines, vanishing points, keyframes."""
    mapping: IncrementalConfig = field(default_factory=IncrementalConfig)
    """Initialisation, PnP tracking, point triangulation."""
    cull: CullConfig = field(default_factory=lambda: CullConfig(enabled=False))
    """Redundant keyframe culling after registration. Off: it halves keyframes and BA memory but costs
    accuracy (benchmarks/RESULTS.md)."""
    rotations: RotationCheckConfig = field(default_factory=RotationCheckConfig)
    """The first points-only BA checked against keyframe rotations averaged from pairwise essential
    matrices; where they disagree, the BA also runs from those and the lower cost is kept."""
    reverse: ReverseCheckConfig = field(default_factory=ReverseCheckConfig)
    """The recording registered backwards as well; the points-only BA also runs from those keyframe poses
    and they are kept where they fit every observation of the tracks better."""
    completion: CompletionConfig = field(default_factory=CompletionConfig)
    """Track merging, completion and retriangulation after the points-only BA (then BA again)."""
    lines: LineInitConfig = field(default_factory=LineInitConfig)
    """Line triangulation (the temporary-vanishing-point stage for structural lines)."""
    axes: AxesConfig = field(default_factory=AxesConfig)
    """Principal axes: creation, association (soft or hard) and update after BA, every axis setting."""
    ba: BAConfig = field(default_factory=lambda: BAConfig(relative_error_tol=1e-3, anchor_offset=True))
    """Bundle adjustment. Stops when an iteration gains under 0.1% of the cost; anchored lines get the
    sideways offset besides the inverse depth (2n + 2 parameters per axis instead of the paper's n + 2,
    `--preset paper-anchors`), so each line fits all its views (benchmarks/RESULTS.md)."""
    variant: VariantConfig = field(default_factory=VariantConfig)
    """Ablation switches."""
    output: OutputConfig = field(default_factory=OutputConfig)
    """Extra outputs."""
    focal: FocalCheckConfig = field(default_factory=FocalCheckConfig)
    """Focal-length plausibility check after mapping (warns when the map supports another focal length)."""
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    """Metric scale after mapping (markers, camera height); none by default: arbitrary units."""
    seed: int = 0
    """Seed of every random choice, so the same input gives the same map: the pipeline passes it to
    each stage that draws (vanishing-point search, feature verification, initialisation, PnP, segment
    merging, rotation check, line directions, focal check); no stage has a seed setting of its own."""
    local_ba_window: int = 15
    """Keyframes optimised by each windowed BA."""
    local_ba_relative_error_tol: float = 1e-4
    """The windowed BAs of registration stop when an iteration gains under this fraction of the cost: ten
    times tighter than the global BA (`ba.relative_error_tol`). Their problems are small, and the drift a
    window leaves unconverged is built on by every later frame's PnP, where no global BA undoes it."""
    stray_line_margin: float = 0.2
    """Lines reaching beyond the points' extent (1-99 percentiles) by this fraction of its diagonal are
    dropped after BA."""
    lines_from_all_frames: bool = True
    """Triangulate lines from the segments of every registered frame (else keyframes only)."""
    max_point_error_px: float = 4.0
    """Point observations reprojecting further than this are culled before each bundle adjustment."""
    max_line_error_px: float = 4.0
    """Line observations with an endpoint further than this from the projected line are culled."""
    hfov_deg: float = 60.0
    """Horizontal field of view used to guess intrinsics when no camera file is given."""


PRESETS: dict[str, list[str]] = {
    "full": [],
    "hard-association": ["axes.association=hard"],
    "no-axis-management": ["axes.update=false"],
    "no-vertical-prior": ["frontend.vp.use_vertical_prior=false"],
    "no-vp-refinement": ["frontend.vp.refine_svd=false"],
    "points-only": ["variant.lines=none"],
    "orthonormal-lines": ["variant.lines=orthonormal"],
    "no-revisit": ["mapping.revisit.enabled=false"],
    "paper-anchors": ["ba.anchor_offset=false"],
    "no-final-completion": ["completion.after_full_ba=false"],
}


def with_input(config: RunConfig, **given: Any) -> RunConfig:
    """`config` with the `input` fields that are given (not None) replaced: command-line flags (or a
    batch's recording) over the config file."""
    changes = {k: v for k, v in given.items() if v is not None}
    if not changes:
        return config
    return dataclasses.replace(config, input=dataclasses.replace(config.input, **changes))


def with_extras(
    config: RunConfig, render: bool = False, report: bool = False, gt: Path | None = None
) -> RunConfig:
    """`config` with previews and the report switched on when asked and the ground-truth folder when
    given (command-line flags, or a batch's recording, over the config file)."""
    o = config.output
    output = dataclasses.replace(o, render=o.render or render, report=o.report or report, gt=gt or o.gt)
    return dataclasses.replace(config, output=output)
