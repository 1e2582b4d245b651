"""Applying a scale to a map and to trajectories: every length multiplies, orientations stay.

Points, line endpoints and camera centres scale about the world origin; anchored lines' inverse
depths divide by the scale; the map's units become metres and its metadata records how.
"""

from __future__ import annotations

import copy

import numpy as np

from papl_mapper.geometry.similarity import Sim3
from papl_mapper.map import Map
from papl_mapper.trajectory_io import Trajectory

from .estimate import ScaleEstimate


def _similarity(scale: float) -> Sim3:
    return Sim3(np.eye(3), np.zeros(3), float(scale), "scale")


def scale_map(m: Map, estimate: ScaleEstimate) -> Map:
    """A copy of `m` in metres: lengths times `estimate.scale`, units 'm', metadata['scale'] set."""
    s = _similarity(estimate.scale)
    out = copy.deepcopy(m)
    out.points.xyz = s.apply(m.points.xyz)
    out.lines.endpoints_w = s.apply(m.lines.endpoints_w)
    out.lines.inverse_depth = m.lines.inverse_depth / estimate.scale
    if len(m.keyframes):
        out.keyframes.T_wc = s.apply_poses(m.keyframes.T_wc)
    previous = m.metadata.get("scale")
    out.metadata["units"] = "m"
    record = estimate.to_dict()
    if previous:  # a run scaled again (a known length after a marker): the factors multiply
        record["metres_per_original_unit"] = estimate.scale * float(
            previous.get("metres_per_original_unit", previous["metres_per_unit"])
        )
        record["previous"] = previous
    out.metadata["scale"] = record
    return out


def scale_trajectory(traj: Trajectory, scale: float) -> Trajectory:
    """The trajectory with its camera centres times `scale`."""
    return Trajectory(traj.timestamps.copy(), _similarity(scale).apply_poses(traj.T_wc), traj.name)
