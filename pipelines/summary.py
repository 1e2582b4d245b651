"""What a run reports in summary.json: `RunSummary`, one typed object filled by the pipeline.

`MappingStats` is the part the mapping stages fill (registration to the last BA); the stage
checkpoints keep it, so a resumed run reports the statistics of the stages it did not rerun. The JSON
keeps one flat table (`RunSummary.to_dict`): the report (gui/report.py), batch.json rows, tests and
benchmarks read its keys.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

if TYPE_CHECKING:
    from papl_mapper.mapping.revisit import Revisit
    from papl_mapper.tracks import Tracks


@dataclass
class RecordingInfo:
    """The recording as opened: path, content hash, frames decoded and (when mapped) its format."""

    path: str
    sha256: str
    frames: int
    fps: float | None = None
    width: int | None = None
    height: int | None = None
    stopped_early: bool | None = None
    stop_message: str | None = None


@dataclass
class MappingStats:
    """Statistics of the stages after the frontend, in the order they run (None: the stage did not run)."""

    frames_unregistered: int = 0
    segments_left_out: list[list[int]] = field(default_factory=list)
    """[first, last] recording frame index of each tracking segment that could not be joined to the map."""
    keyframes_registered: int = 0
    culling: dict[str, Any] = field(default_factory=dict)
    revisits: list[dict[str, Any]] = field(default_factory=list)
    ba_points: dict[str, Any] | None = None
    """The last points-only BA (the statistics of `mapping.adjust.adjust`)."""
    rotation_check: dict[str, Any] | None = None
    """The first points BA's rotations against those averaged from pairwise two-view geometry."""
    reverse_check: dict[str, Any] | None = None
    """The points BA from the forward registration against the one from the backward registration
    (`mapping.reverse_start.ReverseCheck`)."""
    completion: dict[str, int] | None = None
    """Track completion after the points BA."""
    ba: dict[str, Any] | None = None
    """The last full BA over points and lines."""
    completion_full_ba: dict[str, int] | None = None
    """Track completion after the full BA."""
    line_completion: dict[str, int] | None = None
    """Segment tracks merged and completed into the map lines after the full BA."""
    axis_update: list[str] | None = None
    """What the axis update after the full BA did, one line per change."""
    culled_after_ba: dict[str, int] | None = None
    """Observations beyond the error limits after the last BA, and the points and lines they left without
    views, removed from the map (`cull_observations`' counts)."""

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MappingStats:
        """From `as_dict` (a checkpoint's stage.json); ValueError for unknown keys."""
        if not isinstance(d, dict):
            raise ValueError("stage.json: stats is not a table")
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"stage.json: stats with unknown keys {sorted(unknown)}")
        return cls(**d)


@dataclass(kw_only=True)
class RunSummary:
    """summary.json of one run: a map (`status` "mapped") or why there is none ("unmapped")."""

    status: Literal["mapped", "unmapped"] = "mapped"
    error: str | None = None
    """Why the recording could not be mapped."""
    recording: RecordingInfo
    frames_posed: int | None = None
    """Frames with a pose (unmapped: orientations only)."""
    camera: dict[str, Any] | None = None
    """The camera used (`Camera.to_dict`), its source and whether it was guessed."""
    counts: dict[str, Any] | None = None
    """`Map.summary()`: keyframes, points, lines, axes."""
    frontend: dict[str, Any]
    """`frontend.FrontendStats` as a table."""
    frames_lost: int | None = None
    """Frames without a pose (mapped)."""
    mapping: MappingStats | None = None
    focal_check: dict[str, Any] | None = None
    timings_s: dict[str, float] | None = None
    """Wall time per stage, in the order the stages ran."""
    resumed: dict[str, Any] | None = None
    """The checkpoint a resumed run continued from (written as null when it did not resume)."""
    checkpoints_written: dict[str, dict[str, float]] | None = None
    per_frame: dict[str, list[int]] | None = None
    """Frame index and point and line observations per frame."""
    segment_maps: list[dict[str, Any]] | None = None
    """Tracking segments left out of the map and mapped on their own: frames, folder, counts."""

    def to_dict(self) -> dict[str, Any]:
        """The flat table written as summary.json (stages that did not run left out)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "mapping":
                out.update(value.as_dict() if value is not None else {})
            elif f.name == "recording":
                out[f.name] = {k: v for k, v in dataclasses.asdict(value).items() if v is not None}
            elif value is not None or (f.name == "resumed" and self.status == "mapped"):
                out[f.name] = value
        return out


def revisit_row(rv: Revisit) -> dict[str, Any]:
    """One closed loop as summary.json lists it."""
    return {
        "frame": rv.frame,
        "old_frame": rv.old_frame,
        "tracks_fused": len(rv.pairs),
        "correction": round(rv.drift, 4),
        "scale": round(rv.scale, 4),
        "path": round(rv.path, 4) if np.isfinite(rv.path) else None,
        "old_points_parallax_deg": round(rv.old_parallax_deg, 2)
        if np.isfinite(rv.old_parallax_deg)
        else None,
    }


def per_frame_counts(tracks: Tracks) -> dict[str, list[int]]:
    """Frame index and point and line observations per frame of the tracks."""
    n = len(tracks)
    return {
        "frame": tracks.frame_index.astype(int).tolist(),
        "points": np.bincount(tracks.point_frame, minlength=n).astype(int).tolist(),
        "lines": np.bincount(tracks.line_frame, minlength=n).astype(int).tolist(),
    }
