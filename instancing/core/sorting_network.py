"""Sorting networks: a few per-lane entries sorted by a fixed sequence of compare-exchanges,
which a kernel runs as selects, with no branches and no memory."""

from __future__ import annotations

from functools import cache

from .backend import dr


@cache
def comparators(n: int) -> tuple[tuple[int, int], ...]:
    """The compare-exchanges ``(i, j)``, ``i < j``, of Batcher's merge exchange for ``n``
    entries (Knuth, TAOCP vol. 3, 5.2.2, Algorithm M): 19 for 8 entries, the fewest known."""
    if not (isinstance(n, int) and n >= 0):
        raise ValueError(f"a sorting network needs a count of entries >= 0, got {n!r}")
    pairs = []
    t = max(n - 1, 0).bit_length()
    p = 1 << (t - 1) if t else 0
    while p > 0:
        q, r, d = 1 << (t - 1), 0, p
        while d > 0:
            pairs.extend((i, i + d) for i in range(n - d) if i & p == r)
            d, q, r = q - p, q // 2, p
        p //= 2
    return tuple(pairs)


def sort_by_key(entries: list[tuple]) -> list[tuple]:
    """``entries`` (tuples of Dr.Jit arrays of one width) sorted per lane by their first
    element, ascending. Not stable: the order of entries with equal keys is the network's."""
    entries = list(entries)
    for i, j in comparators(len(entries)):
        a, b = entries[i], entries[j]
        swap = b[0] < a[0]
        entries[i] = tuple(dr.select(swap, y, x) for x, y in zip(a, b))
        entries[j] = tuple(dr.select(swap, x, y) for x, y in zip(a, b))
    return entries
