"""Binned surface area heuristic splits of a BVH build, one tree level at a time on Dr.Jit.

Wald, "On fast Construction of SAH-based Bounding Volume Hierarchies" (2007), and
pbrt-v4's ``BVHAggregate::buildRecursive``: the centroids of a node's items are binned
into SAH_BINS slabs along each axis of their bounds; each of the 3 (SAH_BINS - 1) planes
between bins is scored with the expected cost of the split,
``SAH_TRAVERSAL_COST + (A_left n_left + A_right n_right) / A_node`` (in units of one item
test), against ``n`` for a leaf. A node becomes a leaf when it holds one item, or at most
``leaf_size`` and no split is cheaper; otherwise it is split at its cheapest plane, or at
its median index (in the order the items come in) when all its centroids coincide, no
plane's cost is finite, or it lies SAH_MAX_DEPTH deep.

All pending nodes of a level are split together, in four steps per level:

1. binning: every item adds itself to its node's bin on each axis (atomic count, minima and
   maxima: order-independent, so the build is deterministic), SAH_CHUNK_NODES nodes at a
   time so that the bin arrays stay small;
2. sweep: one lane per (node, axis) accumulates the bins from both ends and keeps its
   cheapest plane; per node the cheapest of its three axes. Nodes of at most
   SAH_SMALL_NODE items (most nodes of the deep levels) skip steps 1 and 2: one lane per
   (node, axis) sorts their few items by bin and finds the same plane at the same cost;
3. decision (NumPy, one entry per node): leaf, split by plane, or split at the median;
4. partition: a stable partition of each split node's items (left ones first, each side in
   its order) by an exclusive prefix sum, and the children's boxes and centroid bounds by
   atomic minima and maxima.

Item boxes are float32, rounded outward, so that the children's boxes (minima and maxima
of them) contain the float64 items.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..core.backend import Array3f, Bool, Float, UInt32, dr
from ..core.sorting_network import sort_by_key

#: Bins per axis, and the cost of one traversal step (two box tests) in units of one item
#: test: fewest loop iterations per ray on the bundled meshes (sweep in
#: docs/how-it-works.md, "Tuned constants").
SAH_BINS = 16
SAH_TRAVERSAL_COST = 1.0
#: Depth from which nodes split at the median index instead. An SAH split can be as
#: uneven as 1 : n - 1, so its depth alone is unbounded; from this depth on the items per
#: node halve each level, so inner nodes lie less than SAH_MAX_DEPTH + log2(N) <= 32 + 28 =
#: 60 deep (see bvh.STACK_SIZE).
SAH_MAX_DEPTH = 32
#: Nodes binned at once (bounds the bins of one pass to SAH_CHUNK_NODES * 3 * SAH_BINS).
SAH_CHUNK_NODES = 32768
#: Nodes of at most this many items are scored without bins (:func:`_small_planes`): four
#: in five of the nodes scored on the LEGO scene, where the bins cost more than the items.
SAH_SMALL_NODE = 8
#: Bin of an absent item in :func:`_small_planes` (after every real bin).
_ABSENT = 0xFFFFFFFF
#: Reductions run in per-thread copies (Dr.Jit's ``Expand`` mode: plain read-modify-writes
#: instead of atomics, which collide near the root, where every item of a level meets the
#: same few bins) while the copies hold at most this many entries together, their arrays
#: padded to a power of two (the size is compiled into the kernel); larger ones pre-reduce
#: within a packet (``Local``), with no size in the kernel. The copies are filled and summed
#: on every call, so their total is bounded rather than each copy's size (sweep in
#: docs/how-it-works.md, "Tuned constants").
_EXPAND_ENTRIES = 1 << 21
_LARGE_MODE = dr.ReduceMode.Local


def sah_levels(lo: np.ndarray, hi: np.ndarray, start: np.ndarray, count: np.ndarray,
               leaf_size: int) -> tuple[list[tuple], np.ndarray]:
    """Split N >= 1 float32 boxes (in the order given) level by level, from the roots
    ``[start, start + count)`` (consecutive ranges covering them, each non-empty).

    Returns:
        The levels from the root's down, each as the fields of
        :class:`~instancing.accel.bvh.Level` (float32 child boxes), and the item order:
        position j of the leaves' ranges holds item ``order[j]`` of the input.
    """
    n = len(lo)
    lo, hi = _without_subnormals(lo, hi)
    # The items of the pending nodes by position, in node order: each one's position, node,
    # box and input index. An item's input index goes into ``order`` at its position when
    # its node becomes a leaf.
    pos, seg = dr.arange(UInt32, n), UInt32(np.repeat(np.arange(len(start)), count).astype(np.uint32))
    item_lo, item_hi = Array3f(*lo.T.copy()), Array3f(*hi.T.copy())
    item_index, order = dr.arange(UInt32, n), dr.zeros(UInt32, n)
    centre = 0.5 * lo + 0.5 * hi
    node_lo, node_hi = np.minimum.reduceat(lo, start), np.maximum.reduceat(hi, start)
    c_min, c_max = np.minimum.reduceat(centre, start), np.maximum.reduceat(centre, start)
    levels = []
    for depth in itertools.count():
        # Step 1 and 2: bin the items and find each node's cheapest plane.
        item_c = 0.5 * item_lo + 0.5 * item_hi
        bins = _bins(item_c, dr.gather(Array3f, _device(c_min), seg),
                     dr.gather(Array3f, _device(c_max), seg))
        dr.eval(bins)
        cost, plane, axis = _best_planes(item_lo, item_hi, bins, seg, count, node_lo, node_hi)
        # Step 3: leaf, split at the cheapest plane, or split at the median index. Costs
        # are times the node's area; where float32 areas overflow, inf or NaN: no plane.
        with np.errstate(over="ignore", invalid="ignore"):
            splittable = np.isfinite(cost)
            cheaper = splittable & (cost < count * box_area(node_lo, node_hi))
        is_leaf = (count <= 1) | ((count <= leaf_size) & ~cheaper)
        inner = ~is_leaf
        if not inner.any():
            dr.scatter(order, item_index, pos)
            levels.append((start, count, is_leaf, start, *(np.zeros((0, 2, 3), np.float32),) * 2))
            break
        by_plane = splittable & (depth < SAH_MAX_DEPTH) & inner
        # Step 4: partition the inner nodes' items; their children's boxes.
        node_start, moving = _per_item(start, seg), _per_item(inner, seg)
        local = pos - node_start  # each item's position within its node
        goes_left = _goes_left(bins, local, seg, count, by_plane, plane, axis) & moving
        n_left = dr.zeros(UInt32, len(start))
        dr.scatter_reduce(dr.ReduceOp.Add, n_left, UInt32(goes_left), seg)
        rank = dr.prefix_sum(UInt32(goes_left))
        dr.eval(n_left, rank)
        mid = start + n_left.numpy()
        offset = np.cumsum(count) - count  # each node's first entry in the item list
        rank_left = rank - dr.gather(UInt32, rank, _per_item(offset, seg))
        left = dr.gather(UInt32, n_left, seg)
        new_pos = node_start + dr.select(goes_left, rank_left, left + local - rank_left)
        child_base = 2 * _per_item(np.cumsum(inner) - 1, seg)
        child = child_base + dr.select(goes_left, 0, 1)
        k = 2 * int(inner.sum())
        children = [_reduced(op, k, v, child, moving) for op, v in
                    ((dr.ReduceOp.Min, item_lo), (dr.ReduceOp.Max, item_hi),
                     (dr.ReduceOp.Min, item_c), (dr.ReduceOp.Max, item_c))]
        dr.scatter(order, item_index, pos, ~moving)
        # The moving items at their new positions among the next level's items.
        pending = count * inner
        slot = _per_item(np.cumsum(pending) - pending, seg) + new_pos - node_start
        item_lo, item_hi, item_index = (_moved(v, slot, moving, int(pending.sum()))
                                        for v in (item_lo, item_hi, item_index))
        # The next level: the children of the inner nodes, in their order. A position
        # belongs to the left child when it lies before the node's split.
        child_of = child_base + dr.select(local < left, 0, 1)
        keep = dr.compress(moving)
        pos, seg = dr.gather(UInt32, pos, keep), dr.gather(UInt32, child_of, keep)
        dr.eval(item_lo, item_hi, item_index, order, children, pos, seg)
        child_lo, child_hi, c_min, c_max = (np.stack([c.numpy()[:k] for c in v], axis=1) for v in children)
        levels.append((start, count, is_leaf, mid, child_lo.reshape(-1, 2, 3), child_hi.reshape(-1, 2, 3)))
        end = start + count
        start = np.stack([start[inner], mid[inner]], axis=1).ravel()
        count = np.stack([mid[inner], end[inner]], axis=1).ravel() - start
        node_lo, node_hi = child_lo, child_hi
    return levels, order.numpy().astype(np.int64)


def _without_subnormals(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes with subnormal coordinates rounded outward to zero or the smallest normal float:
    Dr.Jit's kernels flush subnormals to zero, which could shrink a box."""
    tiny = np.finfo(np.float32).tiny
    lo = np.where(np.abs(lo) < tiny, np.where(lo < 0, -tiny, 0), lo).astype(np.float32)
    hi = np.where(np.abs(hi) < tiny, np.where(hi > 0, tiny, 0), hi).astype(np.float32)
    return lo, hi


