"""Sorting networks (instancing.core.sorting_network)."""

from __future__ import annotations

import numpy as np
import pytest

from instancing.core.backend import Float, UInt32
from instancing.core.sorting_network import comparators, sort_by_key


@pytest.mark.parametrize("n", range(13))
def test_the_network_sorts_every_sequence_of_zeros_and_ones(n):
    # The 0-1 principle: a comparator network that sorts all 2^n sequences of 0s and 1s
    # sorts every sequence.
    for bits in range(1 << n):
        v = [(bits >> k) & 1 for k in range(n)]
        for i, j in comparators(n):
            assert 0 <= i < j < n
            if v[j] < v[i]:
                v[i], v[j] = v[j], v[i]
        assert v == sorted(v), bits


def test_eight_entries_take_19_compare_exchanges():
    assert len(comparators(8)) == 19  # the fewest known for 8 (Knuth, 5.3.4)


def test_sort_by_key_keeps_each_entry_together_per_lane():
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 5, (7, 1000)).astype(np.float32)  # many equal keys
    keys[2, :100] = np.inf
    entries = [(Float(keys[k]), UInt32(np.full(1000, k, np.uint32))) for k in range(7)]
    out = sort_by_key(entries)
    sorted_keys = np.array([np.array(key) for key, _ in out])
    payload = np.array([np.array(tag) for _, tag in out])
    np.testing.assert_array_equal(sorted_keys, np.sort(keys, axis=0))
    # Each key still travels with its own entry's payload, and every entry appears once.
    np.testing.assert_array_equal(np.take_along_axis(keys, payload.astype(np.int64), axis=0), sorted_keys)
    np.testing.assert_array_equal(np.sort(payload, axis=0), np.arange(7)[:, None].repeat(1000, axis=1))


def test_a_negative_count_is_refused():
    with pytest.raises(ValueError, match="count of entries"):
        comparators(-1)
