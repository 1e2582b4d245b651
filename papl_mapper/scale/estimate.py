"""A scale estimate (metres per map unit) with its uncertainty, and the choice between several.

Every source (marker, camera height, known length) returns a `ScaleEstimate`; `choose` keeps the
best-conditioned one and refuses sources that disagree beyond their uncertainties.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

from papl_mapper.errors import InputError

log = logging.getLogger(__name__)


@dataclass
class ScaleEstimate:
    """`scale` metres per map unit, from `source`, with relative standard uncertainty `rel_sigma`."""

    scale: float
    rel_sigma: float
    source: str  # "marker", "camera_height", "length", "points"
    description: str  # one line for the report and `info`, e.g. "ArUco 4X4_50 id 7 (0.2 m) in 12 keyframes"
    detail: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise InputError(f"{self.description}: the scale came out {self.scale!r}, not a positive number")
        if not math.isfinite(self.rel_sigma):
            self.rel_sigma = float("inf")

    @property
    def sigma(self) -> float:
        """Absolute standard uncertainty of `scale` (metres per map unit)."""
        return self.scale * self.rel_sigma

    def to_dict(self) -> dict[str, Any]:
        """The record stored in the map's metadata['scale'] and in summary.json."""
        return {
            "source": self.source,
            "description": self.description,
            "metres_per_unit": self.scale,
            "rel_sigma": self.rel_sigma if math.isfinite(self.rel_sigma) else None,
            **({"detail": self.detail} if self.detail else {}),
        }


def choose(
    estimates: list[ScaleEstimate], max_disagreement_sigma: float = 3.0, min_disagreement: float = 0.03
) -> ScaleEstimate:
    """The estimate with the smallest relative uncertainty; InputError when two disagree.

    Two estimates conflict when their ratio differs from 1 by more than `max_disagreement_sigma`
    combined relative sigmas and by more than `min_disagreement`: the sigmas cover the noise of each
    source, not its systematic errors (a marker's corners, a camera that is not quite at the height
    given), which reach a percent or two.
    """
    if not estimates:
        raise InputError("no scale source given")
    best = min(estimates, key=lambda e: e.rel_sigma)
    for other in estimates:
        if other is best:
            continue
        apart = abs(other.scale / best.scale - 1.0)
        tol = max(max_disagreement_sigma * math.hypot(best.rel_sigma, other.rel_sigma), min_disagreement)
        if apart > tol:
            raise InputError(
                f"conflicting scales: {best.description} gives {best.scale:.6g} m/unit "
                f"(±{100 * best.rel_sigma:.2g}%), {other.description} gives {other.scale:.6g} m/unit "
                f"(±{100 * other.rel_sigma:.2g}%): {100 * apart:.1f}% apart, more than their uncertainties "
                "allow; check the marker size, camera height or length, or give one source only"
            )
        log.info(
            "scale: %s and %s agree within %.2f%%; using %s (better conditioned)",
            best.description, other.description, 100 * apart, best.source,
        )  # fmt: skip
    return best


def units_note(metadata: dict[str, Any]) -> str:
    """The map's units and how they were found, for info, report, previews and file headers:
    'm from camera height 1.6 m above the floor ±0.2%', or 'arbitrary (monocular scale unknown)'."""
    units = str(metadata.get("units", "arbitrary"))
    rec = metadata.get("scale")
    if units == "arbitrary":
        return "arbitrary (monocular scale unknown)"
    if not isinstance(rec, dict):
        return f"{units} (given)"
    sigma = rec.get("rel_sigma")
    unc = f" ±{100 * float(sigma):.2g}%" if isinstance(sigma, (int, float)) else ""
    return f"{units} from {rec.get('description', rec.get('source', 'an unnamed source'))}{unc}"
