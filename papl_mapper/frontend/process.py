"""The frontend: one recording -> `Tracks` (undistorted observations with persistent track ids).

Per frame: KLT point tracks, segments (EDLines/LSD) with their tracks, keyframe choice, and on
keyframes ORB/LBD descriptors with re-association of lost tracks. Vanishing directions run
afterwards on the stored segments of all frames: the vertical is initialised from the first
frames, then tracked while each frame gets its Atlanta directions and structural labels.
Frames without texture (near-uniform) are skipped; their indices are in `Tracks.skipped_frames`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from papl_mapper.errors import GeometryError, InputError
from papl_mapper.frontend.camera import Undistorter, fit_camera
from papl_mapper.frontend.keyframes import KeyframeConfig, KeyframeSelector
from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.lines import LBD, LineConfig, LineTracker, SegmentDetector
from papl_mapper.frontend.motion import common_points, rotation_from_bearings
from papl_mapper.frontend.points import PointConfig, PointTracker
from papl_mapper.frontend.vanishing import (
    VPConfig,
    classify_segments,
    estimate_frame,
    estimate_vertical,
    update_vertical,
)
from papl_mapper.frontend.video import Frame, Recording
from papl_mapper.map import Camera
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]
# seconds per step; with parallel=True "lines" runs in a worker thread during "points" and
# "lines_wait" is the main thread waiting for it; "decode" is waiting for the decoder thread
STEPS = (
    "decode",
    "convert",
    "points",
    "lines",
    "lines_wait",
    "line_tracking",
    "keyframes",
    "descriptors",
    "undistort",
    "vp",
)


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
    vp: VPConfig = field(default_factory=lambda: VPConfig(track_gate_deg=3.0))
    """Vanishing directions (Atlanta world with a vertical prior). The vertical prior is carried
    from frame to frame by the point tracks' rotation (about 0.1 deg error per frame on the
    synthetic corridor), so a frame's refined vertical is blended in only within 3 deg of it
    (2, 3, 5 deg measured on the corridor: 3 gave the lowest vertical error at 640 and 1280 px)."""
    vanishing: bool = True
    """Estimate vanishing directions and structural labels (False: all segments -1)."""
    report_tracked_vertical: bool = True
    """Report the tracked vertical (carried by the point rotation, blended with each frame's
    refined one) as the frame's vertical direction, instead of the frame's own refinement, which
    is off by several degrees in frames with few vertical segments. Not with vp.use_vertical_prior
    off (that ablation reports each frame's own directions)."""
    vertical_init_frames: int = 30
    """The vertical is initialised from the segments of this many first frames."""
    min_texture_std: float = 2.0
    """Frames whose gray-level standard deviation is below this are skipped as textureless."""
    work_max_size: int = 640
    """Point tracking, ORB, LBD and keyframe parallax run on the frame downscaled so its longer side
    is at most this (coordinates are mapped back to full resolution; pixel settings of points and
    keyframes are in these work pixels); segments are detected at full resolution."""
    vp_stride: int = 1
    """Estimate vanishing directions on every n-th frame and on keyframes; frames between reuse the
    last estimate's directions and classify their own segments against them (1 = every frame)."""
    segments_max_size: int = 0
    """Detect segments on the frame downscaled to this longer side (0: full resolution). Faster on
    large frames; endpoints are mapped back to full resolution, min_length_px is in these pixels."""
    parallel: bool = False
    """Detect segments in a worker thread while points are tracked. Off by default: on the 2-core
    benchmark machine under load it was slower than sequential (OpenCV already uses its own threads)."""


MIN_ROTATION_POINTS = 15  # common point tracks needed to carry the vertical to the next frame

PRESETS = {
    "accurate": {},
    "realtime": {"segments_max_size": 640, "vp_stride": 3},
}
"""Named presets: changes to the FrontendConfig defaults ("accurate" is the default)."""


def frontend_preset(name: str) -> FrontendConfig:
    """The FrontendConfig of a named preset; InputError for an unknown name."""
    if name not in PRESETS:
        raise InputError(f"unknown frontend preset {name!r}; known: {', '.join(PRESETS)}")
    return dataclasses.replace(FrontendConfig(), **PRESETS[name])


@dataclass
class FrontendStats:
    """What a run measured: seconds per step, counts; filled when passed to `process`."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STEPS, 0.0))
    frames: int = 0
    skipped: int = 0
    keyframes: int = 0
    keyframe_reasons: dict[str, int] = field(default_factory=dict)  # first/forced/parallax/survival/...
    points_per_frame: float = 0.0
    segments_per_frame: float = 0.0
    vp_failures: int = 0
    vertical_rotations: int = 0  # frames whose vertical prior was rotated by the point-track rotation
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
    camera = fit_camera(camera, recording.width, recording.height, name=f"camera for {recording.path}")
    run = _Run(recording, camera, config, stats)
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="segments") if config.parallel else None
    try:
        for done, frame in enumerate(recording, 1):
            message = run.frame(frame, pool)
            if progress:
                progress(done, run.total, message)
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    tracks = run.finish()
    stats.wall_seconds = time.perf_counter() - wall0
    return tracks


def _timed(fn: Callable, *args: object) -> tuple:
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


class _Run:
    """State of one `process` call: the trackers and the growing observation lists."""

    def __init__(self, recording: Recording, camera: Camera, config: FrontendConfig, stats: FrontendStats):
        w, h = recording.width, recording.height
        self.recording, self.config, self.stats = recording, config, stats
        self.und = Undistorter(camera)
        s = min(1.0, config.work_max_size / max(w, h))
        self.work_size = (max(1, round(w * s)), max(1, round(h * s)))
        self.work_scale = np.array([self.work_size[0] / w, self.work_size[1] / h])  # work px per full px
        self.points = PointTracker(config.points, config.flow, *self.work_size)
        self.detector = SegmentDetector(config.lines)
        self.lines = LineTracker(config.lines)
        self.lbd = LBD()
        self.selector = KeyframeSelector(config.keyframes)
        self.total = recording.expected_frames()
        self.done = 0
        self.prev_gray: np.ndarray | None = None
        self.prev_small: np.ndarray | None = None
        self.frame_index: list[int] = []
        self.timestamps: list[float] = []
        self.is_kf: list[bool] = []
        self.skipped: list[int] = []
        self.p_frame, self.p_track, self.p_uv = [], [], []
        self.l_frame, self.l_track, self.l_xy = [], [], []
        self.pd_row, self.pd_desc, self.ld_row, self.ld_desc = [], [], [], []
        self.n_points = self.n_lines = 0
        self._t_last = time.perf_counter()

    def _segments(self, gray: np.ndarray) -> np.ndarray:
        """Segments (S, 4) in full-resolution pixels, detected at segments_max_size if set."""
        h, w = gray.shape[:2]
        limit = self.config.segments_max_size
        if limit <= 0 or max(w, h) <= limit:
            return self.detector.detect(gray)
        s = limit / max(w, h)
        size = (max(1, round(w * s)), max(1, round(h * s)))
        small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        scale = np.array([size[0] / w, size[1] / h] * 2)
        return (self.detector.detect(small) + 0.5) / scale - 0.5

    def _to_full(self, uv: np.ndarray) -> np.ndarray:
        """Work-image pixels (N, 2) -> full-resolution pixels (integer pixel centres)."""
        return (np.asarray(uv, np.float64) + 0.5) / self.work_scale - 0.5

    def frame(self, frame: Frame, pool: ThreadPoolExecutor | None) -> str:
        """Process one decoded frame; returns a progress message."""
        sec = self.stats.seconds
        t1 = time.perf_counter()
        sec["decode"] += t1 - self._t_last  # waiting for the decoder thread
        self.done += 1
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        small = gray
        if self.work_size != (gray.shape[1], gray.shape[0]):
            small = cv2.resize(gray, self.work_size, interpolation=cv2.INTER_AREA)
        t2 = time.perf_counter()
        sec["convert"] += t2 - t1
        if _is_textureless(gray, self.config.min_texture_std):
            self.skipped.append(frame.index)
            self.prev_gray = self.prev_small = None
            self._t_last = time.perf_counter()
            return f"frame {frame.index}: skipped (no texture)"
        points, lines = self.points, self.lines
        restart = self.prev_gray is None
        pending = pool.submit(_timed, self._segments, gray) if pool is not None else None
        points.step(small, self.prev_small, force_detect=restart)
        uv = self._to_full(points.uv)
        t4 = time.perf_counter()
        sec["points"] += t4 - t2
        segs, line_seconds = pending.result() if pending is not None else _timed(self._segments, gray)
        t5 = time.perf_counter()
        sec["lines"] += line_seconds
        if pending is not None:
            sec["lines_wait"] += t5 - t4
        if restart:
            lines.step(segs, None, None)
        else:
            lines.step(segs, self._to_full(points.flow_from), self._to_full(points.flow_to))
        t6 = time.perf_counter()
        sec["line_tracking"] += t6 - t5
        kf = self.selector.update(points.ids, points.uv, force=restart)
        if kf:
            reasons = self.stats.keyframe_reasons
            reasons[self.selector.last_reason] = reasons.get(self.selector.last_reason, 0) + 1
        t7 = time.perf_counter()
        sec["keyframes"] += t7 - t6
        row = len(self.frame_index)
        if kf:
            pids, pdesc = points.keyframe(small)
            self.selector.set_reference(points.ids, points.uv)
            lids, ldesc = lines.keyframe(small, self.lbd, self.work_scale)
            # descriptor rows: position of each described id among this frame's observations
            self.pd_row.append(self.n_points + _positions(points.ids, pids))
            self.pd_desc.append(pdesc)
            self.ld_row.append(self.n_lines + _positions(lines.ids, lids))
            self.ld_desc.append(ldesc)
        t8 = time.perf_counter()
        sec["descriptors"] += t8 - t7
        self.frame_index.append(frame.index)
        self.timestamps.append(frame.timestamp_s)
        self.is_kf.append(kf)
        k, s = len(points.ids), len(lines.ids)
        self.p_frame.append(np.full(k, row, np.int64))
        self.p_track.append(points.ids.copy())
        self.p_uv.append(self.und.points(uv))
        self.l_frame.append(np.full(s, row, np.int64))
        self.l_track.append(lines.ids.copy())
        self.l_xy.append(self.und.segments(lines.segs))
        self.n_points += k
        self.n_lines += s
        self.prev_gray, self.prev_small = gray, small
        self._t_last = time.perf_counter()
        sec["undistort"] += self._t_last - t8
        return f"frame {frame.index}: {k} points, {s} segments{', keyframe' if kf else ''}"

    def finish(self) -> Tracks:
        """Vanishing directions over all frames, then the Tracks."""
        rec, stats = self.recording, self.stats
        if rec.stopped_early:
            log.warning("%s: decoding stopped early: %s", rec.path, rec.stop_message)
        if self.skipped:
            log.warning("%s: skipped %d textureless frames (of %d)", rec.path, len(self.skipped), self.done)
        if not self.frame_index:
            raise InputError(
                f"{rec.path}: all {self.done} decoded frames are textureless (uniform or black); "
                "nothing to track"
            )
        F = len(self.frame_index)
        is_kf = np.array(self.is_kf, bool)
        line_frame = np.concatenate(self.l_frame)
        line_xy = np.concatenate(self.l_xy).reshape(-1, 4)
        K = self.und.undistorted_camera.K
        t0 = time.perf_counter()
        pts = (np.concatenate(self.p_frame), np.concatenate(self.p_track), np.concatenate(self.p_uv))
        line_vp, vp_dirs, vertical_vp = _vanishing(line_frame, line_xy, pts, is_kf, K, self.config, stats)
        stats.seconds["vp"] += time.perf_counter() - t0
        tracks = Tracks(
            camera=self.und.undistorted_camera,
            frame_index=np.array(self.frame_index, np.int64),
            timestamp=np.array(self.timestamps, np.float64),
            is_keyframe=is_kf,
            point_frame=np.concatenate(self.p_frame),
            point_track=self.points.resolve(np.concatenate(self.p_track)),
            point_uv=np.concatenate(self.p_uv).reshape(-1, 2),
            line_frame=line_frame,
            line_track=self.lines.resolve(np.concatenate(self.l_track)),
            line_xy=line_xy,
            line_vp=line_vp,
            vp_dirs_c=vp_dirs,
            vertical_vp=vertical_vp,
            point_desc_row=_cat(self.pd_row, np.int64, (0,)),
            point_desc=_cat(self.pd_desc, np.uint8, (0, 32)),
            line_desc_row=_cat(self.ld_row, np.int64, (0,)),
            line_desc=_cat(self.ld_desc, np.uint8, (0, 32)),
            skipped_frames=np.array(self.skipped, np.int64),
        )
        tracks.validate()
        stats.frames = F
        stats.skipped = len(self.skipped)
        stats.keyframes = int(is_kf.sum())
        stats.points_per_frame = len(tracks.point_frame) / F
        stats.segments_per_frame = len(tracks.line_frame) / F
        log.info(
            "%s: %d frames (%d skipped), %d keyframes, %.0f points and %.0f segments per frame",
            rec.path,
            F,
            len(self.skipped),
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


def _initial_vertical(
    segments: list[np.ndarray], rotation: Callable, K: np.ndarray, config: FrontendConfig
) -> np.ndarray | None:
    """The vertical of the first frame, from the first frames' own verticals (no prior).

    Single-frame verticals are either good (0.1-0.3 deg on the synthetic corridor) or far off, so
    the largest group agreeing within track_gate_deg is found, and its earliest frame's vertical
    is rotated back into the first frame by the chained point-track rotations (chaining all of
    them would add their drift). None when no frame shows a vertical or the chain is broken.
    """
    R_f0 = np.eye(3)  # x_f = R_f0 x_0
    chain: list[np.ndarray | None] = []
    found: list[tuple[int, np.ndarray]] = []
    for f, segs in enumerate(segments):
        if f > 0 and R_f0 is not None:
            R = rotation(f - 1, f)
            R_f0 = None if R is None else R @ R_f0
        chain.append(R_f0)
        try:
            res = estimate_frame(segs, K, None, config.vp)
        except GeometryError:
            continue
        if res.vertical_c is not None:
            v = res.vertical_c
            found.append((f, v if v[1] <= 0 else -v))  # up is -y for an upright camera
    if not found:
        return None
    V = np.array([v for _, v in found])
    agree = np.degrees(np.arccos(np.clip(np.abs(V @ V.T), 0, 1))) <= config.vp.track_gate_deg
    group = np.flatnonzero(agree[int(np.argmax(agree.sum(axis=1)))])
    f, v = found[int(group[0])]
    if chain[f] is None:
        return None
    v = chain[f].T @ v
    return v / np.linalg.norm(v)


def _vanishing(
    line_frame: np.ndarray,
    line_xy: np.ndarray,
    points: tuple[np.ndarray, np.ndarray, np.ndarray],
    is_keyframe: np.ndarray,
    K: np.ndarray,
    config: FrontendConfig,
    stats: FrontendStats,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame VPs and labels: vertical from the first frames, then tracked. (Kl,), (F, V, 3), (F,).

    The tracked vertical is rotated from frame to frame by the relative rotation of the point
    tracks (`points`: frame row, track id, undistorted pixels; a robust rotation-only fit, which
    moved the vertical within 0.06-0.08 deg median per frame on the synthetic corridor, as well as
    essential-matrix RANSAC at a tenth of its cost), then blended with each frame's refined vertical.
    """
    n_frames = len(is_keyframe)
    labels = np.full(len(line_frame), -1, np.int64)
    if not config.vanishing:
        stats.vertical_source = "off"
        return labels, np.full((n_frames, 3, 3), np.nan), np.full(n_frames, -1, np.int64)
    bounds = np.searchsorted(line_frame, np.arange(n_frames + 1))
    per_frame = [line_xy[bounds[f] : bounds[f + 1]] for f in range(n_frames)]
    p_frame, p_track, p_uv = points
    p_bounds = np.searchsorted(p_frame, np.arange(n_frames + 1))

    def rotation(a: int, b: int) -> np.ndarray | None:
        sa, sb = slice(p_bounds[a], p_bounds[a + 1]), slice(p_bounds[b], p_bounds[b + 1])
        uv_a, uv_b = common_points(p_track[sa], p_uv[sa], p_track[sb], p_uv[sb])
        if len(uv_a) < MIN_ROTATION_POINTS:
            return None
        return rotation_from_bearings(uv_a, uv_b, K)

    vertical = _initial_vertical(per_frame[: config.vertical_init_frames], rotation, K, config)
    if vertical is not None:
        stats.vertical_source = "initialised"
    else:
        try:  # no rotation chain (e.g. tracking broke at once): the frames' verticals averaged as they are
            vertical = estimate_vertical(per_frame[: config.vertical_init_frames], K, config.vp)
            stats.vertical_source = "initialised-unaligned"
        except GeometryError as exc:
            log.warning("vanishing points: %s; estimating each frame without a vertical prior", exc)
            stats.vertical_source = "per-frame"
    results: list = [None] * n_frames
    stride = max(1, config.vp_stride)
    last = None
    prev = None  # row of the frame the tracked vertical refers to
    for f in range(n_frames):
        if last is not None and f % stride and not is_keyframe[f]:
            # between estimates: the last directions, this frame's segments classified against them
            labels[bounds[f] : bounds[f + 1]] = classify_segments(per_frame[f], K, last.dirs_c, config.vp)
            results[f] = last
            continue
        if vertical is not None and prev is not None:
            R = rotation(prev, f)
            if R is not None:
                vertical = update_vertical(vertical, None, R, config.vp)
                stats.vertical_rotations += 1
        prev = f
        try:
            res = estimate_frame(per_frame[f], K, vertical, config.vp)
        except GeometryError as exc:
            log.debug("frame row %d: no vanishing directions (%s)", f, exc)
            stats.vp_failures += 1
            continue
        labels[bounds[f] : bounds[f + 1]] = res.labels
        if vertical is not None:
            vertical = update_vertical(vertical, res.vertical_c, None, config.vp)
            if config.report_tracked_vertical and config.vp.use_vertical_prior and res.vertical_index == 0:
                dirs_c = res.dirs_c.copy()
                dirs_c[0] = vertical
                res = dataclasses.replace(res, dirs_c=dirs_c)
        results[f] = last = res
    V = max([3] + [len(r.dirs_c) for r in results if r is not None])
    dirs = np.full((n_frames, V, 3), np.nan)
    vertical_vp = np.full(n_frames, -1, np.int64)
    for f, r in enumerate(results):
        if r is not None:
            dirs[f, : len(r.dirs_c)] = r.dirs_c
            vertical_vp[f] = r.vertical_index
    return labels, dirs, vertical_vp
