"""unique_rows: np.unique(axis=0)'s answer, and a Ctrl-C inside it stays a KeyboardInterrupt."""

from __future__ import annotations

import signal
import time
from collections import Counter

import numpy as np
import pytest

from papl_mapper.rows import unique_rows


@pytest.mark.parametrize("shape", [(0, 2), (1, 2), (7, 1), (500, 2), (300, 3)])
@pytest.mark.parametrize("kind", ["int", "float"])
def test_unique_rows_is_numpys_unique_along_rows(shape, kind):
    rng = np.random.default_rng(sum(shape))
    a = rng.integers(-4, 5, shape)
    if kind == "float":
        a = a * 0.25
    want = np.unique(a, axis=0, return_index=True, return_inverse=True)
    got = unique_rows(a, return_index=True, return_inverse=True)
    assert np.array_equal(got[0], want[0])
    assert np.array_equal(got[1], want[1])  # first occurrences
    assert np.array_equal(got[2], want[2].ravel())
    assert np.array_equal(got[0][got[2]], a)
    assert np.array_equal(unique_rows(a), want[0])


def test_unique_rows_refuses_other_than_two_dimensions():
    with pytest.raises(ValueError, match="2-D"):
        unique_rows(np.arange(4))


def _outcomes(fn, a: np.ndarray, trials: int) -> Counter:
    """SIGALRM raising KeyboardInterrupt at a random moment of `fn(a)`: what came out of the call."""

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for _ in range(20):
        fn(a)
    duration = (time.perf_counter() - t0) / 20
    previous = signal.signal(signal.SIGALRM, interrupt)
    seen: Counter = Counter()
    try:
        for _ in range(trials):
            try:
                signal.setitimer(signal.ITIMER_REAL, rng.uniform(1e-6, duration))
                fn(a)
                outcome = "returned"
            except KeyboardInterrupt:
                outcome = "KeyboardInterrupt"
            except Exception as exc:  # noqa: BLE001 - what the interrupt turned into is the finding
                outcome = type(exc).__name__
            try:
                time.sleep(2 * duration + 1e-3)  # the timer fired after the call returned
            except KeyboardInterrupt:
                pass
            seen[outcome] += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    return seen


def test_an_interrupt_inside_unique_rows_stays_a_keyboard_interrupt():
    """np.unique(axis=0) turned about 2% of these into TypeError (and a run caught it: Ctrl-C lost)."""
    a = np.random.default_rng(1).integers(0, 50, (100, 2))
    seen = _outcomes(unique_rows, a, 400)
    assert set(seen) <= {"KeyboardInterrupt", "returned"}, seen
    assert seen["KeyboardInterrupt"] > 0, seen
