"""Registration's point store: a dict's behaviour (order included) with array lookups."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.mapping.point_store import PointStore


def test_point_store_behaves_as_a_dict_and_keeps_insertion_order():
    rng = np.random.default_rng(0)
    store, ref = PointStore(), {}
    for _ in range(3000):  # random inserts, overwrites and deletes, as registration and loops do
        tid = int(rng.integers(0, 5000))
        if rng.random() < 0.25 and tid in ref:
            del store[tid], ref[tid]
        else:
            x = rng.normal(size=3)
            store[tid], ref[tid] = x, x
    assert len(store) == len(ref) and list(store) == list(ref)
    assert all(np.array_equal(store[t], ref[t]) for t in ref)
    ids = np.arange(-3, 5200)
    np.testing.assert_array_equal(store.has(ids), [int(t) in ref for t in ids])
    held = np.array(list(ref)[::7])
    np.testing.assert_array_equal(store.xyz(held), np.stack([ref[int(t)] for t in held]))
    assert -1 not in store and 10**9 not in store and "a" not in store
    with pytest.raises(KeyError):
        store.xyz(np.array([int(np.flatnonzero(~store.has(np.arange(5000)))[0])]))


def test_point_store_values_are_copies_and_copy_is_independent():
    store = PointStore({3: np.zeros(3)})
    x = store[3]
    store[3] = np.ones(3)
    assert np.array_equal(x, np.zeros(3))  # what was read earlier does not change under it
    twin = store.copy()
    twin[3] = np.full(3, 2.0)
    del twin[3]
    assert np.array_equal(store[3], np.ones(3)) and 3 not in twin and 3 in store
