"""Every frame's pose after mapping: keyframes from the map, the others by PnP on its points, refined
with its lines and axes; frames that only turn in place keep an orientation."""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.se3 import invert
from papl_mapper.map import Map
from papl_mapper.mapping.pose_refine import FrameRefiner
from papl_mapper.mapping.rotation_only import RotationOnlyConfig, fill_rotation_only
from papl_mapper.mapping.tracking import PnPConfig, track_pnp
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import Trajectory


def keyframe_poses(m: Map) -> dict[int, np.ndarray]:
    """T_wc of the map's keyframes by frame id."""
    return {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}


def frame_poses(
    tracks: Tracks, m: Map, pnp: PnPConfig, rotation_only: RotationOnlyConfig, seed: int = 0
) -> dict[int, np.ndarray]:
    """T_wc of every frame that has one: keyframes from the map, the others by PnP on its points
    (`seed` seeds its RANSAC)."""
    K = tracks.camera.K
    kf = keyframe_poses(m)
    pid = m.points.ids
    out: dict[int, np.ndarray] = {}
    last = None
    # the map's lines and axes refine each PnP pose (points alone drift in rotation where few)
    refiner = FrameRefiner.from_map(tracks, m, pnp.refine)
    for f in range(len(tracks)):
        if f in kf:
            T_wc = kf[f]
        else:
            ids, uv = tracks.points_in(f)
            idx = np.minimum(np.searchsorted(pid, ids), max(len(pid) - 1, 0))
            known = pid[idx] == ids if len(pid) else np.zeros(len(ids), bool)
            guess = np.linalg.inv(last) if last is not None else None
            X, uv = m.points.xyz[idx[known]], uv[known]
            res = track_pnp(X, uv, K, guess, pnp, seed=seed)
            if not res.ok:
                continue
            T_cw, _ = refiner.refine(f, res.T_cw, X[res.inliers], uv[res.inliers])
            T_wc = np.linalg.inv(T_cw)
        last = out[f] = T_wc
    # frames that turn in place where nothing is mapped (a pan at the start) keep an orientation
    turned = fill_rotation_only(tracks, {f: invert(T) for f, T in out.items()}, rotation_only)
    out.update({f: invert(T) for f, T in turned.items()})
    return dict(sorted(out.items()))


def frame_trajectory(
    tracks: Tracks, m: Map, pnp: PnPConfig, rotation_only: RotationOnlyConfig, seed: int = 0
) -> Trajectory:
    """A pose for every frame that has one (see `frame_poses`), as a timestamped trajectory."""
    poses = frame_poses(tracks, m, pnp, rotation_only, seed)
    frames = np.array(sorted(poses), np.int64)
    T = np.array([poses[int(f)] for f in frames]).reshape(-1, 4, 4)
    return Trajectory(tracks.timestamp[frames].astype(np.float64), T, "trajectory")
