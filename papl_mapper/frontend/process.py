"""The frontend: one recording -> `Tracks` (undistorted observations with persistent track ids).

Per frame: KLT point tracks, segments (EDLines/LSD) with their tracks, keyframe choice, and on
keyframes ORB/LBD descriptors with re-association of lost tracks. Vanishing directions run
afterwards on the stored segments of all frames: the vertical is initialised from the first
frames, then tracked while each frame gets its Atlanta directions and structural labels.
Frames without texture (near-uniform) are skipped; their indices are in `Tracks.skipped_frames`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from papl_mapper.errors import GeometryError, InputError
from papl_mapper.frontend.camera import Undistorter, fit_camera
from papl_mapper.frontend.keyframes import KeyframeConfig, KeyframeSelector
from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.lines import LBD, LineConfig, LineTracker, SegmentDetector
from papl_mapper.frontend.points import PointConfig, PointTracker
from papl_mapper.frontend.vanishing import VPConfig, estimate_frame, estimate_vertical, update_vertical
from papl_mapper.frontend.video import Recording
from papl_mapper.map import Camera
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]
STEPS = ("decode", "convert", "points", "lines", "line_tracking", "keyframes", "descriptors", "vp")


@dataclass
class FrontendConfig:
    """Settings of the whole frontend, nested by step."""

    flow: FlowConfig = field(default_factory=FlowConfig)
    """KLT settings shared by points and line prediction."""
    points: PointConfig = field(default_factory=PointConfig)
    """Corner detection, replenishment and ORB re-association."""
    lines: LineConfig = field(default_factory=LineConfig)
    """Segment detection, fusion, tracking and LBD."""
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    """Keyframe selection."""
    vp: VPConfig = field(default_factory=VPConfig)
    """Vanishing directions (Atlanta world with a vertical prior)."""
    vanishing: bool = True
    """Estimate vanishing directions and structural labels (False: all segments -1)."""
    vertical_init_frames: int = 30
    """The vertical is initialised from the segments of this many first frames."""
    min_texture_std: float = 2.0
    """Frames whose gray-level standard deviation is below this are skipped as textureless."""


@dataclass
class FrontendStats:
    """What a run measured: seconds per step, counts; filled when passed to `process`."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STEPS, 0.0))
    frames: int = 0
    skipped: int = 0
    keyframes: int = 0
    points_per_frame: float = 0.0
    segments_per_frame: float = 0.0
    vp_failures: int = 0
    vertical_source: str = ""  # "initialised", "per-frame" (no vertical found) or "off"
    wall_seconds: float = 0.0


def _is_textureless(gray: np.ndarray, min_std: float) -> bool:
    small = gray[::4, ::4]
    return float(small.std()) < min_std


