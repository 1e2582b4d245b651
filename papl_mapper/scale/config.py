"""What `papl-map run` uses to put its map in metres (all off by default: arbitrary units)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ScaleConfig:
    """Scale sources applied after mapping; with several, the best-conditioned one wins."""

    markers: list[str] = field(default_factory=list)
    """Fiducial markers `aruco:DICT:ID=SIZE_M` (side length in metres) seen in the recording."""
    camera_height: float = 0.0
    """Camera height above the floor in metres (0: not used)."""
    max_view_angle_deg: float = 75.0
    """Marker views more than this far off the marker's normal are left out as grazing."""
    max_disagreement_sigma: float = 3.0
    """Two sources further apart than this many combined standard uncertainties (and than
    min_disagreement) are refused."""
    min_disagreement: float = 0.03
    """Two sources closer than this fraction are never refused (their systematic errors reach it)."""

    @property
    def enabled(self) -> bool:
        return bool(self.markers) or self.camera_height > 0