def _device(rows: np.ndarray) -> Array3f:
    return Array3f(*np.ascontiguousarray(rows.T, np.float32))


def _bins(c: Array3f, c_min: Array3f, c_max: Array3f) -> list[UInt32]:
    """Each item's bin along the three axes of its node's centroid bounds (a flat axis puts
    every item into bin 0 and so offers no split)."""
    bins = []
    for a in range(3):
        extent = c_max[a] - c_min[a]
        fraction = dr.select(extent > 0, (c[a] - c_min[a]) / extent, 0.0)
        bins.append(dr.minimum(UInt32(fraction * SAH_BINS), SAH_BINS - 1))
    return bins


def _best_planes(item_lo: Array3f, item_hi: Array3f, bins: list[UInt32], seg: UInt32,
                 count: np.ndarray, node_lo: np.ndarray, node_hi: np.ndarray):
    """(cost, plane, axis) of each node's cheapest plane (cost inf where it has none): nodes
    of at most SAH_SMALL_NODE items from their items directly (:func:`_small_planes`), the
    others binned SAH_CHUNK_NODES at a time."""
    k = len(count)
    offset = np.concatenate([[0], np.cumsum(count)])
    cost, plane = np.full((k, 3), np.inf, np.float32), np.zeros((k, 3), np.int64)
    small = count <= SAH_SMALL_NODE
    if small.any():
        cost[small], plane[small] = _small_planes(item_lo, item_hi, bins, offset[:-1][small], count[small],
                                                  node_lo[small], node_hi[small])
    large = np.flatnonzero(~small)
    if 0 < len(large) < k:
        # The large nodes' items, their nodes numbered among the large ones.
        keep = dr.compress(dr.gather(Bool, Bool(~small), seg))
        renumbered = UInt32(np.cumsum(~small).astype(np.uint32) - 1)
        item_lo, item_hi = dr.gather(Array3f, item_lo, keep), dr.gather(Array3f, item_hi, keep)
        bins = [dr.gather(UInt32, b, keep) for b in bins]
        seg = dr.gather(UInt32, renumbered, dr.gather(UInt32, seg, keep))
        offset = np.concatenate([[0], np.cumsum(count[large])])
    for first in range(0, len(large), SAH_CHUNK_NODES):
        last = min(first + SAH_CHUNK_NODES, len(large))
        if first == 0 and last == len(large):
            chunk = (item_lo, item_hi, bins, seg)
        else:
            index = dr.arange(UInt32, int(offset[last] - offset[first])) + dr.opaque(UInt32, offset[first])
            chunk = (dr.gather(Array3f, item_lo, index), dr.gather(Array3f, item_hi, index),
                     [dr.gather(UInt32, b, index) for b in bins],
                     dr.gather(UInt32, seg, index) - dr.opaque(UInt32, first))
        nodes = large[first:last]
        cost[nodes], plane[nodes] = _sweep(*_binned(*chunk, last - first), count[nodes],
                                           node_lo[nodes], node_hi[nodes])
    # The cheapest axis; among equal costs the lowest plane, then the lowest axis.
    axis = np.lexsort((np.arange(3)[None].repeat(k, 0), plane, cost), axis=1)[:, 0]
    rows = np.arange(k)
    return cost[rows, axis], plane[rows, axis], axis


