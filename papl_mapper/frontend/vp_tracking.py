"""Per-frame vanishing directions with a tracked vertical, fed one frame at a time.

The vertical is initialised from the first frames (their own verticals, the largest agreeing group,
rotated back to the first frame by the point tracks' rotations), then carried from frame to frame by
the relative rotation of the point tracks and blended with each frame's refined vertical. Frames
arrive one by one (`add`), so the stage can run in a worker thread beside the frontend's per-frame
work; its results are the same whichever thread runs it.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from papl_mapper.errors import GeometryError
from papl_mapper.frontend.motion import common_points, rotation_from_bearings
from papl_mapper.frontend.vanishing import (
    VPConfig,
    VPResult,
    classify_segments,
    estimate_frame,
    estimate_vertical,
    update_vertical,
)

log = logging.getLogger(__name__)

MIN_ROTATION_POINTS = 15  # common point tracks needed to carry the vertical to the next frame


@dataclass
class VPTrackingConfig:
    """How the per-frame estimation is chained (the frontend fills it from its own config)."""

    vp: VPConfig
    """Thresholds of the per-frame estimation."""
    init_frames: int = 30
    """The vertical is initialised from the segments of at most this many first frames (sooner once
    the frames still to come could no longer outvote the agreeing group: `VanishingTracker._vote_decided`)."""
    stride: int = 1
    """Estimate on every n-th frame and on keyframes; frames between reuse the last directions."""
    report_tracked_vertical: bool = True
    """Report the tracked vertical as the frame's vertical (see FrontendConfig)."""


@dataclass
class _FrameIn:
    segs: np.ndarray  # (S, 4) undistorted pixels
    point_ids: np.ndarray  # (P,) track ids
    point_uv: np.ndarray  # (P, 2) undistorted pixels
    is_keyframe: bool


