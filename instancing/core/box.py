"""Axis-aligned boxes: the ray/box slab test and the outward float32 rounding that
keeps a box conservative."""

from __future__ import annotations

import numpy as np

from .backend import Array3f, Bool, Float, dr


#: t_far and t_max scaled up by 2 ulp-ish (Ize, "Robust BVH Ray Traversal") in the box test,
#: so that rounding in the slab test never culls a box the ray touches, nor one whose surface
#: ties the nearest hit so far (its entry distance can round above that hit's t).
SLAB_SLACK = 1.0 + 2.0 * 1.1920929e-07


def slab_span(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f) -> tuple[Float, Float]:
    """Slab test of the ray ``o + t d`` (``inv_d = 1 / d``) against a box: the part
    (t_near, t_far) of t >= 0 inside it (empty: t_near > t_far)."""
    return _slabs(lo, hi, o, inv_d, 0.0)


def slab_interval(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f) -> tuple[Float, Float]:
    """The interval (t_enter, t_exit) of the whole line ``o + t d`` inside the box, t of
    either sign (empty: t_enter > t_exit)."""
    return _slabs(lo, hi, o, inv_d, -float("inf"))


def _slabs(lo, hi, o, inv_d, t_from: float) -> tuple[Float, Float]:
    """The last slab entered after ``t_from`` and the first one left, in the precision of
    ``o``. An axis whose distances are NaN (0 * inf: an origin on a slab's plane, the
    direction parallel to it) is left out, so that the box is not culled there."""
    t_lo = (lo - o) * inv_d
    t_hi = (hi - o) * inv_d
    # Each axis's entry and exit by the direction's sign, then the running bounds by
    # compare and select: a NaN compares false and is skipped, and each select compiles to
    # one min or max instruction (dr.minimum's NaN-propagating form takes several).
    backwards = inv_d < 0
    near = dr.select(backwards, t_hi, t_lo)
    far = dr.select(backwards, t_lo, t_hi)
    scalar = type(near.x)
    t_enter, t_exit = scalar(t_from), scalar(float("inf"))
    for k in range(3):
        t_enter = dr.select(near[k] > t_enter, near[k], t_enter)
        t_exit = dr.select(far[k] < t_exit, far[k], t_exit)
    return t_enter, t_exit


def ray_box(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f, t_max: Float) -> tuple[Float, Bool]:
    """Ray/box slab test: (entry distance, hit) for the segment (0, t_max) of the ray
    ``o + t d`` (``inv_d = 1 / d``)."""
    t_near, t_far = slab_span(lo, hi, o, inv_d)
    return t_near, within(t_near, t_far) & within(t_near, t_max)


def within(t_near: Float, t_max: Float) -> Bool:
    """Whether a box entered at ``t_near`` lies within ``t_max`` up to the slab test's
    rounding (:data:`SLAB_SLACK`): the test that culls a box behind the nearest hit."""
    return t_near <= t_max * SLAB_SLACK


