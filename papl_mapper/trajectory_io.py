"""Trajectory files: TUM (`t tx ty tz qx qy qz qw`) and KITTI (3x4 row-major per line), read and written.

The one home of these formats: the run's `trajectory.tum`/`keyframes.tum`, the exporters' `.tum` and
`.kitti`, the synthetic ground truth, evaluation and the report all go through here. Every number is
written as `%.17g`, which reads back to the same float64 (round trip exact), with the quaternion as
scipy gives it (any sign: TUM readers accept both).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import InputError

log = logging.getLogger(__name__)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
NUMBER_FORMAT = "%.17g"
"""Every value of every trajectory file: the shortest printf format that round-trips float64."""


@dataclass
class Trajectory:
    """Timestamped camera poses `T_wc` (N, 4, 4) float64, sorted by time."""

    timestamps: np.ndarray  # (N,) float64, seconds
    T_wc: np.ndarray  # (N, 4, 4) float64, camera -> world
    name: str = ""

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, np.float64).reshape(-1)
        self.T_wc = np.asarray(self.T_wc, np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.T_wc):
            raise InputError(
                f"{self.name or 'trajectory'}: {len(self.timestamps)} timestamps for {len(self.T_wc)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.T_wc[:, :3, 3]

    def subset(self, idx: np.ndarray) -> Trajectory:
        """The poses at indices `idx`, in that order."""
        return Trajectory(self.timestamps[idx], self.T_wc[idx], self.name)

    def path_length(self) -> float:
        """Sum of the distances between consecutive camera centres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def _rows(values: np.ndarray) -> str:
    """(N, k) float64 as N lines of k space-separated `NUMBER_FORMAT` values."""
    if len(values) == 0:
        return ""
    row = " ".join([NUMBER_FORMAT] * values.shape[1]) + "\n"
    return (row * len(values)) % tuple(values.ravel().tolist())


def format_tum(timestamps: np.ndarray, T_wc: np.ndarray, header: str = TUM_HEADER) -> str:
    """TUM text: the `header` comment line, then `t tx ty tz qx qy qz qw` per pose (T_wc)."""
    from scipy.spatial.transform import Rotation  # here: scipy takes a third of a second to load

    T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
    q_xyzw = Rotation.from_matrix(T_wc[:, :3, :3]).as_quat() if len(T_wc) else np.zeros((0, 4))
    rows = np.column_stack([np.asarray(timestamps, np.float64), T_wc[:, :3, 3], q_xyzw])
    return header + "\n" + _rows(rows)


def format_kitti(T_wc: np.ndarray) -> str:
    """KITTI odometry text: the 3x4 top of each T_wc, row-major, one pose per line (no timestamps)."""
    T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
    return _rows(T_wc[:, :3, :4].reshape(-1, 12))


def write_tum(path: str | os.PathLike, traj: Trajectory, header: str = TUM_HEADER) -> Path:
    """Write `traj` as a TUM file (atomically, through `papl_mapper.atomic`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(format_tum(traj.timestamps, traj.T_wc, header))
    return path


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM file (`t tx ty tz qx qy qz qw` per line, '#' comments); InputError names file and line."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such trajectory file")
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text TUM trajectory ({exc})") from exc
    rows, line_no = [], []
    for k, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(
                f"{path}: line {k} has {len(parts)} values, a TUM row is 't tx ty tz qx qy qz qw' (8 values)"
            )
        try:
            values = [float(v) for v in parts]
        except ValueError as exc:
            raise InputError(f"{path}: line {k} holds a non-number ({exc})") from exc
        if not np.isfinite(values).all():
            raise InputError(f"{path}: line {k} holds NaN or infinite values")
        q_norm = float(np.linalg.norm(values[4:]))
        if q_norm < 1e-6:
            raise InputError(f"{path}: line {k} has a zero quaternion")
        rows.append(values)
        line_no.append(k)
    if not rows:
        raise InputError(f"{path}: holds no poses")
    data, lines = np.asarray(rows, np.float64), np.asarray(line_no)
    t = data[:, 0]
    if np.any(np.diff(t) < 0):
        log.warning("%s: timestamps are not sorted; sorting them", path)
        order = np.argsort(t, kind="stable")
        data, t, lines = data[order], t[order], lines[order]
    dup = np.flatnonzero(np.diff(t) == 0)
    if dup.size:
        i = dup[0]
        raise InputError(
            f"{path}: lines {lines[i]} and {lines[i + 1]} share timestamp {float(t[i])!r}; "
            "each pose needs its own timestamp"
        )
    from scipy.spatial.transform import Rotation  # here, as in format_tum

    T = np.repeat(np.eye(4)[None], len(data), axis=0)
    T[:, :3, :3] = Rotation.from_quat(data[:, 4:8]).as_matrix()  # scalar-last (x, y, z, w), normalised
    T[:, :3, 3] = data[:, 1:4]
    return Trajectory(t, T, path.name)