class VanishingTracker:
    """Feed frames in order with `add`; `result` gives labels, directions and the vertical's index."""

    def __init__(self, K: np.ndarray, config: VPTrackingConfig, seed: int = 0):
        self.K = np.asarray(K, np.float64)
        self.config = config
        self.seed = seed  # of the 2-line searches without a vertical prior
        self.vertical: np.ndarray | None = None
        self.vertical_source = ""  # "initialised", "initialised-unaligned" or "per-frame"
        self.failures = 0  # frames without vanishing directions
        self.rotations = 0  # frames whose vertical prior was rotated by the point-track rotation
        self._pending: list[_FrameIn] = []  # frames waiting for the vertical's initialisation
        # their chained rotations x_f = R_f0 x_0 (None once the chain broke) and own verticals (frame, v)
        self._chain: list[np.ndarray | None] = []
        self._found: list[tuple[int, np.ndarray]] = []
        self._started = False
        self._labels: list[np.ndarray] = []
        self._results: list[VPResult | None] = []
        self._last: VPResult | None = None
        self._prev: _FrameIn | None = None  # the frame the tracked vertical refers to

    def add(self, segs: np.ndarray, point_ids: np.ndarray, point_uv: np.ndarray, is_keyframe: bool) -> None:
        """One frame's undistorted segments (S, 4) and point tracks (ids (P,), pixels (P, 2))."""
        frame = _FrameIn(np.asarray(segs, np.float64).reshape(-1, 4), point_ids, point_uv, bool(is_keyframe))
        if self._started:
            self._step(frame)
            return
        self._observe_pending(frame)
        self._pending.append(frame)
        if len(self._pending) >= self.config.init_frames or self._vote_decided():
            self._start()

    def result(self) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """Labels per frame [(S_f,) int64, -1 non-structural], directions (F, V, 3) (NaN where none)
        and the vertical's row per frame (F,) (-1: none)."""
        if not self._started:
            self._start()
        n = len(self._results)
        V = max([3] + [len(r.dirs_c) for r in self._results if r is not None])
        dirs = np.full((n, V, 3), np.nan)
        vertical_vp = np.full(n, -1, np.int64)
        for f, r in enumerate(self._results):
            if r is not None:
                dirs[f, : len(r.dirs_c)] = r.dirs_c
                vertical_vp[f] = r.vertical_index
        return self._labels, dirs, vertical_vp

    def _rotation(self, a: _FrameIn, b: _FrameIn) -> np.ndarray | None:
        uv_a, uv_b = common_points(a.point_ids, a.point_uv, b.point_ids, b.point_uv)
        if len(uv_a) < MIN_ROTATION_POINTS:
            return None
        return rotation_from_bearings(uv_a, uv_b, self.K)

    def _start(self) -> None:
        """Initialise the vertical from the buffered first frames, then process them."""
        self._started = True
        frames, self._pending = self._pending, []
        cfg = self.config
        vertical = self._initial_vertical()
        if vertical is not None:
            self.vertical_source = "initialised"
        else:  # no rotation chain (e.g. tracking broke at once): the frames' verticals averaged as they are
            try:
                vertical = estimate_vertical([f.segs for f in frames], self.K, cfg.vp, self.seed)
                self.vertical_source = "initialised-unaligned"
            except GeometryError as exc:
                log.warning("vanishing points: %s; estimating each frame without a vertical prior", exc)
                self.vertical_source = "per-frame"
        self.vertical = vertical
        for frame in frames:
            self._step(frame)

    def _observe_pending(self, frame: _FrameIn) -> None:
        """A frame waiting for the initialisation: its rotation from the first frame (chained point-track
        rotations) and its own vertical (no prior), found as it arrives so that `_start` has only the
        vote left (the frontend's worker thread does this beside the frames that follow)."""
        f = len(self._pending)
        R_f0 = np.eye(3) if f == 0 else self._chain[-1]
        if f > 0 and R_f0 is not None:
            R = self._rotation(self._pending[-1], frame)
            R_f0 = None if R is None else R @ R_f0
        self._chain.append(R_f0)
        try:
            res = estimate_frame(frame.segs, self.K, None, self.config.vp, self.seed)
        except GeometryError:
            return
        if res.vertical_c is not None:
            v = res.vertical_c
            self._found.append((f, v if v[1] <= 0 else -v))  # up is -y for an upright camera

    def _agreement(self) -> np.ndarray:
        """(n, n) whether the pending frames' own verticals (in `_found`) agree within track_gate_deg."""
        V = np.array([v for _, v in self._found])
        return np.degrees(np.arccos(np.clip(np.abs(V @ V.T), 0, 1))) <= self.config.vp.track_gate_deg

    def _vote_decided(self) -> bool:
        """Whether the vote of `_initial_vertical` is settled before init_frames: the largest agreeing
        group leads every group of the frames outside it by more than the frames still to come, so
        waiting for them (and estimating each of them twice, without and then with the prior) could
        not hand the vote to a vertical outside it (the winner within it may still move to another of
        its members when more frames join: one within track_gate_deg)."""
        remaining = self.config.init_frames - len(self._pending)
        if len(self._found) <= remaining:
            return False
        agree = self._agreement()
        counts = agree.sum(axis=1)
        best = int(np.argmax(counts))
        rival = counts[~agree[best]].max(initial=0)
        return bool(counts[best] - rival > remaining)

    def _initial_vertical(self) -> np.ndarray | None:
        """The vertical of the first frame, from the first frames' own verticals (no prior).

        Single-frame verticals are either good (0.1-0.3 deg on the synthetic corridor) or far off, so
        the largest group agreeing within track_gate_deg is found, and its earliest frame's vertical
        is rotated back into the first frame by the chained point-track rotations (chaining all of
        them would add their drift). None when no frame shows a vertical or the chain is broken.
        """
        found, chain = self._found, self._chain
        if not found:
            return None
        agree = self._agreement()
        group = np.flatnonzero(agree[int(np.argmax(agree.sum(axis=1)))])
        f, v = found[int(group[0])]
        if chain[f] is None:
            return None
        v = chain[f].T @ v
        return v / np.linalg.norm(v)

    def _step(self, frame: _FrameIn) -> None:
        cfg = self.config
        f = len(self._results)
        self._labels.append(np.full(len(frame.segs), -1, np.int64))
        self._results.append(None)
        if self._last is not None and f % max(1, cfg.stride) and not frame.is_keyframe:
            # between estimates: the last directions, this frame's segments classified against them
            self._labels[f] = classify_segments(frame.segs, self.K, self._last.dirs_c, cfg.vp)
            self._results[f] = self._last
            return
        if self.vertical is not None and self._prev is not None:
            R = self._rotation(self._prev, frame)
            if R is not None:
                self.vertical = update_vertical(self.vertical, None, R, cfg.vp)
                self.rotations += 1
        self._prev = frame
        try:
            res = estimate_frame(frame.segs, self.K, self.vertical, cfg.vp, self.seed)
        except GeometryError as exc:
            log.debug("frame row %d: no vanishing directions (%s)", f, exc)
            self.failures += 1
            return
        self._labels[f] = res.labels
        if self.vertical is not None:
            self.vertical = update_vertical(self.vertical, res.vertical_c, None, cfg.vp)
            if cfg.report_tracked_vertical and cfg.vp.use_vertical_prior and res.vertical_index == 0:
                dirs_c = res.dirs_c.copy()
                dirs_c[0] = self.vertical
                res = dataclasses.replace(res, dirs_c=dirs_c)
        self._results[f] = self._last = res