def outward32(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Round float64 boxes outward to float32 so that they stay conservative."""
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


#: Cells of the pairing grid (:func:`overlapping_pairs`) a box may cover before it is paired
#: with every box of the other set instead.
PAIRING_MAX_CELLS = 64
#: Box pairs (N M) up to which :func:`overlapping_pairs` tests every pair, a few at a time,
#: instead of building the grid (a handful of moving boxes against a large field).
PAIRING_DIRECT_TESTS = 1 << 24
#: Pair tests per block of rows in that case (memory of a block: a few bytes a test).
PAIRING_BLOCK_TESTS = 1 << 20


def overlapping_pairs(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray | None = None,
                      hi_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The index pairs (i, j), each once and in order of i then j, of the boxes ``a_i`` and
    ``b_j`` (float64 (N, 3) and (M, 3) corners, lo <= hi) that overlap or touch; without
    ``b``, the pairs i < j of the boxes ``a``.

    Step 1: a uniform grid of cells the size of the median box extent; each box lists the
    cells it covers. Step 2: two boxes that share the cell holding the larger of their lower
    corners are candidates (each pair meets there once), tested exactly. A box covering
    more than PAIRING_MAX_CELLS cells (a ground under many objects) is tested against every
    box instead (step 3). Memory and time grow with the boxes and the pairs that share
    cells, not with N M. Where N M is at most PAIRING_DIRECT_TESTS, every pair is tested
    (step 0: rows of a against all of b).
    """
    same = lo_b is None
    lo_a, hi_a = (np.asarray(v, np.float64).reshape(-1, 3) for v in (lo_a, hi_a))
    lo_b, hi_b = (lo_a, hi_a) if same else (np.asarray(v, np.float64).reshape(-1, 3) for v in (lo_b, hi_b))
    if not len(lo_a) or not len(lo_b):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(lo_a) * len(lo_b) <= PAIRING_DIRECT_TESTS:
        return _tested_pairs(lo_a, hi_a, lo_b, hi_b, same)
    extents = np.concatenate([hi_a - lo_a, hi_b - lo_b]).max(axis=1)
    origin = np.minimum(lo_a.min(axis=0), lo_b.min(axis=0))
    cell = max(float(np.median(extents)), 1e-300)
    first_a, last_a = _cells(lo_a, hi_a, origin, cell)
    first_b, last_b = _cells(lo_b, hi_b, origin, cell)
    big_a = np.prod(last_a - first_a + 1, axis=1) > PAIRING_MAX_CELLS
    big_b = np.prod(last_b - first_b + 1, axis=1) > PAIRING_MAX_CELLS
    pairs = [_shared_cell_pairs(first_a, last_a, np.flatnonzero(~big_a),
                                first_b, last_b, np.flatnonzero(~big_b))]
    # Step 3: each outsized box against every box (an outsized pair from the a side only).
    for k in np.flatnonzero(big_a):
        j = np.flatnonzero(_overlap(lo_a[k], hi_a[k], lo_b, hi_b))
        pairs.append((np.full(len(j), k), j))
    for k in np.flatnonzero(big_b):
        i = np.flatnonzero(_overlap(lo_a, hi_a, lo_b[k], hi_b[k]) & ~big_a)
        pairs.append((i, np.full(len(i), k)))
    i = np.concatenate([p[0] for p in pairs])
    j = np.concatenate([p[1] for p in pairs])
    keep = _overlap(lo_a[i], hi_a[i], lo_b[j], hi_b[j])
    if same:
        # Each unordered pair met as (i, j) and (j, i): the first; a box with itself never.
        keep &= i < j
    key = np.sort(i[keep] * len(lo_b) + j[keep])
    return key // len(lo_b), key % len(lo_b)


def swept_overlap(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray,
                  sweep: np.ndarray) -> np.ndarray:
    """Whether boxes ``a`` meet boxes ``b`` moved along ``sweep`` (b + t sweep, 0 <= t <= 1),
    pair by pair (float64 (N, 3) arrays): the segment t sweep against the box a - b of
    their Minkowski difference, by slabs. Where a shifted slab bound rounds, the test keeps
    the pair (a relative slack of 1e-9)."""
    m_lo, m_hi = lo_a - hi_b, hi_a - lo_b
    slack = 1e-9 * (np.abs(m_lo) + np.abs(m_hi) + np.abs(sweep))
    m_lo, m_hi = m_lo - slack, m_hi + slack
    moving = sweep != 0.0
    step = np.where(moving, sweep, 1.0)
    t_lo, t_hi = m_lo / step, m_hi / step
    enter = np.where(moving, np.minimum(t_lo, t_hi), -np.inf)
    leave = np.where(moving, np.maximum(t_lo, t_hi), np.inf)
    # An axis the sweep keeps still: the boxes overlap there or never meet.
    still = np.all(moving | ((m_lo <= 0.0) & (0.0 <= m_hi)), axis=-1)
    enter = np.maximum(enter.max(axis=-1), 0.0)
    leave = np.minimum(leave.min(axis=-1), 1.0)
    return still & (enter <= leave)


def _tested_pairs(lo_a, hi_a, lo_b, hi_b, same: bool) -> tuple[np.ndarray, np.ndarray]:
    """Step 0 of :func:`overlapping_pairs`: each box of a tested against every box of b, in
    blocks of rows of about PAIRING_BLOCK_TESTS tests."""
    rows = max(1, PAIRING_BLOCK_TESTS // len(lo_b))
    pairs = []
    for first in range(0, len(lo_a), rows):
        block = slice(first, first + rows)
        hit = _overlap(lo_a[block, None], hi_a[block, None], lo_b[None], hi_b[None])
        if same:
            hit &= np.arange(first, first + hit.shape[0])[:, None] < np.arange(len(lo_b))[None]
        i, j = np.nonzero(hit)
        pairs.append((i + first, j))
    return np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])


