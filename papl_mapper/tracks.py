"""Frontend output, mapping input: 2D observations of a recording with persistent track ids.

The frontend produces these from images; tests and benchmarks produce them by projecting a
known scene. Everything is undistorted pixels in the OpenCV convention, struct-of-arrays,
one row per observation, so mapping never touches images.
"""

from __future__ import annotations

import json
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.map import Camera


@dataclass
class Tracks:
    """Per-frame point and segment observations of one recording, keyed by frame and track id.

    `vp_dirs_c[f]` holds up to V camera-frame vanishing directions of frame f (NaN rows where
    fewer were found); `line_vp` is the index of the direction a segment was classified to in
    its frame, or -1 for non-structural segments.
    """

    camera: Camera  # undistorted pinhole camera of the observations
    frame_index: np.ndarray  # (F,) int64, index of the frame in the recording
    timestamp: np.ndarray  # (F,) float64 seconds
    is_keyframe: np.ndarray  # (F,) bool, the frontend's keyframe choice
    point_frame: np.ndarray  # (Kp,) int64, row into the frame arrays
    point_track: np.ndarray  # (Kp,) int64, persistent point track id
    point_uv: np.ndarray  # (Kp, 2) float64 pixels
    line_frame: np.ndarray  # (Kl,) int64
    line_track: np.ndarray  # (Kl,) int64, persistent segment track id
    line_xy: np.ndarray  # (Kl, 4) float64 pixels x1 y1 x2 y2
    line_vp: np.ndarray  # (Kl,) int64, index into vp_dirs_c[frame] or -1
    vp_dirs_c: np.ndarray  # (F, V, 3) float64, NaN where absent
    vertical_vp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (F,) or empty
    # keyframe descriptors (track completion, revisits, merging): ORB of point rows, LBD of line rows
    point_desc_row: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (Dp,) row
    point_desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))  # (Dp, 32) ORB
    line_desc_row: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (Dl,) row
    line_desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))  # (Dl, 32) LBD
    skipped_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # textureless

    def __len__(self) -> int:
        return len(self.frame_index)

    def validate(self) -> None:
        """Check lengths and ranges; raise ValueError naming the first inconsistent array."""
        n = len(self.frame_index)
        for name in ("timestamp", "is_keyframe", "vp_dirs_c"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Tracks.{name} has {len(getattr(self, name))} rows for {n} frames")
        for prefix, extra in (("point", ("uv",)), ("line", ("xy", "vp"))):
            k = len(getattr(self, f"{prefix}_frame"))
            for suffix in ("track", *extra):
                arr = getattr(self, f"{prefix}_{suffix}")
                if len(arr) != k:
                    raise ValueError(f"Tracks.{prefix}_{suffix} has {len(arr)} rows, expected {k}")
            frames = getattr(self, f"{prefix}_frame")
            if k and (frames.min() < 0 or frames.max() >= n):
                raise ValueError(f"Tracks.{prefix}_frame refers to frames outside 0..{n - 1}")
        if not np.isfinite(self.point_uv).all() or not np.isfinite(self.line_xy).all():
            raise ValueError("Tracks hold non-finite pixel coordinates")

    def points_in(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Track ids (K,) and pixels (K, 2) of the points seen in one frame."""
        sel = self._rows(self.point_frame, frame)
        return self.point_track[sel], self.point_uv[sel]

    def lines_in(self, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track ids (K,), endpoints (K, 4) and VP labels (K,) of the segments seen in one frame."""
        sel = self._rows(self.line_frame, frame)
        return self.line_track[sel], self.line_xy[sel], self.line_vp[sel]

    def _rows(self, frames: np.ndarray, frame: int) -> slice | np.ndarray:
        """The observation rows of one frame: a slice when the rows are in frame order (as the frontend
        writes them; a binary search instead of a scan of every observation), else a mask."""
        cache = self.__dict__.setdefault("_frame_order", {})
        key = id(frames)
        if key not in cache or cache[key][0] is not frames:
            in_order = bool(np.all(frames[1:] >= frames[:-1]))
            cache[key] = (frames, in_order)
        if cache[key][1]:
            return slice(*np.searchsorted(frames, [frame, frame + 1]).tolist())
        return frames == frame

    def reversed(self) -> Tracks:
        """The same observations with the frames in reverse order (row r becomes F-1-r, times run from
        0 at the last frame), observation rows re-sorted by frame and the keyframe descriptors' rows
        following them: the recording played backwards, for a second registration. Copies: the
        original's track ids stay as they are."""
        n = len(self)
        flip = n - 1 - np.arange(n)

        def by_frame(frame: np.ndarray, desc_row: np.ndarray, *rest: np.ndarray) -> list[np.ndarray]:
            """Observation arrays in the new frame order, and the descriptor rows (indices of observation
            rows) renumbered to follow their observations, in ascending order."""
            order = np.argsort(n - 1 - frame, kind="stable")
            new_row = np.empty(len(order), np.int64)
            new_row[order] = np.arange(len(order))
            moved = new_row[desc_row]
            by_row = np.argsort(moved, kind="stable")
            return [(n - 1 - frame)[order], *(a[order] for a in rest), moved[by_row], by_row]

        point_frame, point_track, point_uv, point_desc_row, p_by = by_frame(
            self.point_frame, self.point_desc_row, self.point_track, self.point_uv
        )
        line_frame, line_track, line_xy, line_vp, line_desc_row, l_by = by_frame(
            self.line_frame, self.line_desc_row, self.line_track, self.line_xy, self.line_vp
        )
        point_desc, line_desc = self.point_desc[p_by], self.line_desc[l_by]
        t = self.timestamp[flip]
        return Tracks(
            camera=self.camera,
            frame_index=self.frame_index[flip].copy(),
            timestamp=(t[0] - t) if n else t.copy(),
            is_keyframe=self.is_keyframe[flip].copy(),
            point_frame=point_frame,
            point_track=point_track,
            point_uv=point_uv,
            line_frame=line_frame,
            line_track=line_track,
            line_xy=line_xy,
            line_vp=line_vp,
            vp_dirs_c=self.vp_dirs_c[flip].copy(),
            vertical_vp=self.vertical_vp[flip].copy()
            if len(self.vertical_vp) == n
            else self.vertical_vp.copy(),
            point_desc_row=point_desc_row,
            point_desc=point_desc,
            line_desc_row=line_desc_row,
            line_desc=line_desc,
            skipped_frames=self.skipped_frames.copy(),
        )

    def save(self, path: str | Path) -> Path:
        """Write to one .npz (camera as JSON) under a temporary name, then rename."""
        path = Path(path)
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "camera"}
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, camera=np.array(json.dumps(self.camera.to_dict())), **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Tracks:
        """Read a file written by `save`; ValueError if it is not one."""
        with np.load(path, allow_pickle=False) as z:
            missing = {f.name for f in fields(cls) if f.default_factory is MISSING} - set(z.files)
            if missing:
                raise ValueError(f"{path}: not a tracks file (missing {sorted(missing)})")
            kw = {f.name: z[f.name] for f in fields(cls) if f.name != "camera" and f.name in z.files}
            camera = Camera.from_dict(json.loads(str(z["camera"])))
        tracks = cls(camera=camera, **kw)
        tracks.validate()
        return tracks


class PointRows:
    """Point observation rows grouped by track id: a few tracks' observations without scanning all.

    Built from `tracks.point_track` as it is now; after track ids change (loop closure renames
    tracks in place), `rename` follows them or it is built again.
    """

    def __init__(self, tracks: Tracks):
        self._order = np.argsort(tracks.point_track, kind="stable")
        self._sorted = tracks.point_track[self._order]

    def rename(self, pairs: np.ndarray) -> None:
        """Follow the renaming of track ids pairs[k, 0] -> pairs[k, 1] (unique on both sides): relabel
        their rows and re-sort the nearly sorted labels, instead of grouping every row again."""
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
        if not len(pairs):
            return
        lo = np.searchsorted(self._sorted, pairs[:, 0], "left")
        n = np.searchsorted(self._sorted, pairs[:, 0], "right") - lo
        at = np.repeat(lo - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))
        self._sorted[at] = np.repeat(pairs[:, 1], n)
        perm = np.argsort(self._sorted, kind="stable")
        self._order, self._sorted = self._order[perm], self._sorted[perm]

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """Rows (ascending) of every observation of the track ids `ids` (unique)."""
        return np.sort(self.rows_by_id(ids)[0])

    def rows_by_id(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of every observation of the track ids `ids` (repeats allowed), id by id, and for each
        row the index in `ids` it belongs to."""
        ids = np.asarray(ids, np.int64)
        lo = np.searchsorted(self._sorted, ids, "left")
        n = np.searchsorted(self._sorted, ids, "right") - lo
        starts = np.repeat(lo - (np.cumsum(n) - n), n)
        return self._order[starts + np.arange(int(n.sum()))], np.repeat(np.arange(len(ids)), n)
