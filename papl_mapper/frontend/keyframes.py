"""Keyframe selection by parallax (median flow of common point tracks) and track survival.

A frame becomes a keyframe when, relative to the last keyframe, the median displacement of the
point tracks both see reaches `min_parallax_px`, or the fraction of the last keyframe's tracks
still alive drops below `min_survival`; never closer than `min_gap_frames` to the previous
keyframe unless `min_gap_s` of recording time lies between them (a density cap for dense video, not
for photos), and at least every `max_gap_frames` frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KeyframeConfig:
    """Settings of keyframe selection."""

    min_parallax_px: float = 20.0
    """Median displacement of common point tracks (work-image pixels, see FrontendConfig) for a keyframe."""
    min_survival: float = 0.6
    """A keyframe is made when fewer than this fraction of the last keyframe's tracks survive."""
    min_gap_frames: int = 3
    """Density cap: at least this many processed frames between keyframes ..."""
    min_gap_s: float = 0.5
    """... unless this much recording time lies between them: the cap keeps dense video from making
    keyframes that add no view; photos (or a large --step) half a second apart are never redundant."""
    max_gap_frames: int = 60
    """A keyframe at least every this many processed frames (0 = no limit)."""
    min_common_tracks: int = 12
    """Below this many common tracks a keyframe is made (tracking is about to break)."""


class KeyframeSelector:
    """Decides per frame whether it is a keyframe; remembers the last keyframe's point tracks."""

    def __init__(self, config: KeyframeConfig):
        self.config = config
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2))
        self._last = None  # counter of the last keyframe
        self._last_t = -np.inf  # its time, seconds
        self._frame = -1
        self.last_parallax_px = 0.0
        self.last_survival = 1.0
        self.last_reason = ""  # why the last frame became a keyframe ("" if it did not)

    def update(self, ids: np.ndarray, uv: np.ndarray, force: bool = False, t: float = 0.0) -> bool:
        """Feed one frame's point tracks (ids (N,), pixels (N, 2)) and time (s); True if it is a keyframe."""
        self._frame += 1
        cfg = self.config
        ids = np.asarray(ids, np.int64)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        is_kf = force or self._last is None
        self.last_reason = "forced" if force else ("first" if self._last is None else "")
        if not is_kf:
            gap = self._frame - self._last
            common, ia, ib = np.intersect1d(self._ids, ids, assume_unique=True, return_indices=True)
            self.last_survival = len(common) / max(1, len(self._ids))
            self.last_parallax_px = (
                float(np.median(np.linalg.norm(uv[ib] - self._uv[ia], axis=1))) if len(common) else 0.0
            )
            if gap >= cfg.min_gap_frames or t - self._last_t >= cfg.min_gap_s:
                reasons = (
                    ("parallax", self.last_parallax_px >= cfg.min_parallax_px),
                    ("survival", self.last_survival < cfg.min_survival),
                    ("few_tracks", len(common) < cfg.min_common_tracks),
                    ("max_gap", cfg.max_gap_frames > 0 and gap >= cfg.max_gap_frames),
                )
                self.last_reason = next((name for name, hit in reasons if hit), "")
                is_kf = bool(self.last_reason)
        if is_kf:
            self._ids, self._uv, self._last, self._last_t = ids.copy(), uv.copy(), self._frame, t
        return is_kf
