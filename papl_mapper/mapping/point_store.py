"""Registration's map points by track id: a dict to the bookkeeping, dense arrays to the searches.

Track ids are small dense integers (rows of the frontend's track table), so the points live in arrays
indexed by id. Per-point access behaves as a dict's does (insertion order included, which keeps every
seeded RANSAC that samples points in that order reproducible), while a revisit search over every
mapped point, or PnP over one frame's tracks, reads them with one array lookup instead of a loop.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, MutableMapping

import numpy as np


class PointStore(MutableMapping[int, np.ndarray]):
    """3D points (world) by track id, as a mutable mapping with vectorised lookups."""

    def __init__(self, items: Iterable[tuple[int, np.ndarray]] | dict[int, np.ndarray] = ()) -> None:
        self._xyz = np.zeros((0, 3))
        self._seq = np.zeros(0, np.int64)  # insertion number of each present id, -1 when absent
        self._next = 0
        self._n = 0
        self.update(items)

    def _grow(self, n: int) -> None:
        size = max(n, 2 * len(self._seq), 1024)
        xyz, seq = np.zeros((size, 3)), np.full(size, -1, np.int64)
        xyz[: len(self._xyz)], seq[: len(self._seq)] = self._xyz, self._seq
        self._xyz, self._seq = xyz, seq

    def __getitem__(self, tid: int) -> np.ndarray:
        if tid not in self:
            raise KeyError(tid)
        return self._xyz[tid].copy()

    def __setitem__(self, tid: int, x: np.ndarray) -> None:
        tid = int(tid)
        if tid < 0:
            raise KeyError(tid)
        if tid >= len(self._seq):
            self._grow(tid + 1)
        self._xyz[tid] = x
        if self._seq[tid] < 0:
            self._seq[tid] = self._next
            self._next += 1
            self._n += 1

    def __delitem__(self, tid: int) -> None:
        if tid not in self:
            raise KeyError(tid)
        self._seq[tid] = -1
        self._n -= 1

    def __contains__(self, tid: object) -> bool:
        try:
            i = int(tid)  # type: ignore[call-overload]
        except (TypeError, ValueError):
            return False
        return 0 <= i < len(self._seq) and self._seq[i] >= 0

    def __iter__(self) -> Iterator[int]:
        return iter(self.ids().tolist())

    def __len__(self) -> int:
        return self._n

    def ids(self) -> np.ndarray:
        """Every id, in insertion order (as a dict iterates)."""
        present = np.flatnonzero(self._seq >= 0)
        return present[np.argsort(self._seq[present], kind="stable")]

    def has(self, ids: np.ndarray) -> np.ndarray:
        """Per id whether it has a point (bool, same shape)."""
        ids = np.asarray(ids, np.int64)
        inside = (ids >= 0) & (ids < len(self._seq))
        out = np.zeros(ids.shape, bool)
        out[inside] = self._seq[ids[inside]] >= 0
        return out

    def xyz(self, ids: np.ndarray) -> np.ndarray:
        """Points (N, 3) of ids that all have one."""
        ids = np.asarray(ids, np.int64)
        if not self.has(ids).all():
            raise KeyError("ids without a point")
        return self._xyz[ids]

    def copy(self) -> PointStore:
        """An independent store with the same points in the same order."""
        out = PointStore()
        out._xyz, out._seq, out._next, out._n = self._xyz.copy(), self._seq.copy(), self._next, self._n
        return out