def _binned(item_lo: Array3f, item_hi: Array3f, bins: list[UInt32], seg: UInt32, k: int):
    """Per (node, axis, bin), flat in that order: the item count and the box of the items."""
    size, mode = _reduction_size(k * 3 * SAH_BINS)
    count = dr.zeros(UInt32, size)
    lo, hi = _filled(np.inf, size), _filled(-np.inf, size)
    for a in range(3):
        key = (seg * 3 + a) * SAH_BINS + bins[a]
        dr.scatter_reduce(dr.ReduceOp.Add, count, UInt32(1), key, mode=mode)
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Min, lo[c], item_lo[c], key, mode=mode)
            dr.scatter_reduce(dr.ReduceOp.Max, hi[c], item_hi[c], key, mode=mode)
    dr.eval(count, lo, hi)
    return count, lo, hi


def _sweep(bin_count: UInt32, bin_lo: Array3f, bin_hi: Array3f, count: np.ndarray,
           node_lo: np.ndarray, node_hi: np.ndarray):
    """(cost, plane) per (node, axis): one lane per (node, axis) accumulates its bins from the
    right end, then from the left end scores each plane (the plane after bin s has bins
    <= s on its left) and keeps the cheapest (the first of equal ones). Both passes are
    unrolled over the SAH_BINS bins, so that the partial sums stay in registers."""
    k = len(count)
    lane, _, _, node_area = _node_axis_lanes(node_lo, node_hi)
    bins = [(dr.gather(Array3f, bin_lo, lane * SAH_BINS + s), dr.gather(Array3f, bin_hi, lane * SAH_BINS + s),
             dr.gather(UInt32, bin_count, lane * SAH_BINS + s)) for s in range(SAH_BINS)]

    def add_bin(s, lo, hi, total):
        return dr.minimum(lo, bins[s][0]), dr.maximum(hi, bins[s][1]), total + bins[s][2]

    # Right pass: the area and count of bins s .. SAH_BINS - 1, for s >= 1.
    right = {}
    part = (Array3f(np.inf), Array3f(-np.inf), UInt32(0))
    for s in range(SAH_BINS - 1, 0, -1):
        part = add_bin(s, *part)
        right[s] = (box_area(part[0], part[1]), part[2])
    # Left pass: the cost of the plane after bin s, for s < SAH_BINS - 1.
    part = (Array3f(np.inf), Array3f(-np.inf), UInt32(0))
    best, plane = dr.full(Float, np.inf, 3 * k), dr.zeros(UInt32, 3 * k)
    for s in range(SAH_BINS - 1):
        part = add_bin(s, *part)
        area_right, n_right = right[s + 1]
        cost = _split_cost(node_area, part[2], box_area(part[0], part[1]), n_right, area_right)
        better = (part[2] > 0) & (n_right > 0) & (cost < best)
        best, plane = dr.select(better, cost, best), dr.select(better, s, plane)
    return _per_axis(best, plane, k)


