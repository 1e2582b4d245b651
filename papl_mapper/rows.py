"""Unique rows of an array without numpy's structured (void) view.

`np.unique(a, axis=0)` sorts and compares a structured view of `a`; a Ctrl-C that lands inside those
comparisons comes out as a TypeError ("Cannot compare structured arrays ..."), so a run ended with
that error instead of stopping at its checkpoint. Sorting the columns with `np.lexsort` keeps the
interrupt a KeyboardInterrupt.
"""

from __future__ import annotations

import numpy as np


def unique_rows(
    a: np.ndarray, return_index: bool = False, return_inverse: bool = False
) -> np.ndarray | tuple[np.ndarray, ...]:
    """The distinct rows of the 2-D array `a` in lexicographic order, as `np.unique(a, axis=0)`; with
    `return_index` the row of each one's first occurrence, with `return_inverse` each row's index among
    them (1-D)."""
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"unique_rows takes a 2-D array, not {a.ndim}-D")
    order = np.lexsort(a.T[::-1]) if a.shape[1] else np.arange(len(a))  # stable: first occurrence first
    s = a[order]
    first = np.ones(len(a), bool)
    if len(a) > 1:
        first[1:] = (s[1:] != s[:-1]).any(axis=1)
    out: list[np.ndarray] = [s[first]]
    if return_index:
        out.append(order[first])
    if return_inverse:
        inverse = np.empty(len(a), np.intp)
        inverse[order] = np.cumsum(first) - 1
        out.append(inverse)
    return out[0] if len(out) == 1 else tuple(out)
