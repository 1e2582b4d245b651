"""World lines for pose tracking during registration: line tracks triangulated from the keyframes so far.

The paper's tracking refines each frame's pose with point AND line reprojection; during registration
there is no line map yet, so this module keeps one: every line track seen by at least `min_views`
registered keyframes with enough parallax is triangulated from those keyframes' poses (structural
tracks along their vanishing direction, texture edges left out: `mapping.lines.triangulate_lines`
with `triangulation`'s thresholds), and re-triangulated when a keyframe that sees it is added or moves
(windowed BA, loop closure). Triangulation is lazy: a track is (re)made only when a frame that sees it
asks for its lines, so a frame costs the tracks it sees, not the map.

Refining every pose with them is off by default (`RegistrationLinesConfig.enabled`: measured, it does
not hold the garage's U-turn); the frames that neither PnP nor the relative pose can register are posed
from them (`tracking.pose_from_lines`, `mapping.pnp.from_lines`).
`RegistrationLines(tracks, config).frame_lines(f, reg.T_cw)` gives the world Pluecker lines (M, 6) and
the frame's observed segments (M, 4), the form `track_pnp(lines_w=..., line_xy=...)` and
`pose_from_lines` take; `pnp_config` turns the line term of the refinement on for `track_pnp`.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from papl_mapper.geometry.lines import plucker_from_endpoints
from papl_mapper.mapping.assemble import vp_directions_w
from papl_mapper.mapping.lines import LineInitConfig, triangulate_lines
from papl_mapper.mapping.tracking import PnPConfig
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)


def _triangulation_defaults() -> LineInitConfig:
    return LineInitConfig(min_views=3, min_plane_angle_deg=5.0, max_error_px=2.0)


@dataclass
class RegistrationLinesConfig:
    """Line tracks triangulated during registration and used in each frame's pose refinement."""

    enabled: bool = False
    """Refine each registered frame's pose with the endpoint-to-line distances of the line tracks the
    keyframes so far triangulate (as well as its points and vanishing directions). Off: it did not
    help where it should, the garage, whose scale breaks in its U-turn where no line track spans the
    turn, so lines cannot carry the scale across (benchmarks/registration_lines.py,
    results/registration_lines.json; benchmarks/RESULTS.md)."""
    triangulation: LineInitConfig = field(default_factory=_triangulation_defaults)
    """Which tracks make a line: `min_views` counts registered keyframes, `min_plane_angle_deg` is the
    parallax, structural tracks only (`min_vp_fraction`, `max_vp_angle_deg`) as in the map's lines.
    5 degrees, not the map's 1: registration has no BA over lines to repair those from little parallax
    (benchmarks/results/notes.md)."""
    below_inliers: int = 0
    """Use the lines only for poses with fewer PnP inliers than this (0: always)."""
    gate_px: float = 8.0
    """Leave out a line whose observed endpoints lie farther than this from its projection under the
    PnP pose (a wrong track or a line triangulated from a bad pair of views)."""
    regrow: float = 1.2
    """A line is triangulated again when the keyframes seeing it grew by this factor since it was made
    (1: at every new keyframe); a track without a line yet is tried at every new keyframe, and a
    keyframe that moves (windowed BA, loop closure) always re-triangulates the lines it sees."""


@contextlib.contextmanager
def _quiet(name: str) -> Iterator[None]:
    """Silence a module's INFO log for the duration (line triangulation logs its drop reasons per call)."""
    logger = logging.getLogger(name)
    level = logger.level
    logger.setLevel(max(logging.WARNING, level))
    try:
        yield
    finally:
        logger.setLevel(level)