def _small_planes(item_lo: Array3f, item_hi: Array3f, bins: list[UInt32], first: np.ndarray,
                  count: np.ndarray, node_lo: np.ndarray, node_hi: np.ndarray):
    """(cost, plane) per (node, axis) of nodes of at most SAH_SMALL_NODE items (the items of
    node j at ``first[j] ..``), as :func:`_sweep` finds them, without bins: one lane per
    (node, axis) sorts the node's items by their bin (a sorting network) and scores the
    plane after each bin that has items beyond it. A plane inside a run of empty bins
    splits the items as the plane after the run's last non-empty bin below, which the
    sweep, keeping the first of equal costs, picks; the boxes and counts on either side
    are the same unions and sums, so the costs are the same float32 numbers."""
    k = len(count)
    _, node, axis, node_area = _node_axis_lanes(node_lo, node_hi)
    start, n = (dr.gather(UInt32, UInt32(v.astype(np.uint32)), node) for v in (first, count))
    # The node's items; absent ones with the largest bin (sorted last) and an empty box.
    items = []
    for i in range(SAH_SMALL_NODE):
        present = i < n
        index = start + i
        b = dr.select(axis == 0, dr.gather(UInt32, bins[0], index, present),
                      dr.select(axis == 1, dr.gather(UInt32, bins[1], index, present),
                                dr.gather(UInt32, bins[2], index, present)))
        items.append((dr.select(present, b, _ABSENT),
                      dr.select(present, dr.gather(Array3f, item_lo, index, present), np.inf),
                      dr.select(present, dr.gather(Array3f, item_hi, index, present), -np.inf)))
    items = sort_by_key(items)
    # The boxes of the items from i on (right sides), then the planes from the left.
    right = [None] * SAH_SMALL_NODE
    lo, hi = Array3f(np.inf), Array3f(-np.inf)
    for i in range(SAH_SMALL_NODE - 1, 0, -1):
        lo, hi = dr.minimum(lo, items[i][1]), dr.maximum(hi, items[i][2])
        right[i] = box_area(lo, hi)
    lo, hi = Array3f(np.inf), Array3f(-np.inf)
    best, plane = dr.full(Float, np.inf, 3 * k), dr.zeros(UInt32, 3 * k)
    for i in range(SAH_SMALL_NODE - 1):
        lo, hi = dr.minimum(lo, items[i][1]), dr.maximum(hi, items[i][2])
        # The plane after item i's bin, where the next item lies in a later bin.
        b, after = items[i][0], items[i + 1][0]
        cost = _split_cost(node_area, UInt32(i + 1), box_area(lo, hi), n - (i + 1), right[i + 1])
        better = (after > b) & (after != _ABSENT) & (cost < best)
        best, plane = dr.select(better, cost, best), dr.select(better, b, plane)
    return _per_axis(best, plane, k)


