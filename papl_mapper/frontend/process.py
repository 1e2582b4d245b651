"""The frontend: one recording -> `Tracks` (undistorted observations with persistent track ids).

Per frame: KLT point tracks, segments (EDLines/LSD) with their tracks, keyframe choice, and on
keyframes ORB/LBD descriptors (LBD also re-associates lost segment tracks). Vanishing directions follow
frame by frame (in a worker thread, overlapping the next frames' work): the vertical is initialised
from the first frames, then tracked while each frame gets its Atlanta directions and structural labels.
Frames without texture (near-uniform) are skipped; their indices are in `Tracks.skipped_frames`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.frontend.camera import Undistorter, fit_camera
from papl_mapper.frontend.features import FeatureConfig, KeyframeFeatures, SiftDetector, feature_tracks
from papl_mapper.frontend.keyframes import KeyframeConfig, KeyframeSelector
from papl_mapper.frontend.klt import FlowConfig
from papl_mapper.frontend.line_links import LineLinkConfig, link_line_tracks
from papl_mapper.frontend.lines import LBD, LineConfig, LineTracker, SegmentDetector
from papl_mapper.frontend.points import PointConfig, PointTracker
from papl_mapper.frontend.vanishing import VPConfig
from papl_mapper.frontend.video import Frame, Recording
from papl_mapper.frontend.vp_tracking import VanishingTracker, VPTrackingConfig
from papl_mapper.map import Camera
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]
# seconds per step; with parallel=True "lines" runs in a worker thread during "points" and
# "lines_wait" is the main thread waiting for it; "decode" is waiting for the decoder thread;
# with vp_thread=True "vp" runs in a worker thread beside the next frames and "vp_wait" is the main
# thread waiting for it after the last frame; with parallel=True the keyframes' SIFT keypoints are
# detected in a worker thread and "features_wait" is the main thread waiting for the last of them
STEPS = (
    "decode",
    "features_wait",
    "matching",
    "convert",
    "points",
    "lines",
    "lines_wait",
    "line_tracking",
    "keyframes",
    "descriptors",
    "undistort",
    "vp",
    "vp_wait",
)


@dataclass
class FrontendConfig:
    """Settings of the whole frontend, nested by step."""

    flow: FlowConfig = field(default_factory=FlowConfig)
    """KLT settings shared by points and line prediction."""
    points: PointConfig = field(default_factory=PointConfig)
    """Corner detection and replenishment."""
    lines: LineConfig = field(default_factory=LineConfig)
    """Segment detection, fusion, tracking and LBD."""
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    """Keyframe selection."""
    features: FeatureConfig = field(default_factory=FeatureConfig)
    """Wide-baseline SIFT features on keyframes, matched where KLT breaks (jumps, photo sets)."""
    line_links: LineLinkConfig = field(default_factory=LineLinkConfig)
    """Segment tracks joined across the keyframe pairs the wide-baseline features verified."""
    vp: VPConfig = field(default_factory=lambda: VPConfig(track_gate_deg=3.0))
    """Vanishing directions (Atlanta world with a vertical prior). The vertical prior is carried
    from frame to frame by the point tracks' rotation (a small error per frame), so a frame's refined
    vertical is blended in only within 3 deg of it (of 2, 3 and 5 deg, 3 gave the lowest vertical error
    on the synthetic corridor at both resolutions tried)."""
    vanishing: bool = True
    """Estimate vanishing directions and structural labels (False: all segments -1)."""
    report_tracked_vertical: bool = True
    """Report the tracked vertical (carried by the point rotation, blended with each frame's
    refined one) as the frame's vertical direction, instead of the frame's own refinement, which
    is off by several degrees in frames with few vertical segments. Not with vp.use_vertical_prior
    off (that ablation reports each frame's own directions)."""
    vertical_init_frames: int = 30
    """The vertical is initialised from the segments of at most this many first frames (fewer once
    their vote is settled: `VPTrackingConfig.init_frames`)."""
    min_texture_std: float = 2.0
    """Frames whose gray-level standard deviation is below this are skipped as textureless."""
    work_max_size: int = 1280
    """Point tracking, ORB, LBD and keyframe parallax run on the frame downscaled so its longer side
    is at most this (coordinates are mapped back to full resolution; pixel settings of points and
    keyframes are in these work pixels); segments are detected at full resolution. Tracking at half
    resolution halves the corners' precision, which real driving video pays for in drift (see
    benchmarks/results/real.json); 1280 bounds the cost of a 1080p or larger video."""
    vp_stride: int = 1
    """Estimate vanishing directions on every n-th frame and on keyframes; frames between reuse the
    last estimate's directions and classify their own segments against them (1 = every frame)."""
    segments_max_size: int = 0
    """Detect segments on the frame downscaled to this longer side (0: full resolution). Faster on
    large frames; endpoints are mapped back to full resolution, min_length_px is in these pixels."""
    parallel: bool = True
    """Detect segments in a worker thread while points are tracked (OpenCV's EDLines releases the
    GIL): the main thread's CPU per frame drops (benchmarks/RESULTS.md, frontend_throughput); on a
    fully loaded machine the wall time is the same either way."""
    opencv_threads: int = 0
    """OpenCV's own worker threads while `process` runs (cv2.setNumThreads; restored afterwards);
    0 leaves OpenCV's setting as it is."""
    vp_thread: bool = True
    """Estimate vanishing directions in a worker thread as frames arrive, overlapping the next
    frames' work (numpy and OpenCV release the GIL for much of it); False: in the main thread after
    each frame. The results are the same."""


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
    cpu_seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STEPS, 0.0))
    """CPU seconds per step of the thread running it (OpenCV's own worker threads not included)."""
    frames: int = 0
    skipped: int = 0
    bad_frames: list[str] = field(default_factory=list)  # frames that did not decode: "name (reason)"
    breaks: int = 0  # frames where KLT lost most tracks of the previous frame (a jump)
    exposure_compensated: int = 0  # frames whose exposure change from the previous one KLT compensated
    feature_tracks: int = 0  # tracks chained from SIFT matches across weak KLT links
    line_tracks_joined: int = 0  # segment tracks joined into others across verified keyframe pairs
    feature_pairs_verified: int = 0
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
    seed: int = 0,
) -> Tracks:
    """Observations of a recording: point and segment tracks (undistorted pixels), keyframes, VPs
    (`seed` seeds the random choices: vanishing-point search, feature verification).

    `camera` is fitted to the recording's (possibly downscaled) size: scaled when the aspect ratio
    matches, InputError otherwise. Raises InputError when every frame is textureless.
    """
    config = config or FrontendConfig()
    stats = stats if stats is not None else FrontendStats()
    wall0 = time.perf_counter()
    camera = fit_camera(camera, recording.width, recording.height, name=f"camera for {recording.path}")
    cv_threads = cv2.getNumThreads()
    if config.opencv_threads > 0:
        cv2.setNumThreads(config.opencv_threads)
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="segments") if config.parallel else None
    vp_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vanishing") if config.vp_thread else None
    # two SIFT workers: the keyframes' detections queue up behind the frames and the last ones are
    # waited for at the end, where one worker would leave a core idle
    features_pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="sift") if config.parallel else None
    run = _Run(recording, camera, config, stats, vp_pool, features_pool, seed)
    try:
        for done, frame in enumerate(recording, 1):
            message = run.frame(frame, pool)
            if progress:
                progress(done, run.total, message)
        tracks = run.finish()
    finally:
        for p in (pool, vp_pool, features_pool):
            if p is not None:
                p.shutdown(wait=True, cancel_futures=True)
        cv2.setNumThreads(cv_threads)
    stats.wall_seconds = time.perf_counter() - wall0
    return tracks


