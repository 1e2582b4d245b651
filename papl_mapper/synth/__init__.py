"""Synthetic walkthroughs with ground truth: scenes, camera paths, renderer, generator, projected tracks."""

from papl_mapper.synth.generate import (
    VARIANTS,
    SynthConfig,
    camera_path,
    drop_pattern,
    generate,
    gt_map,
    with_variants,
)
from papl_mapper.synth.path import look_around, pan_then_walk, walkthrough
from papl_mapper.synth.project import tracks_from_scene, visible_points, visible_segments
from papl_mapper.synth.render import Renderer
from papl_mapper.synth.scenes import SCENES, Scene, low_texture, make_scene

__all__ = [
    "SCENES",
    "VARIANTS",
    "Renderer",
    "Scene",
    "SynthConfig",
    "camera_path",
    "drop_pattern",
    "generate",
    "gt_map",
    "look_around",
    "low_texture",
    "make_scene",
    "pan_then_walk",
    "tracks_from_scene",
    "visible_points",
    "visible_segments",
    "walkthrough",
    "with_variants",
]
