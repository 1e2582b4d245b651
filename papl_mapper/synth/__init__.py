"""Synthetic walkthroughs with ground truth: scenes, camera paths, renderer, generator, projected tracks."""

from papl_mapper.synth.generate import SynthConfig, generate, gt_map
from papl_mapper.synth.path import walkthrough
from papl_mapper.synth.project import tracks_from_scene, visible_points, visible_segments
from papl_mapper.synth.render import Renderer
from papl_mapper.synth.scenes import SCENES, Scene, make_scene

__all__ = [
    "SCENES",
    "Renderer",
    "Scene",
    "SynthConfig",
    "generate",
    "gt_map",
    "make_scene",
    "tracks_from_scene",
    "visible_points",
    "visible_segments",
    "walkthrough",
]