class RegistrationLines:
    """Line tracks triangulated from the registered keyframes, kept up to date as keyframes are added
    and move, for the pose refinement of the frames being registered."""

    def __init__(self, tracks: Tracks, config: RegistrationLinesConfig | None = None) -> None:
        self.tracks = tracks
        self.cfg = config or RegistrationLinesConfig()
        n = len(tracks)
        by_frame = np.argsort(tracks.line_frame, kind="stable")
        self._frame_rows = np.split(by_frame, np.searchsorted(tracks.line_frame[by_frame], np.arange(1, n)))
        self._by_track = np.argsort(tracks.line_track, kind="stable")
        self._sorted_track = tracks.line_track[self._by_track]
        self._poses: dict[int, np.ndarray] = {}  # keyframe -> T_cw the lines were last made with
        self._dirty: set[int] = set()  # tracks whose keyframes moved or left since they were triangulated
        self._views: dict[int, int] = {}  # track -> registered keyframes that see it
        self._made_from: dict[int, int] = {}  # track -> keyframes seeing it when it was last triangulated
        self._lines: dict[int, np.ndarray] = {}  # track -> world endpoints (2, 3)
        self.triangulated = 0  # track triangulations run (for statistics)

    def pnp_config(self, pnp: PnPConfig) -> PnPConfig:
        """`pnp` with the refinement's line term on, gated as configured (for `track_pnp`)."""
        rc = replace(
            pnp.refine,
            enabled=True,
            lines=True,
            lines_below_inliers=self.cfg.below_inliers,
            line_gate_px=self.cfg.gate_px,
        )
        return replace(pnp, refine=rc)

    def _rows_of_tracks(self, ids: np.ndarray) -> np.ndarray:
        lo = np.searchsorted(self._sorted_track, ids, "left")
        n = np.searchsorted(self._sorted_track, ids, "right") - lo
        starts = np.repeat(lo - (np.cumsum(n) - n), n)
        return self._by_track[starts + np.arange(int(n.sum()))]

    def _sync(self, T_cw: dict[int, np.ndarray]) -> None:
        """Count the views of the tracks of keyframes added since the last call; mark the tracks of
        keyframes that moved or were removed."""
        gone = [f for f in self._poses if f not in T_cw]
        for f, T in T_cw.items():
            old = self._poses.get(f)
            if old is not None and np.array_equal(old, T):
                continue
            tids = (
                self.tracks.line_track[self._frame_rows[f]].tolist() if 0 <= f < len(self._frame_rows) else []
            )
            if old is None:
                for t in tids:
                    self._views[t] = self._views.get(t, 0) + 1
            else:
                self._dirty.update(tids)
            self._poses[f] = T.copy()
        for f in gone:
            tids = (
                self.tracks.line_track[self._frame_rows[f]].tolist() if 0 <= f < len(self._frame_rows) else []
            )
            for t in tids:
                self._views[t] -= 1
            self._dirty.update(tids)
            del self._poses[f]

    def _stale(self, t: int) -> bool:
        """Whether track t should be triangulated (again) before its line is used."""
        views = self._views.get(t, 0)
        if t in self._dirty:
            return True
        if t not in self._made_from:
            return views > 0
        made = self._made_from[t]
        return views != made and (t not in self._lines or views >= self.cfg.regrow * made)

    def _triangulate(self, ids: np.ndarray) -> None:
        """(Re)triangulate the tracks `ids` from their observations in the registered keyframes."""
        tr = self.tracks
        for t in ids.tolist():
            self._lines.pop(t, None)
            self._dirty.discard(t)
            self._made_from[t] = self._views.get(t, 0)
        rows = self._rows_of_tracks(ids)
        rows = rows[np.isin(tr.line_frame[rows], np.fromiter(self._poses, np.int64, len(self._poses)))]
        if not len(rows):
            return
        frames = tr.line_frame[rows]
        T_wc = np.linalg.inv(np.stack([self._poses[int(f)] for f in frames]))
        vp_w = vp_directions_w(tr, frames, tr.line_vp[rows], T_wc)
        with _quiet("papl_mapper.mapping.lines"):
            est = triangulate_lines(
                tr.line_track[rows], T_wc, tr.line_xy[rows], vp_w, tr.camera.K, self.cfg.triangulation
            )
        self.triangulated += len(ids)
        for t, ends in zip(est.track.tolist(), est.endpoints_w, strict=True):
            self._lines[t] = ends

    def frame_lines(self, f: int, T_cw: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World Pluecker lines (M, 6), observed segments (M, 4) and track ids (M,) of the line tracks
        frame f sees that the registered keyframes `T_cw` (frame -> world-to-camera pose) triangulate."""
        self._sync(T_cw)
        rows = self._frame_rows[f] if 0 <= f < len(self._frame_rows) else np.zeros(0, np.int64)
        if not len(rows):
            return np.zeros((0, 6)), np.zeros((0, 4)), np.zeros(0, np.int64)
        ids = self.tracks.line_track[rows]
        stale = np.array(sorted({t for t in ids.tolist() if self._stale(t)}), np.int64)
        if len(stale):
            self._triangulate(stale)
        have = np.array([t in self._lines for t in ids.tolist()], bool)
        if not have.any():
            return np.zeros((0, 6)), np.zeros((0, 4)), np.zeros(0, np.int64)
        ends = np.stack([self._lines[int(t)] for t in ids[have]])
        return plucker_from_endpoints(ends[:, 0], ends[:, 1]), self.tracks.line_xy[rows[have]], ids[have]

    def lines(self) -> tuple[np.ndarray, np.ndarray]:
        """Track ids (M,) and world endpoints (M, 2, 3) of every line triangulated so far (stale ones too)."""
        ids = np.array(sorted(self._lines), np.int64)
        ends = np.stack([self._lines[int(t)] for t in ids]) if len(ids) else np.zeros((0, 2, 3))
        return ids, ends
