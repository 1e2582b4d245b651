"""Axis update after BA (paper "Update"): adopt big changes, delete axes that keep jumping, merge
adjacent axes keeping the older one. The vertical axis is never deleted and wins every merge."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.axes.config import AxesConfig
from papl_mapper.axes.directions import unit_rows
from papl_mapper.errors import GeometryError
from papl_mapper.geometry.lines import line_angle_deg
from papl_mapper.map import Axes

log = logging.getLogger(__name__)


@dataclass
class AxisState:
    """Book-keeping per axis: creation serial (smaller = older), age in updates, jump count."""

    serial: np.ndarray  # (A,) int64
    age: np.ndarray  # (A,) int64
    jumps: np.ndarray  # (A,) int64
    vertical_index: int = -1
    next_serial: int = 0

    @classmethod
    def new(cls, n_axes: int, vertical_index: int = -1) -> AxisState:
        s = np.arange(n_axes, dtype=np.int64)
        z = np.zeros(n_axes, np.int64)
        return cls(s, z.copy(), z.copy(), vertical_index, n_axes)

    def __len__(self) -> int:
        return len(self.serial)

    def appended(self, n_new: int) -> AxisState:
        """State with n_new freshly created axes appended (youngest serials)."""
        s = np.arange(self.next_serial, self.next_serial + n_new, dtype=np.int64)
        z = np.zeros(n_new, np.int64)
        return AxisState(
            np.concatenate([self.serial, s]),
            np.concatenate([self.age, z]),
            np.concatenate([self.jumps, z]),
            self.vertical_index,
            self.next_serial + n_new,
        )


@dataclass
class UpdateResult:
    """Axes after the update, their state, and what happened (for logs and to remap line weights)."""

    axes: np.ndarray  # (A', 3)
    state: AxisState
    index_map: np.ndarray  # (A,) old axis -> new axis index (merged -> the kept axis), -1 deleted
    adopted: list[int] = field(default_factory=list)  # old indices whose post-BA direction was taken
    deleted: list[tuple[int, str]] = field(default_factory=list)  # (old index, reason)
    merged: list[tuple[int, int]] = field(default_factory=list)  # (removed old index, kept old index)

    @property
    def vertical_index(self) -> int:
        return self.state.vertical_index

    def messages(self) -> list[str]:
        out = [f"axis {i}: adopted the post-BA direction" for i in self.adopted]
        out += [f"axis {i}: deleted ({why})" for i, why in self.deleted]
        out += [f"axis {a}: merged into axis {b}" for a, b in self.merged]
        return out

    def to_map_axes(self) -> Axes:
        return Axes(self.axes.copy(), int(self.state.vertical_index))


def remap_weights(weights: np.ndarray, index_map: np.ndarray, n_new: int) -> np.ndarray:
    """Carry (N, A) line weights over to the updated axes: merged columns add up, deleted ones drop."""
    out = np.zeros((weights.shape[0], n_new))
    for old, new in enumerate(index_map):
        if new >= 0:
            out[:, new] += weights[:, old]
    return out


def update_axes(
    old_axes: np.ndarray, new_axes: np.ndarray, state: AxisState, config: AxesConfig | None = None
) -> UpdateResult:
    """Compare axes before (A,3) and after (A,3) BA; adopt, count jumps, delete, merge."""
    config = config or AxesConfig()
    old = unit_rows(old_axes, "axes before BA") if len(old_axes) else np.zeros((0, 3))
    new = unit_rows(new_axes, "axes after BA") if len(new_axes) else np.zeros((0, 3))
    a = len(old)
    if len(new) != a or len(state) != a:
        raise GeometryError(f"axis update: {a} axes before BA, {len(new)} after, {len(state)} in the state")
    change = np.degrees(np.arccos(np.clip(np.abs(np.sum(old * new, axis=1)), 0.0, 1.0)))
    result_dirs = old.copy()
    adopted = np.flatnonzero(change > config.tau_diff_deg)
    for i in adopted:
        result_dirs[i] = new[i] if old[i] @ new[i] >= 0 else -new[i]
    jumps = state.jumps + (change > config.jump_deg)
    age = state.age + 1
    keep = np.ones(a, bool)
    deleted: list[tuple[int, str]] = []
    for i in range(a):
        if i != state.vertical_index and jumps[i] >= config.max_jumps:
            keep[i] = False
            deleted.append((i, f"jumped more than {config.jump_deg} deg {int(jumps[i])} times"))
    # merge adjacent axes: the older (smaller serial) survives, the vertical always survives
    merged: list[tuple[int, int]] = []
    target = np.arange(a)
    order = sorted(range(a), key=lambda i: (i != state.vertical_index, state.serial[i]))
    ang = line_angle_deg(result_dirs[:, None], result_dirs[None]) if a else np.zeros((0, 0))
    for pos, i in enumerate(order):
        if not keep[i]:
            continue
        for j in order[pos + 1 :]:
            if keep[j] and ang[i, j] < config.merge_deg:
                keep[j] = False
                target[j] = i
                merged.append((j, i))
                deleted.append((j, f"within {config.merge_deg} deg of older axis {i}"))
    kept = np.flatnonzero(keep)
    new_index = np.full(a, -1, np.int64)
    new_index[kept] = np.arange(len(kept))
    index_map = np.full(a, -1, np.int64)
    for i in range(a):
        if keep[i]:
            index_map[i] = new_index[i]
        elif target[i] != i:
            index_map[i] = new_index[target[i]]
    vi = int(new_index[state.vertical_index]) if state.vertical_index >= 0 else -1
    out_state = AxisState(state.serial[kept], age[kept], jumps[kept], vi, state.next_serial)
    res = UpdateResult(result_dirs[kept], out_state, index_map, [int(i) for i in adopted], deleted, merged)
    for msg in res.messages():
        log.info(msg)
    return res
