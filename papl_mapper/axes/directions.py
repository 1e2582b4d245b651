"""Sign-invariant helpers on unit direction vectors (lines: d and -d are the same direction)."""

from __future__ import annotations

import numpy as np

from papl_mapper.errors import GeometryError


def unit_rows(v: np.ndarray, what: str = "directions") -> np.ndarray:
    """Normalise the rows of an (N, 3) array; raise GeometryError on zero or non-finite rows."""
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    n = np.linalg.norm(v, axis=1)
    bad = ~np.isfinite(n) | (n < 1e-12)
    if np.any(bad):
        raise GeometryError(
            f"{what}: {int(bad.sum())} of {len(v)} rows are zero or non-finite (first at row "
            f"{int(np.flatnonzero(bad)[0])}); drop degenerate lines before calling"
        )
    return v / n[:, None]


def canonical_sign(v: np.ndarray) -> np.ndarray:
    """Flip rows so that their largest-magnitude component is positive (a stable representative)."""
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    idx = np.argmax(np.abs(v), axis=1)
    s = np.sign(v[np.arange(len(v)), idx])
    s[s == 0] = 1.0
    return v * s[:, None]