def _overlap(lo_a, hi_a, lo_b, hi_b) -> np.ndarray:
    """Whether boxes overlap or touch (broadcast over leading axes), axis by axis."""
    meet = (lo_a[..., 0] <= hi_b[..., 0]) & (lo_b[..., 0] <= hi_a[..., 0])
    for k in (1, 2):
        meet &= (lo_a[..., k] <= hi_b[..., k]) & (lo_b[..., k] <= hi_a[..., k])
    return meet


def _cells(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The first and last grid cell (per axis) that boxes cover."""
    limit = float((1 << 21) - 1)  # (a key packs three cell coordinates of 21 bits)
    first = np.clip(np.floor((lo - origin) / cell), 0, limit).astype(np.int64)
    last = np.clip(np.floor((hi - origin) / cell), 0, limit).astype(np.int64)
    return first, last


def _shared_cell_pairs(first_a, last_a, rows_a, first_b, last_b, rows_b) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the boxes ``rows_a`` and ``rows_b`` that share the grid cell holding the
    larger of their first cells (per axis), from each box's cells as sorted keys."""
    key_a, box_a = _cell_keys(first_a, last_a, rows_a)
    key_b, box_b = _cell_keys(first_b, last_b, rows_b)
    # Both sorted by cell: the lookups then read the cells in order.
    order_a, order_b = np.argsort(key_a), np.argsort(key_b)
    key_a, box_a, key_b, box_b = key_a[order_a], box_a[order_a], key_b[order_b], box_b[order_b]
    start = np.searchsorted(key_b, key_a, side="left")
    count = np.searchsorted(key_b, key_a, side="right") - start
    a = np.repeat(box_a, count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    b = box_b[np.repeat(start, count) + offset]
    shared = _key(np.maximum(first_a[a], first_b[b])) == np.repeat(key_a, count)
    return a[shared], b[shared]


def _key(cell: np.ndarray) -> np.ndarray:
    """One integer per grid cell (x, y, z) (each below 2^21)."""
    return (cell[..., 0] << 42) | (cell[..., 1] << 21) | cell[..., 2]


def _cell_keys(first: np.ndarray, last: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One (cell key, box) entry per cell that each box of ``rows`` covers."""
    first, span = first[rows], np.maximum(last[rows] - first[rows] + 1, 0)
    count = np.prod(span, axis=1)
    box = np.repeat(rows, count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    span_r, first_r = np.repeat(span, count, axis=0), np.repeat(first, count, axis=0)
    x = first_r[:, 0] + k % span_r[:, 0]
    y = first_r[:, 1] + (k // span_r[:, 0]) % span_r[:, 1]
    z = first_r[:, 2] + k // (span_r[:, 0] * span_r[:, 1])
    return _key(np.stack([x, y, z], axis=-1)), box
