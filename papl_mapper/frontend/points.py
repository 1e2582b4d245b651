"""Point tracks: Shi-Tomasi corners followed by pyramidal KLT, replenished where sparse.

Track ids persist for as long as KLT (with its forward-backward check) follows a corner. On
keyframes every live track gets an ORB descriptor; a track born since the previous keyframe
whose descriptor matches a recently lost track near its last position takes over the lost
track's id (re-association after a brief occlusion or KLT failure).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from papl_mapper.frontend.descriptors import describe_corners, hamming_pairs
from papl_mapper.frontend.klt import FlowConfig, predict_flow, track_klt

log = logging.getLogger(__name__)


@dataclass
class PointConfig:
    """Settings of corner detection, replenishment and ORB re-association (pixels of the work image)."""

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
    reassociate: bool = True
    """Give new tracks the id of a recently lost track with a matching ORB descriptor."""
    orb_max_hamming: int = 40
    """Largest Hamming distance (of 256 bits) of an ORB re-association."""
    orb_ratio: float = 0.8
    """Lowe ratio of the best to the second-best ORB distance."""
    reassociate_radius_px: float = 30.0
    """A lost track is re-found only this close to where it was last seen."""
    lost_memory_frames: int = 60
    """How long (frames) a lost track can be re-found."""


@dataclass
class _Lost:
    uv: np.ndarray  # (L, 2) last keyframe position
    desc: np.ndarray  # (L, 32) uint8
    ids: np.ndarray  # (L,) int64
    lost_at: np.ndarray  # (L,) int64 frame counter when it was lost


class PointTracker:
    """Stateful tracker of one recording; call `step` once per frame, `keyframe` on keyframes."""

    def __init__(self, config: PointConfig, flow: FlowConfig, width: int, height: int):
        self.config = config
        self.flow = flow
        self.width, self.height = width, height
        self.ids = np.zeros(0, np.int64)
        self.uv = np.zeros((0, 2), np.float32)
        self.next_id = 0
        self.frame = -1
        self.flow_from = np.zeros((0, 2), np.float32)  # survivors of the last step, before and after
        self.flow_to = np.zeros((0, 2), np.float32)
        self.born: dict[
            int, int
        ] = {}  # track id -> frame counter of birth (only tracks born since the last keyframe)
        self.aliases: dict[int, int] = {}  # track id -> earlier id it continues
        self._kf_desc: dict[int, np.ndarray] = {}  # live id -> ORB descriptor at its last keyframe
        self._kf_uv: dict[int, np.ndarray] = {}
        self._lost = _Lost(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.int64), np.zeros(0))
        self._orb = cv2.ORB_create(edgeThreshold=15, patchSize=15)

    def step(self, gray: np.ndarray, prev: np.ndarray | None, force_detect: bool = False) -> None:
        """Follow live tracks from gray image prev to gray; replenish corners where sparse."""
        self.frame += 1
        motion = predict_flow(self.flow_from, self.flow_to) if self.flow.predict else None
        self.flow_from = self.flow_to = np.zeros((0, 2), np.float32)
        if prev is not None and len(self.ids):
            new_uv, ok = track_klt(prev, gray, self.uv, self.flow, self.width, self.height, motion)
            self._forget(self.ids[~ok])
            self.flow_from, self.flow_to = self.uv[ok], new_uv[ok]
            self.ids, self.uv = self.ids[ok], new_uv[ok]
        elif prev is None and len(self.ids):
            self._forget(self.ids)
            self.ids, self.uv = np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
        if force_detect or len(self.ids) < self.config.replenish_below * self.config.max_points:
            self._replenish(gray)

    def _forget(self, lost_ids: np.ndarray) -> None:
        """Move lost tracks that have a keyframe descriptor into the re-association pool."""
        if not self.config.reassociate:
            return
        keep = [i for i in lost_ids.tolist() if i in self._kf_desc]
        for i in lost_ids.tolist():
            self.born.pop(i, None)
        if not keep:
            return
        lost = self._lost
        self._lost = _Lost(
            np.vstack([lost.uv, np.array([self._kf_uv.pop(i) for i in keep])]),
            np.vstack([lost.desc, np.array([self._kf_desc.pop(i) for i in keep])]),
            np.concatenate([lost.ids, np.array(keep, np.int64)]),
            np.concatenate([lost.lost_at, np.full(len(keep), self.frame)]),
        )

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
        for i in new_ids.tolist():
            self.born[i] = self.frame
        self.ids = np.concatenate([self.ids, new_ids])
        self.uv = np.vstack([self.uv, corners])

    def keyframe(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB descriptors of the live tracks (after re-association); returns ids (D,) and (D, 32) uint8."""
        if len(self.ids) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        rows, desc = describe_corners(self._orb, gray, self.uv)
        if len(rows) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        if self.config.reassociate:
            self._reassociate(rows, desc)
        ids = self.ids[rows]
        for i, r, d in zip(ids.tolist(), rows.tolist(), desc, strict=True):
            self._kf_desc[i] = d
            self._kf_uv[i] = self.uv[r].astype(np.float64)
        self.born.clear()
        self._expire()
        return ids, desc

    def _expire(self) -> None:
        keep = self.frame - self._lost.lost_at <= self.config.lost_memory_frames
        lost = self._lost
        self._lost = _Lost(lost.uv[keep], lost.desc[keep], lost.ids[keep], lost.lost_at[keep])

    def _reassociate(self, rows: np.ndarray, desc: np.ndarray) -> None:
        """Rename young tracks that match a lost one (descriptor, ratio, radius; one-to-one)."""
        cfg = self.config
        lost = self._lost
        young = np.array([self.ids[r] in self.born for r in rows], bool)
        if not young.any() or len(lost.ids) == 0:
            return
        yr = np.flatnonzero(young)
        dist = np.linalg.norm(self.uv[rows[yr]][:, None, :] - lost.uv[None, :, :], axis=2)
        born = np.array([self.born[int(self.ids[rows[y]])] for y in yr])
        # the lost track must end before the young one starts, so no frame sees both ids
        ok = (dist <= cfg.reassociate_radius_px) & (born[:, None] >= lost.lost_at[None, :])
        ham = np.full(ok.shape, 10_000, np.int64)
        iy, il = np.nonzero(ok)
        ham[iy, il] = hamming_pairs(desc[yr], lost.desc, iy, il)
        used_lost: set[int] = set()
        best_ham = ham.min(axis=1)
        order = np.argsort(best_ham)
        for y in order[best_ham[order] <= cfg.orb_max_hamming].tolist():
            cand = np.argsort(ham[y])
            best = int(cand[0])
            if ham[y, best] > cfg.orb_max_hamming or best in used_lost:
                continue
            second = ham[y, cand[1]] if len(cand) > 1 else 10_000
            if ham[y, best] > cfg.orb_ratio * second:
                continue
            row = rows[yr[y]]
            young_id, old_id = int(self.ids[row]), int(lost.ids[best])
            used_lost.add(best)
            self.aliases[young_id] = old_id
            self.ids[row] = old_id
        if used_lost:
            keep = np.ones(len(lost.ids), bool)
            keep[list(used_lost)] = False
            self._lost = _Lost(lost.uv[keep], lost.desc[keep], lost.ids[keep], lost.lost_at[keep])
            log.debug("re-associated %d point tracks", len(used_lost))

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Map track ids through the re-association aliases to their oldest id."""
        if not self.aliases:
            return ids
        out = ids.copy()
        for young, old in self.aliases.items():
            while old in self.aliases:
                old = self.aliases[old]
            out[ids == young] = old
        return out