def _timed(fn: Callable, *args: object) -> tuple:
    """fn(*args), its wall seconds and the CPU seconds of the calling thread."""
    t0, c0 = time.perf_counter(), time.thread_time()
    out = fn(*args)
    return out, time.perf_counter() - t0, time.thread_time() - c0


class _Clock:
    """Adds the wall and (calling thread's) CPU seconds since the last lap to a step of the stats."""

    def __init__(self, stats: FrontendStats):
        self.stats = stats
        self.restart()

    def restart(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.thread_time()

    def lap(self, step: str) -> None:
        wall, cpu = time.perf_counter(), time.thread_time()
        self.stats.seconds[step] += wall - self.wall
        self.stats.cpu_seconds[step] += cpu - self.cpu
        self.wall, self.cpu = wall, cpu


class _Run:
    """State of one `process` call: the trackers and the growing observation lists."""

    def __init__(
        self,
        recording: Recording,
        camera: Camera,
        config: FrontendConfig,
        stats: FrontendStats,
        vp_pool: ThreadPoolExecutor | None = None,
        features_pool: ThreadPoolExecutor | None = None,
        seed: int = 0,
    ):
        w, h = recording.width, recording.height
        self.recording, self.config, self.stats, self.seed = recording, config, stats, seed
        self.und = Undistorter(camera)
        s = min(1.0, config.work_max_size / max(w, h))
        self.work_size = (max(1, round(w * s)), max(1, round(h * s)))
        self.work_scale = np.array([self.work_size[0] / w, self.work_size[1] / h])  # work px per full px
        self.points = PointTracker(config.points, config.flow, *self.work_size)
        self.detector = SegmentDetector(config.lines)
        self.lines = LineTracker(config.lines)
        self.lbd = LBD()
        self.selector = KeyframeSelector(config.keyframes)
        self.sift = SiftDetector(config.features) if config.features.enabled else None
        self.feats = KeyframeFeatures()
        self.features_pool = features_pool
        self.feature_jobs: list[tuple[int, Future]] = []  # (frame row, its SIFT detection) per keyframe
        # the last keyframes (row, point ids, image, described) and how many more to describe
        self._recent_kf: deque[list] = deque(maxlen=max(1, config.features.window))
        self._describe_next = 0
        self.total = recording.expected_frames()
        self.done = 0
        self.prev_gray: np.ndarray | None = None
        self.prev_small: np.ndarray | None = None
        self.frame_index: list[int] = []
        self.timestamps: list[float] = []
        self.is_kf: list[bool] = []
        self.skipped: list[int] = []
        self.break_rows: list[int] = []  # frame rows that kept too few of the previous frame's KLT tracks
        self.p_frame, self.p_track, self.p_uv = [], [], []
        self.l_frame, self.l_track, self.l_xy = [], [], []
        self.pd_row, self.pd_desc, self.ld_row, self.ld_desc = [], [], [], []
        self.n_points = self.n_lines = 0
        self.vp = VanishingTracker(
            self.und.undistorted_camera.K,
            VPTrackingConfig(
                config.vp, config.vertical_init_frames, config.vp_stride, config.report_tracked_vertical
            ),
            seed,
        )
        self.vp_pool = vp_pool
        self.vp_jobs: deque[Future] = deque()
        self._clock = _Clock(stats)

    def _vp_add(self, segs: np.ndarray, ids: np.ndarray, uv: np.ndarray, kf: bool) -> None:
        _, wall, cpu = _timed(self.vp.add, segs, ids, uv, kf)
        self.stats.seconds["vp"] += wall
        self.stats.cpu_seconds["vp"] += cpu

    def _vp_collect(self, wait: bool) -> None:
        """Drop finished VP jobs (re-raising their errors); all of them when wait."""
        while self.vp_jobs and (wait or self.vp_jobs[0].done()):
            self.vp_jobs.popleft().result()

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

    def _is_break(self, ids: np.ndarray) -> bool:
        """KLT kept fewer than `break_survival` of the previous frame's tracks: the image jumped."""
        if not self.p_track or self.sift is None:
            return False
        prev = self.p_track[-1]
        return len(prev) > 0 and np.isin(prev, ids).mean() < self.config.features.break_survival

    def _keyframe_before_break(self) -> None:
        """Make the last processed frame a keyframe with features, so a match can bridge the break."""
        if self.sift is None or not self.is_kf or self.is_kf[-1] or self.prev_gray is None:
            return
        self.is_kf[-1] = True
        self.stats.keyframe_reasons["break"] = self.stats.keyframe_reasons.get("break", 0) + 1
        self._keyframe_features(len(self.is_kf) - 1, self.p_track[-1], self.prev_gray)

    def _keyframe_features(self, row: int, ids: np.ndarray, gray: np.ndarray, broken: bool = False) -> None:
        """SIFT keypoints on the keyframes within `features.window` of a weak KLT link (a break, or few
        tracks shared with the last keyframe), and only there: a video that KLT follows throughout pays
        nothing. The last `window` keyframe images are kept for this. Full-resolution keypoints: on the
        work image their precision halves (KITTI: 0.104 vs 0.069 m ATE)."""
        if self.sift is None:
            return
        cfg = self.config.features
        recent = self._recent_kf
        weak = bool(recent) and (broken or len(np.intersect1d(recent[-1][1], ids)) < cfg.weak_link_tracks)
        recent.append([row, ids.copy(), gray, False])
        if weak:
            self._describe_next = cfg.window
        elif self._describe_next > 0:
            self._describe_next -= 1
        else:
            return
        for kf in recent if weak else (recent[-1],):
            if not kf[3]:
                if self.features_pool is not None:
                    job = self.features_pool.submit(self.sift.detect, kf[2])
                else:
                    job = Future()
                    job.set_result(self.sift.detect(kf[2]))
                self.feature_jobs.append((kf[0], job))
                kf[3] = True

    def _collect_features(self) -> None:
        """The keyframes' SIFT keypoints, detected in the worker thread while later frames were tracked."""
        for row, job in self.feature_jobs:
            uv, sift, desc = job.result()
            self.feats.add(row, self.und.points(uv), sift, desc)
        self.feature_jobs = []

    def frame(self, frame: Frame, pool: ThreadPoolExecutor | None) -> str:
        """Process one decoded frame; returns a progress message."""
        clock = self._clock
        clock.lap("decode")  # waiting for the decoder thread
        self.done += 1
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        small = gray
        if self.work_size != (gray.shape[1], gray.shape[0]):
            small = cv2.resize(gray, self.work_size, interpolation=cv2.INTER_AREA)
        clock.lap("convert")
        if _is_textureless(gray, self.config.min_texture_std):
            self.skipped.append(frame.index)
            self._keyframe_before_break()
            self.prev_gray = self.prev_small = None
            clock.lap("convert")
            return f"frame {frame.index}: skipped (no texture)"
        points, lines = self.points, self.lines
        restart = self.prev_gray is None
        pending = pool.submit(_timed, self._segments, gray) if pool is not None else None
        points.step(small, self.prev_small, force_detect=restart)
        self.stats.exposure_compensated += points.gain != 1.0
        broken = not restart and self._is_break(points.ids)
        if broken:
            self.stats.breaks += 1
            self.break_rows.append(len(self.frame_index))
            self._keyframe_before_break()
        uv = self._to_full(points.uv)
        clock.lap("points")
        timed = pending.result() if pending is not None else _timed(self._segments, gray)
        segs, line_seconds, line_cpu = timed
        if pending is not None:
            clock.lap("lines_wait")
        else:
            clock.restart()
        self.stats.seconds["lines"] += line_seconds
        self.stats.cpu_seconds["lines"] += line_cpu
        if restart:
            lines.step(segs, None, None)
        else:
            lines.step(segs, self._to_full(points.flow_from), self._to_full(points.flow_to))
        clock.lap("line_tracking")
        kf = self.selector.update(points.ids, points.uv, force=restart or broken, t=frame.timestamp_s)
        if kf:
            reasons = self.stats.keyframe_reasons
            reasons[self.selector.last_reason] = reasons.get(self.selector.last_reason, 0) + 1
        clock.lap("keyframes")
        row = len(self.frame_index)
        if kf:
            pids, pdesc = points.keyframe(small)
            lids, ldesc = lines.keyframe(small, self.lbd, self.work_scale)
            # descriptor rows: position of each described id among this frame's observations
            self.pd_row.append(self.n_points + _positions(points.ids, pids))
            self.pd_desc.append(pdesc)
            self.ld_row.append(self.n_lines + _positions(lines.ids, lids))
            self.ld_desc.append(ldesc)
            self._keyframe_features(row, points.ids, gray, broken)
        clock.lap("descriptors")
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
        clock.lap("undistort")
        if self.config.vanishing:
            job = (self.l_xy[-1], self.p_track[-1], self.p_uv[-1], kf)
            if self.vp_pool is not None:
                self.vp_jobs.append(self.vp_pool.submit(self._vp_add, *job))
                self._vp_collect(wait=False)
            else:
                self._vp_add(*job)
        clock.restart()
        return f"frame {frame.index}: {k} points, {s} segments{', keyframe' if kf else ''}"

    def _point_observations(self, is_kf: np.ndarray) -> dict[str, Any]:
        """KLT point observations with the feature tracks matched across weak links added, in frame
        order, and the geometry of the keyframe pairs the features verified."""
        frame = np.concatenate(self.p_frame)
        track = np.concatenate(self.p_track)
        uv = np.concatenate(self.p_uv).reshape(-1, 2)
        desc_row = _cat(self.pd_row, np.int64, (0,))
        desc = _cat(self.pd_desc, np.uint8, (0, 32))
        out = {"frame": frame, "track": track, "uv": uv, "desc_row": desc_row, "desc": desc, "geometry": []}
        t0 = time.perf_counter()
        self._collect_features()
        self.stats.seconds["features_wait"] = time.perf_counter() - t0
        if self.sift is None or not self.feats.frame:
            return out
        t0 = time.perf_counter()
        ft = feature_tracks(
            self.feats,
            self.und.undistorted_camera.K,
            frame,
            track,
            int(track.max(initial=-1)) + 1,
            self.config.features,
            workers=2 if self.config.parallel else 1,
            seed=self.seed,
            breaks=np.array(self.break_rows, np.int64),
        )
        self.stats.seconds["matching"] = time.perf_counter() - t0
        self.stats.feature_tracks = len(np.unique(ft.track))
        self.stats.feature_pairs_verified = ft.pairs_verified
        if len(ft.frame) == 0:
            return out
        order = np.argsort(np.concatenate([frame, ft.frame]), kind="stable")
        new_pos = np.empty_like(order)
        new_pos[order] = np.arange(len(order))
        return {
            "frame": np.concatenate([frame, ft.frame])[order],
            "track": np.concatenate([track, ft.track])[order],
            "uv": np.concatenate([uv, ft.uv])[order],
            "desc_row": new_pos[np.concatenate([desc_row, len(frame) + np.arange(len(ft.frame))])],
            "desc": np.concatenate([desc, ft.desc]),
            "geometry": ft.geometry,
        }

    def finish(self) -> Tracks:
        """The Tracks, once the vanishing directions of all frames are in."""
        rec, stats = self.recording, self.stats
        if rec.stopped_early:
            log.warning("%s: decoding stopped early: %s", rec.path, rec.stop_message)
        if rec.bad_frames:
            log.warning("%s: %s", rec.path, rec.bad_frames_message())
            stats.bad_frames = [str(b) for b in rec.bad_frames]
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
        self._clock.restart()
        self._vp_collect(wait=True)
        if self.config.vanishing:
            labels, vp_dirs, vertical_vp = self.vp.result()
            line_vp = _cat(labels, np.int64, (0,))
            stats.vertical_source = self.vp.vertical_source
            stats.vp_failures, stats.vertical_rotations = self.vp.failures, self.vp.rotations
        else:
            stats.vertical_source = "off"
            line_vp = np.full(len(line_frame), -1, np.int64)
            vp_dirs, vertical_vp = np.full((F, 3, 3), np.nan), np.full(F, -1, np.int64)
        self._clock.lap("vp_wait")
        points = self._point_observations(is_kf)
        line_desc_row = _cat(self.ld_row, np.int64, (0,))
        line_desc = _cat(self.ld_desc, np.uint8, (0, 32))
        line_track, stats.line_tracks_joined = link_line_tracks(
            line_frame,
            self.lines.resolve(np.concatenate(self.l_track)),
            line_xy,
            line_desc_row,
            line_desc,
            points["geometry"],
            self.und.undistorted_camera.K,
            self.config.line_links,
            self.config.lines,
        )
        tracks = Tracks(
            camera=self.und.undistorted_camera,
            frame_index=np.array(self.frame_index, np.int64),
            timestamp=np.array(self.timestamps, np.float64),
            is_keyframe=is_kf,
            point_frame=points["frame"],
            point_track=points["track"],
            point_uv=points["uv"],
            line_frame=line_frame,
            line_track=line_track,
            line_xy=line_xy,
            line_vp=line_vp,
            vp_dirs_c=vp_dirs,
            vertical_vp=vertical_vp,
            point_desc_row=points["desc_row"],
            point_desc=points["desc"],
            line_desc_row=line_desc_row,
            line_desc=line_desc,
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
