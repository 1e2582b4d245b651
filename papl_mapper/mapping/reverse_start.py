"""The recording registered backwards: a second start for the global BA.

Registration chains poses frame after frame. In a fast turn (little translation, a view that changes
within a few frames) its windowed BA can settle on a wrong configuration, the rotation through the
turn off by degrees and the scale after it jumped, a basin the global BA does not leave; the same
tracks registered from the last frame to the first meet the turn from its other side and mostly do
not fall in it (benchmarks/results/notes.md). An offline mapper has the whole recording, so it tries
both. Each set of keyframe poses starts a points BA over every observation of the tracks at the
map's keyframes (not only over the observations the forward registration kept: those were chosen by
agreeing with it), outliers beyond the error limit culled first as before every BA. The two results
are judged by their poses alone on the same data (`second_start.pose_losses`: every track re-fitted
to the poses, errors capped), and the backward one is taken only when the tracks favour it
significantly (a paired test over the tracks, `second_start.paired_z`), so two starts that reach one
basin, or two the data cannot tell apart, keep the map as it was.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from papl_mapper.backend import BAConfig, global_ba
from papl_mapper.backend.ba import ProgressFn
from papl_mapper.errors import GeometryError, OptimizationError, UnmappableError
from papl_mapper.geometry.se3 import invert
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.geometry.triangulation import triangulate_points
from papl_mapper.map import Map
from papl_mapper.mapping.assemble import assemble_map, cull_observations
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.mapping.second_start import paired_z, pose_losses
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


@dataclass
class ReverseCheckConfig:
    """Settings of the second start from the recording registered backwards."""

    enabled: bool = True
    """Register the recording backwards too, and start the global BA from those keyframe poses where
    they fit every observation of the tracks better (costs about one more registration)."""
    worker: bool = True
    """Register backwards in a worker process on a second core, beside the forward registration (the
    answer is the same). Only where the job may use two cores: its CPU affinity, and OpenCV's thread
    count where the caller limited it (`papl-map batch --threads 1`, and on Ray)."""
    significance: float = 3.0
    """The backward poses are taken when the tracks' cost differences favour them by more than this
    many standard errors (a paired test over the tracks: the observations of one track share its
    errors, the tracks are the independent samples)."""


@dataclass
class ReverseCheck:
    """What the check found: how many of the map's keyframes the backward registration posed, the
    observations both starts were judged on, their costs, the paired test's z (negative: the backward
    poses fit better) and which poses were kept."""

    keyframes: int = 0
    posed_backward: int = 0
    observations: int = 0
    cost_forward: float | None = None
    cost_backward: float | None = None
    z: float | None = None
    kept: str = "forward"

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def backward_poses(
    reversed_tracks: Tracks, register: Callable[[Tracks], Registration]
) -> dict[int, np.ndarray]:
    """T_wc by frame row of the forward tracks of every frame that `register` poses in the main map of
    `reversed_tracks` (`Tracks.reversed`; the segments it leaves out have frames and scales of their
    own); none where it cannot register them (the check is then skipped, the forward map kept)."""
    n = len(reversed_tracks)
    try:
        reg = register(reversed_tracks)
    except (UnmappableError, GeometryError, OptimizationError) as exc:
        log.info("backward registration: none (%s)", str(exc).split(";")[0])
        return {}
    return {n - 1 - f: invert(T) for f, T in reg.poses().items()}


def _track_maps(tracks: Tracks, frames: np.ndarray, starts: list[np.ndarray]) -> list[Map]:
    """One points-only map per start (keyframe poses (N, 4, 4) at frame rows `frames`, in one frame and
    scale) over every observation of the tracks in those frames, with the same points in each: the
    tracks seen at least twice that some start triangulates. A start that cannot (the point would lie
    behind a camera) takes another's point: its observations then count as outliers against it, so a
    start is not judged on only the points that suit it."""
    sel = np.flatnonzero(np.isin(tracks.point_frame, frames))
    ids, point_row = np.unique(tracks.point_track[sel], return_inverse=True)
    kf_row = np.searchsorted(frames, tracks.point_frame[sel])
    uv = tracks.point_uv[sel]
    tri = [triangulate_points(point_row, T[kf_row], tracks.camera.K, uv, len(ids), 0.0) for T in starts]
    ok = np.array([t[1] for t in tri])
    keep = np.flatnonzero((np.bincount(point_row, minlength=len(ids)) >= 2) & ok.any(axis=0))
    fallback = np.array([t[0] for t in tri])[ok.argmax(axis=0), np.arange(len(ids))]  # a start's own, if any
    rows = sel[np.isin(point_row, keep)]
    maps = []
    for T_wc, (X, good) in zip(starts, tri, strict=True):
        X = np.where(good[:, None], X, fallback)
        maps.append(
            assemble_map(
                tracks,
                {int(f): T for f, T in zip(frames, T_wc, strict=True)},
                {int(ids[p]): X[p] for p in keep},
                LineEstimates.empty(),
                point_rows=rows,
            )
        )
    return maps


BAAside = Callable[[Map, BAConfig], Callable[[], Map]]
"""Starts a global BA of a map elsewhere (another process) and returns what waits for the adjusted map."""


def reverse_checked(
    m: Map,
    tracks: Tracks,
    backward: dict[int, np.ndarray],
    ba: BAConfig,
    max_error_px: float,
    cfg: ReverseCheckConfig | None = None,
    progress: ProgressFn | None = None,
    aside: BAAside | None = None,
) -> tuple[Map, ReverseCheck]:
    """`m` (a points map after its global BA) against the keyframe poses of the backward registration
    (`backward`, T_wc by frame row): both start a points BA over every observation of the tracks at
    m's keyframes (outliers culled first); where the backward one's poses fit the tracks significantly
    better (`cfg.significance`), the map that BA made, else `m`. Taken whole, not as poses for m's points: the
    observations the forward registration kept were chosen by agreeing with the poses that lost.
    `aside`: runs the backward start's BA beside the forward one's (else one after the other)."""
    cfg = cfg or ReverseCheckConfig()
    frames = m.keyframes.ids
    check = ReverseCheck(keyframes=len(frames), posed_backward=int(sum(int(f) in backward for f in frames)))
    if check.posed_backward < len(frames) or len(frames) < 3 or not ba.optimize_poses:
        return m, check  # the backward map does not hold every keyframe: no common problem to judge on
    T_back = np.stack([backward[int(f)] for f in frames])
    T_back = umeyama(T_back[:, :3, 3], m.keyframes.T_wc[:, :3, 3]).apply_poses(T_back)  # into m's frame
    try:
        starts = _track_maps(tracks, frames, [m.keyframes.T_wc, T_back])
        for start in starts:
            cull_observations(start, max_error_px, max_error_px, ba.min_views, 1)
        wait_backward = aside(starts[1], ba) if aside is not None else None
        ends = [global_ba(starts[0], ba, progress).map]
        ends.append(wait_backward() if wait_backward is not None else global_ba(starts[1], ba, progress).map)
    except (GeometryError, OptimizationError) as exc:
        log.info("backward registration: its BA failed (%s); the forward map kept", exc)
        return m, check
    (loss_f, track), (loss_b, _) = (
        pose_losses(tracks, frames, e.keyframes.T_wc, ba.point_sigma_px, ba.huber_k, max_error_px)
        for e in ends
    )
    check.observations = len(loss_f)
    check.cost_forward, check.cost_backward = float(loss_f.sum()), float(loss_b.sum())
    check.z = paired_z(loss_b - loss_f, track)
    better = check.z < -cfg.significance
    log.info(
        "backward registration: started from its poses, the BA over every observation of the tracks at "
        "the %d keyframes (%d) ends at cost %.6g against %.6g from the forward poses (z %.1f over the "
        "tracks): %s",
        len(frames),
        check.observations,
        check.cost_backward,
        check.cost_forward,
        check.z,
        "backward poses kept" if better else "forward poses kept",
    )
    if not better:
        return m, check
    check.kept = "backward"
    ends[1].metadata = dict(m.metadata)
    return ends[1], check
