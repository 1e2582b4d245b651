"""Principal-axis errors: rotate the estimated axes into the ground-truth frame, match, measure angles.

Axes are undirected lines, so matching is sign-invariant: the Hungarian assignment maximises the
total |cos| between ground-truth and estimated directions; each matched pair's error is the angle
between the lines (0..90 degrees). Axes left over on either side (different counts) are reported.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from papl_mapper.errors import InputError
from papl_mapper.geometry.lines import line_angle_deg


@dataclass
class GtAxes:
    """Ground-truth axes: unit directions (A, 3), the vertical one, and their names."""

    directions: np.ndarray
    vertical_index: int = -1
    names: list[str] = field(default_factory=list)


@dataclass
class AxisMatch:
    """The result of matching estimated axes to ground-truth axes."""

    pairs: list[tuple[int, int]]  # (gt index, estimated index), ordered by gt index
    errors_deg: np.ndarray  # (len(pairs),) angle between the matched axis lines
    unmatched_gt: list[int]
    unmatched_est: list[int]


def read_axes(path: str | os.PathLike) -> GtAxes:
    """Read axes.json ({"directions": [[x, y, z], ...], "vertical_index": i, "names": [...]})."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such axes file")
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or "directions" not in data:
        raise InputError(f"{path}: expected an object with 'directions' (a list of [x, y, z])")
    try:
        d = np.asarray(data["directions"], np.float64).reshape(-1, 3)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: 'directions' is not a list of [x, y, z] ({exc})") from exc
    norms = np.linalg.norm(d, axis=1)
    if not np.isfinite(d).all() or (norms < 1e-9).any():
        raise InputError(f"{path}: 'directions' holds zero, NaN or infinite vectors")
    v = data.get("vertical_index", -1)
    if not isinstance(v, int) or not -1 <= v < len(d):
        raise InputError(f"{path}: vertical_index {v!r} is out of range for {len(d)} axes")
    names = data.get("names") or [f"axis {i}" for i in range(len(d))]
    if not isinstance(names, list) or len(names) != len(d):
        raise InputError(f"{path}: 'names' must list one name per direction")
    return GtAxes(d / norms[:, None], v, [str(n) for n in names])


def match_axes(gt: np.ndarray, est: np.ndarray) -> AxisMatch:
    """Sign-invariant Hungarian matching of unit directions gt (G, 3) to est (E, 3) (already rotated)."""
    gt = np.asarray(gt, np.float64).reshape(-1, 3)
    est = np.asarray(est, np.float64).reshape(-1, 3)
    if len(gt) == 0 or len(est) == 0:
        return AxisMatch([], np.zeros(0), list(range(len(gt))), list(range(len(est))))
    cost = -np.abs(gt @ est.T)
    rows, cols = linear_sum_assignment(cost)
    order = np.argsort(rows)
    rows, cols = rows[order], cols[order]
    errors = line_angle_deg(gt[rows], est[cols])
    return AxisMatch(
        [(int(r), int(c)) for r, c in zip(rows, cols, strict=True)],
        errors,
        sorted(set(range(len(gt))) - set(rows.tolist())),
        sorted(set(range(len(est))) - set(cols.tolist())),
    )
