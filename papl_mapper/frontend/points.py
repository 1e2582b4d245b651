"""Point tracks: Shi-Tomasi corners followed by pyramidal KLT, replenished where sparse.

Track ids persist for as long as KLT (with its forward-backward check) follows a corner; a corner
found again after KLT lost it is a new track. On keyframes every live track gets an ORB descriptor.
The frontend does not re-associate lost tracks by descriptor: waiting at its last position while the
image moves on, a lost track was mostly matched to the wrong corner (benchmarks/results/notes.md).
The mapping stage joins the two tracks of one physical point where the map can check it
(mapping/track_completion.py: the point's projection from the adjusted poses, and the descriptors).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from papl_mapper.frontend.descriptors import describe_corners
from papl_mapper.frontend.klt import FlowConfig, predict_flow, track_klt


@dataclass
class PointConfig:
    """Settings of corner detection and replenishment (pixels of the work image)."""

    max_points: int = 400
    """Most point tracks alive at once."""
    quality_level: float = 0.01
    """Shi-Tomasi quality relative to the best corner of the image."""
    min_distance_px: float = 15.0
    """Smallest distance between corners; also the radius masked around live tracks."""
    block_size: int = 3
    """Shi-Tomasi gradient window."""
    replenish_below: float = 0.85
    """Detect new corners when fewer than this fraction of max_points are alive (and on keyframes)."""
    border_px: int = 8
    """Corners closer than this to the image border are not detected."""


class PointTracker:
    """Stateful tracker of one recording; call `step` once per frame, `keyframe` on keyframes."""

    def __init__(self, config: PointConfig, flow: FlowConfig, width: int, height: int):
        self.config = config
        self.flow = flow
        self.width, self.height = width, height
        self.ids = np.zeros(0, np.int64)
        self.uv = np.zeros((0, 2), np.float32)
        self.next_id = 0
        self.flow_from = np.zeros((0, 2), np.float32)  # survivors of the last step, before and after
        self.flow_to = np.zeros((0, 2), np.float32)
        self.gain = 1.0  # exposure change the last step compensated (1: none)
        self._orb = cv2.ORB_create(edgeThreshold=15, patchSize=15)

    def step(self, gray: np.ndarray, prev: np.ndarray | None, force_detect: bool = False) -> None:
        """Follow live tracks from gray image prev to gray; replenish corners where sparse."""
        motion = predict_flow(self.flow_from, self.flow_to) if self.flow.predict else None
        self.flow_from = self.flow_to = np.zeros((0, 2), np.float32)
        self.gain = 1.0
        if prev is not None and len(self.ids):
            new_uv, ok, self.gain = track_klt(prev, gray, self.uv, self.flow, self.width, self.height, motion)
            self.flow_from, self.flow_to = self.uv[ok], new_uv[ok]
            self.ids, self.uv = self.ids[ok], new_uv[ok]
        elif prev is None and len(self.ids):
            self.ids, self.uv = np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
        if force_detect or len(self.ids) < self.config.replenish_below * self.config.max_points:
            self._replenish(gray)

    def _replenish(self, gray: np.ndarray) -> None:
        cfg = self.config
        want = cfg.max_points - len(self.ids)
        if want <= 0:
            return
        mask = np.zeros(gray.shape[:2], np.uint8)
        b = cfg.border_px
        mask[b : self.height - b, b : self.width - b] = 255
        r = max(1, int(round(cfg.min_distance_px)))
        for x, y in self.uv.astype(np.int32):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        corners = cv2.goodFeaturesToTrack(
            gray, want, cfg.quality_level, cfg.min_distance_px, mask=mask, blockSize=cfg.block_size
        )
        if corners is None:
            return
        corners = corners.reshape(-1, 2).astype(np.float32)
        new_ids = np.arange(self.next_id, self.next_id + len(corners), dtype=np.int64)
        self.next_id += len(corners)
        self.ids = np.concatenate([self.ids, new_ids])
        self.uv = np.vstack([self.uv, corners])

    def keyframe(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB descriptors of the live tracks; returns ids (D,) and (D, 32) uint8."""
        if len(self.ids) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        rows, desc = describe_corners(self._orb, gray, self.uv)
        if len(rows) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        return self.ids[rows], desc