def process(
    recording: Recording,
    camera: Camera,
    config: FrontendConfig | None = None,
    progress: ProgressCallback | None = None,
    stats: FrontendStats | None = None,
) -> Tracks:
    """Observations of a recording: point and segment tracks (undistorted pixels), keyframes, VPs.

    `camera` is fitted to the recording's (possibly downscaled) size: scaled when the aspect ratio
    matches, InputError otherwise. Raises InputError when every frame is textureless.
    """
    config = config or FrontendConfig()
    stats = stats if stats is not None else FrontendStats()
    wall0 = time.perf_counter()
    w, h = recording.width, recording.height
    camera = fit_camera(camera, w, h, name=f"camera for {recording.path}")
    und = Undistorter(camera)
    points = PointTracker(config.points, config.flow, w, h)
    detector = SegmentDetector(config.lines)
    lines = LineTracker(config.lines)
    lbd = LBD()
    selector = KeyframeSelector(config.keyframes)
    sec = stats.seconds

    frame_index, timestamps, is_kf, skipped = [], [], [], []
    p_frame, p_track, p_uv = [], [], []
    l_frame, l_track, l_xy = [], [], []
    pd_row, pd_desc, ld_row, ld_desc = [], [], [], []
    n_points = n_lines = 0
    prev_gray = None
    total = recording.expected_frames()
    done = 0
    it = iter(recording)
    while True:
        t0 = time.perf_counter()
        frame = next(it, None)
        t1 = time.perf_counter()
        sec["decode"] += t1 - t0
        if frame is None:
            break
        done += 1
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        t2 = time.perf_counter()
        sec["convert"] += t2 - t1
        if _is_textureless(gray, config.min_texture_std):
            skipped.append(frame.index)
            prev_gray = None
            if progress:
                progress(done, total, f"frame {frame.index}: skipped (no texture)")
            continue
        t3 = t2
        restart = prev_gray is None
        points.step(gray, prev_gray, force_detect=restart)
        t4 = time.perf_counter()
        sec["points"] += t4 - t3
        segs = detector.detect(gray)
        t5 = time.perf_counter()
        sec["lines"] += t5 - t4
        if restart:
            lines.step(segs, None, None)
        else:
            lines.step(segs, points.flow_from, points.flow_to)
        t6 = time.perf_counter()
        sec["line_tracking"] += t6 - t5
        kf = selector.update(points.ids, points.uv, force=restart)
        t7 = time.perf_counter()
        sec["keyframes"] += t7 - t6
        row = len(frame_index)
        if kf:
            pids, pdesc = points.keyframe(gray)
            selector.set_reference(points.ids, points.uv)
            lids, ldesc = lines.keyframe(gray, lbd)
            # descriptor rows: position of each described id among this frame's observations
            pd_row.append(n_points + _positions(points.ids, pids))
            pd_desc.append(pdesc)
            ld_row.append(n_lines + _positions(lines.ids, lids))
            ld_desc.append(ldesc)
        sec["descriptors"] += time.perf_counter() - t7
        frame_index.append(frame.index)
        timestamps.append(frame.timestamp_s)
        is_kf.append(kf)
        k = len(points.ids)
        p_frame.append(np.full(k, row, np.int64))
        p_track.append(points.ids.copy())
        p_uv.append(und.points(points.uv))
        n_points += k
        s = len(lines.ids)
        l_frame.append(np.full(s, row, np.int64))
        l_track.append(lines.ids.copy())
        l_xy.append(und.segments(lines.segs))
        n_lines += s
        prev_gray = gray
        if progress:
            progress(
                done, total, f"frame {frame.index}: {k} points, {s} segments{', keyframe' if kf else ''}"
            )

    if recording.stopped_early:
        log.warning("%s: decoding stopped early: %s", recording.path, recording.stop_message)
    if skipped:
        log.warning("%s: skipped %d textureless frames (of %d)", recording.path, len(skipped), done)
    if not frame_index:
        raise InputError(
            f"{recording.path}: all {done} decoded frames are textureless (uniform or black); "
            "nothing to track"
        )
    F = len(frame_index)
    line_frame = np.concatenate(l_frame)
    line_xy = np.concatenate(l_xy).reshape(-1, 4)
    t8 = time.perf_counter()
    line_vp, vp_dirs, vertical_vp = _vanishing(
        line_frame, line_xy, F, und.undistorted_camera.K, config, stats
    )
    sec["vp"] += time.perf_counter() - t8

    tracks = Tracks(
        camera=und.undistorted_camera,
        frame_index=np.array(frame_index, np.int64),
        timestamp=np.array(timestamps, np.float64),
        is_keyframe=np.array(is_kf, bool),
        point_frame=np.concatenate(p_frame),
        point_track=points.resolve(np.concatenate(p_track)),
        point_uv=np.concatenate(p_uv).reshape(-1, 2),
        line_frame=line_frame,
        line_track=lines.resolve(np.concatenate(l_track)),
        line_xy=line_xy,
        line_vp=line_vp,
        vp_dirs_c=vp_dirs,
        vertical_vp=vertical_vp,
        point_desc_row=_cat(pd_row, np.int64, (0,)),
        point_desc=_cat(pd_desc, np.uint8, (0, 32)),
        line_desc_row=_cat(ld_row, np.int64, (0,)),
        line_desc=_cat(ld_desc, np.uint8, (0, 32)),
        skipped_frames=np.array(skipped, np.int64),
    )
    tracks.validate()
    stats.frames = F
    stats.skipped = len(skipped)
    stats.keyframes = int(tracks.is_keyframe.sum())
    stats.points_per_frame = len(tracks.point_frame) / F
    stats.segments_per_frame = len(tracks.line_frame) / F
    stats.wall_seconds = time.perf_counter() - wall0
    log.info(
        "%s: %d frames (%d skipped), %d keyframes, %.0f points and %.0f segments per frame",
        recording.path,
        F,
        len(skipped),
        stats.keyframes,
        stats.points_per_frame,
        stats.segments_per_frame,
    )
    return tracks


def _positions(all_ids: np.ndarray, some: np.ndarray) -> np.ndarray:
    """Index of each of `some` in `all_ids` (both unique)."""
    order = np.argsort(all_ids)
    return order[np.searchsorted(all_ids, some, sorter=order)].astype(np.int64)


def _cat(parts: list[np.ndarray], dtype: type, empty_shape: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(empty_shape, dtype)


def _vanishing(
    line_frame: np.ndarray,
    line_xy: np.ndarray,
    n_frames: int,
    K: np.ndarray,
    config: FrontendConfig,
    stats: FrontendStats,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame VPs and labels: vertical from the first frames, then tracked. (Kl,), (F, V, 3), (F,)."""
    labels = np.full(len(line_frame), -1, np.int64)
    if not config.vanishing:
        stats.vertical_source = "off"
        return labels, np.full((n_frames, 3, 3), np.nan), np.full(n_frames, -1, np.int64)
    bounds = np.searchsorted(line_frame, np.arange(n_frames + 1))
    per_frame = [line_xy[bounds[f] : bounds[f + 1]] for f in range(n_frames)]
    vertical = None
    try:
        vertical = estimate_vertical(per_frame[: config.vertical_init_frames], K, config.vp)
        stats.vertical_source = "initialised"
    except GeometryError as exc:
        log.warning("vanishing points: %s; estimating each frame without a vertical prior", exc)
        stats.vertical_source = "per-frame"
    results: list = [None] * n_frames
    for f in range(n_frames):
        try:
            res = estimate_frame(per_frame[f], K, vertical, config.vp)
        except GeometryError as exc:
            log.debug("frame row %d: no vanishing directions (%s)", f, exc)
            stats.vp_failures += 1
            continue
        results[f] = res
        labels[bounds[f] : bounds[f + 1]] = res.labels
        if vertical is not None:
            vertical = update_vertical(vertical, res.vertical_c, None, config.vp)
    V = max([3] + [len(r.dirs_c) for r in results if r is not None])
    dirs = np.full((n_frames, V, 3), np.nan)
    vertical_vp = np.full(n_frames, -1, np.int64)
    for f, r in enumerate(results):
        if r is not None:
            dirs[f, : len(r.dirs_c)] = r.dirs_c
            vertical_vp[f] = r.vertical_index
    return labels, dirs, vertical_vp
