"""Vectorised text formatting for the text formats (ASCII PLY, OBJ, TUM, KITTI, COLMAP).

One `%` over a repeated row format and a flat tuple formats a whole block in C instead of a
Python loop per row; blocks bound the memory of the temporary tuple.
"""

from __future__ import annotations

import re

import numpy as np

BLOCK_ROWS = 65_536
# a row format whose conversions all accept floats: %d %i %f %g %e (with flags, width, precision)
_FLOAT_SAFE = re.compile(r"(?:[^%]|%%|%[-+ 0#]*\d*(?:\.\d+)?[difFgGeE])*", re.S)


def format_rows(row_format: str, *columns: np.ndarray) -> bytes:
    """Format rows of equal-length columns with a printf row format ending in a newline.

    Each column is (R,) or (R, k); the row format consumes the columns' values left to right.
    """
    if not columns or len(columns[0]) == 0:
        return b""
    cols = [np.asarray(c).reshape(len(c), -1) for c in columns]
    n = len(cols[0])
    exact = all(
        c.dtype.kind == "f" or (c.dtype.kind in "iub" and (c.size == 0 or np.abs(c).max() < 2**53))
        for c in cols
    )
    if exact and _FLOAT_SAFE.fullmatch(row_format):
        # every conversion takes a float (%d truncates one exactly below 2**53): one float64 table,
        # whose .tolist() runs in C, instead of an object table filled column by column
        table = np.hstack([c.astype(np.float64, copy=False) for c in cols])
        out = []
        for start in range(0, n, BLOCK_ROWS):
            block = table[start : start + BLOCK_ROWS]
            out.append(((row_format * len(block)) % tuple(block.ravel().tolist())).encode())
        return b"".join(out)
    width = sum(c.shape[1] for c in cols)
    out = []
    for start in range(0, n, BLOCK_ROWS):
        stop = min(n, start + BLOCK_ROWS)
        # an object block interleaving the columns: ints stay ints (for %d), floats stay floats
        block = np.empty((stop - start, width), dtype=object)
        k = 0
        for c in cols:
            block[:, k : k + c.shape[1]] = c[start:stop]  # numpy stores Python ints and floats
            k += c.shape[1]
        out.append(((row_format * (stop - start)) % tuple(block.ravel().tolist())).encode())
    return b"".join(out)