def _node_axis_lanes(node_lo: np.ndarray, node_hi: np.ndarray):
    """One lane per (node, axis) of the nodes with boxes (node_lo, node_hi): the lane index,
    its node and axis, and the node's box area."""
    lane = dr.arange(UInt32, 3 * len(node_lo))
    node = lane // 3
    node_area = box_area(*(dr.gather(Array3f, _device(v), node) for v in (node_lo, node_hi)))
    return lane, node, lane - 3 * node, node_area


def _split_cost(node_area: Float, n_left: UInt32, area_left: Float, n_right: UInt32,
                area_right: Float) -> Float:
    """Expected cost of a split, times the node's area, in units of one item test."""
    return SAH_TRAVERSAL_COST * node_area + Float(n_left) * area_left + Float(n_right) * area_right


def _per_axis(best: Float, plane: UInt32, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Lanes (node, axis) as (k, 3) NumPy arrays: cost (float32) and plane."""
    dr.eval(best, plane)
    return best.numpy().reshape(k, 3), plane.numpy().reshape(k, 3).astype(np.int64)


def _goes_left(bins, local, seg, count, by_plane, plane, axis) -> Bool:
    """Whether each item (at ``local`` within its node) would go to its node's left child:
    its bin on the split axis is at most the plane's, or (median splits) it lies in the
    first half of the node's range."""
    ax = _per_item(axis, seg)
    b = dr.select(ax == 0, bins[0], dr.select(ax == 1, bins[1], bins[2]))
    median = local < (_per_item(count, seg) + 1) // 2
    return dr.select(_per_item(by_plane, seg), b <= _per_item(plane, seg), median)


def _per_item(values: np.ndarray, seg: UInt32):
    """Each item's entry of its node's ``values`` (bool or non-negative integers)."""
    if values.dtype == bool:
        return dr.gather(Bool, Bool(values), seg)
    return dr.gather(UInt32, UInt32(values.astype(np.uint32)), seg)


def _moved(values, slot: UInt32, active: Bool, size: int):
    """An array of ``size`` entries holding ``values`` at ``slot`` where ``active`` (every
    entry is the slot of exactly one active lane)."""
    out = dr.empty(type(values), size)
    dr.scatter(out, values, slot, active)
    return out


def _reduced(op, size: int, values: Array3f, index: UInt32, active: Bool) -> Array3f:
    """Per index below ``size``, the minimum or maximum of ``values`` (componentwise; the
    array may be padded)."""
    padded, mode = _reduction_size(size)
    out = _filled(np.inf if op == dr.ReduceOp.Min else -np.inf, padded)
    for c in range(3):
        dr.scatter_reduce(op, out[c], values[c], index, active, mode=mode)
    return out


def _reduction_size(size: int) -> tuple[int, dr.ReduceMode]:
    """The array size and mode of a scatter-reduction into ``size`` entries."""
    padded = 1 << (size - 1).bit_length()
    if padded * dr.thread_count() <= _EXPAND_ENTRIES:
        return padded, dr.ReduceMode.Expand
    return size, _LARGE_MODE


def _filled(value: float, size: int) -> Array3f:
    return Array3f(*(dr.full(Float, value, size) for _ in range(3)))


def box_area(lo, hi):
    """Surface area of boxes: NumPy arrays (..., 3) or Dr.Jit vectors; 0 for empty boxes
    (lo = inf)."""
    if isinstance(lo, np.ndarray):
        d = np.moveaxis(np.maximum(hi - lo, 0.0), -1, 0)
    else:
        d = dr.maximum(hi - lo, 0.0)
    return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
