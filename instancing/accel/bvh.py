"""Binary bounding volume hierarchy: NumPy build, Dr.Jit traversal.

One structure serves both levels of the two-level acceleration: a BVH over
the world bounds of instances (top level) and one per mesh model over its
triangles in object space (bottom level, shared by all instances).

Build: items are sorted along a Morton (Z-order) curve of their box centres
and split at the median index, level by level, with NumPy segment
reductions; this is O(N log N), has no Python loop over items or nodes, and
builds a million boxes in well under a second. Clusters stay contiguous in
Morton order, so the tree adapts to clustered scenes where a uniform grid
does not.

Layout: each node stores the boxes of *both* children (so one traversal step
tests two boxes and visits the nearer child first) and two child references
``ref = index << 4 | count``: ``count == 0`` means an inner node ``index``,
``count > 0`` a leaf holding items ``index .. index + count - 1`` of the
item order. Boxes are rounded outward to float32.

Traversal keeps a per-lane stack in Dr.Jit local memory and runs inside one
symbolic loop per ray batch; leaves call back into the caller's item test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..backend import Array3f, Array4f, Bool, Float, UInt32, dr

#: Items per leaf at most (the reference packs the count into 4 bits).
MAX_LEAF_SIZE = 15
#: Entries of the per-lane traversal stack; the median split bounds the depth
#: by log2(N) + 1, so 64 covers any tree that fits in memory.
STACK_SIZE = 64
_REF_SHIFT = 4


@dataclass(frozen=True)
class BVHArrays:
    """Flat NumPy arrays of a built BVH (see the module docstring for the layout)."""

    child_lo: np.ndarray  # (M, 2, 3) float32
    child_hi: np.ndarray  # (M, 2, 3) float32
    child_ref: np.ndarray  # (M, 2) uint32
    order: np.ndarray  # (N,) int64: item at leaf position j is order[j]
    root_ref: int
    bounds: tuple[np.ndarray, np.ndarray]  # the whole tree's box (float64)

    @property
    def node_count(self) -> int:
        return len(self.child_ref)


def morton_codes(centres: np.ndarray) -> np.ndarray:
    """30-bit Morton codes of points (10 bits per axis) in their bounding box."""
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    extent = np.where(hi > lo, hi - lo, 1.0)
    q = np.clip(((centres - lo) / extent * 1023.0).astype(np.int64), 0, 1023)

    def spread(v: np.ndarray) -> np.ndarray:
        # Interleave two zero bits between the ten bits of v.
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    return (spread(q[:, 0]) << 2) | (spread(q[:, 1]) << 1) | spread(q[:, 2])


def _outward32(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Round float64 boxes outward to float32 so that they stay conservative."""
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


def build_bvh(lo: np.ndarray, hi: np.ndarray, leaf_size: int = 4) -> BVHArrays:
    """Build a BVH over N axis-aligned boxes.

    Args:
        lo, hi: (N, 3) float64 box corners, N >= 1, finite.
        leaf_size: items per leaf at most (1 .. MAX_LEAF_SIZE).

    Returns:
        BVHArrays; a tree of N <= leaf_size items is a single leaf root with
        no nodes.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    n = len(lo)
    if n == 0:
        raise ValueError("build_bvh needs at least one box")
    if not 1 <= leaf_size <= MAX_LEAF_SIZE:
        raise ValueError(f"leaf_size must be in 1..{MAX_LEAF_SIZE}")
    # Step 1: order the items along the Morton curve of their centres.
    order = np.argsort(morton_codes(0.5 * (lo + hi)), kind="stable")
    slo, shi = lo[order], hi[order]
    bounds = (lo.min(axis=0), hi.max(axis=0))
    if n <= leaf_size:
        empty3 = np.zeros((0, 2, 3), np.float32)
        return BVHArrays(empty3, empty3.copy(), np.zeros((0, 2), np.uint32), order,
                         (0 << _REF_SHIFT) | n, bounds)

    # Step 2: split ranges at the median index, one tree level at a time.
    # Each pending inner node is a range [start, end) of the sorted items.
    starts, ends = np.array([0]), np.array([n])
    node_ids = np.array([0])
    next_id = 1
    level_records = []
    while len(starts):
        mid = starts + (ends - starts + 1) // 2
        cs = np.stack([starts, mid], axis=1)  # (K, 2) child starts
        ce = np.stack([mid, ends], axis=1)
        counts = ce - cs
        is_leaf = counts <= leaf_size
        # Child boxes: segment min/max of the sorted item boxes.
        flat_s, flat_e = cs.ravel(), ce.ravel()
        clo = _segment_reduce(np.minimum, slo, flat_s, flat_e).reshape(-1, 2, 3)
        chi = _segment_reduce(np.maximum, shi, flat_s, flat_e).reshape(-1, 2, 3)
        # Inner children get fresh node ids in this level's order.
        inner = ~is_leaf
        ids = np.zeros_like(counts)
        ids[inner] = next_id + np.arange(int(inner.sum()))
        next_id += int(inner.sum())
        ref = np.where(is_leaf, (cs << _REF_SHIFT) | counts, ids << _REF_SHIFT)
        level_records.append((node_ids, clo, chi, ref))
        starts, ends, node_ids = cs[inner], ce[inner], ids[inner]

    m = next_id
    child_lo = np.zeros((m, 2, 3))
    child_hi = np.zeros((m, 2, 3))
    child_ref = np.zeros((m, 2), np.uint64)
    for ids, clo, chi, ref in level_records:
        child_lo[ids], child_hi[ids], child_ref[ids] = clo, chi, ref
    if int(child_ref.max()) >= 2**32:
        raise ValueError("BVH too large for 32-bit references")
    lo32, hi32 = _outward32(child_lo, child_hi)
    return BVHArrays(lo32, hi32, child_ref.astype(np.uint32), order, 0, bounds)


def _segment_reduce(op: np.ufunc, values: np.ndarray, starts: np.ndarray,
                    ends: np.ndarray) -> np.ndarray:
    """op-reduction of values[start:end] for each non-empty segment (gaps allowed)."""
    # reduceat over interleaved (start, end) indices: even entries are the segments.
    padded = np.concatenate([values, values[:1]])
    return op.reduceat(padded, np.stack([starts, ends], axis=1).ravel(), axis=0)[::2]


class BVHKernel:
    """Dr.Jit-side BVH: node arrays as flat jit arrays, and the traversal loop."""

    def __init__(self, arrays: BVHArrays):
        m = arrays.node_count
        # Per node: 2 children x (lo, hi) packed as 4 float4 packets for packet gathers; the
        # child references ride in the lo packets' fourth lane (bit patterns), so that one
        # node step reads 64 bytes in 4 packet gathers and nothing else.
        packed = np.zeros((max(m, 1), 4, 4), np.float32)
        packed[:m, 0, :3] = arrays.child_lo[:, 0]
        packed[:m, 1, :3] = arrays.child_hi[:, 0]
        packed[:m, 2, :3] = arrays.child_lo[:, 1]
        packed[:m, 3, :3] = arrays.child_hi[:, 1]
        packed.view(np.uint32)[:m, 0, 3] = arrays.child_ref[:, 0]
        packed.view(np.uint32)[:m, 2, 3] = arrays.child_ref[:, 1]
        self.boxes = Float(packed.ravel())
        self.root_ref = int(arrays.root_ref)

    @staticmethod
    def _slab(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f, t_max: Float):
        """Ray/box slab test: (entry distance, hit) for the segment (0, t_max)."""
        t0 = (lo - o) * inv_d
        t1 = (hi - o) * inv_d
        t_near = dr.maximum(dr.max(dr.minimum(t0, t1)), 0.0)
        t_far = dr.min(dr.maximum(t0, t1))
        # Scale t_far up by 2 ulp-ish (Ize, "Robust BVH Ray Traversal") so that
        # rounding in the slab test never culls a box the ray touches.
        t_far = t_far * (1.0 + 2.0 * 1.1920929e-07)
        return t_near, (t_near <= t_far) & (t_near <= t_max)

    def traverse(self, o: Array3f, d: Array3f, active: Bool, state: Any,
                 t_of: Callable[[Any], Float], test_item: Callable[[UInt32, Any], Any],
                 root_ref: UInt32 | int | None = None) -> Any:
        """Visit the leaves a ray may hit in front of ``t_of(state)``, nearest first.

        Args:
            o, d: ray (in the space the tree was built in); d need not be unit.
            active: lanes to traverse.
            state: the caller's loop state (a PyTree); ``t_of(state)`` is the
                current closest hit distance, used to cull farther boxes; a
                negative value ends the lane's traversal.
            test_item: ``test_item(position, state) -> state`` tests the item
                at ``position`` of the item order (called for each item of a leaf).
            root_ref: per-lane root reference (meshes sharing one node array);
                defaults to this tree's root.

        Returns:
            The final state.
        """
        inv_d = dr.rcp(d)
        root = self.root_ref if root_ref is None else root_ref
        return _traverse(self.boxes, o, inv_d, UInt32(root), Bool(active), state, t_of, test_item)


#: Reference meaning "stack exhausted": no node or leaf is left to visit.
_DONE = 0xFFFFFFFF


@dr.syntax
def _traverse(boxes, o, inv_d, ref, active, state, t_of, test_item):
    # Loop state at the full ray width (a width-1 local stack cannot index per lane).
    width = dr.width(o)
    ref = dr.zeros(UInt32, width) + ref
    stack = dr.alloc_local(UInt32, STACK_SIZE, dr.zeros(UInt32, width))
    sp = dr.zeros(UInt32, width)
    item = dr.zeros(UInt32, width)
    end = dr.zeros(UInt32, width)
    # One flat loop: each iteration tests one item of the current leaf or, when
    # the leaf is exhausted, takes one step through the tree (as the grid walk;
    # flattening keeps SIMD lanes busy). A negative t_of ends the lane (any-hit
    # queries set it once they have found a hit).
    while active & (t_of(state) >= 0):
        if item < end:
            state = test_item(item, state)
            item += 1
        elif ref == _DONE:
            active = Bool(False)
        else:
            count = ref & 15
            index = ref >> _REF_SHIFT
            pop = Bool(True)
            if count > 0:
                # Leaf: schedule its items, then continue with the next stack entry.
                item = UInt32(index)
                end = index + count
            else:
                # Inner node: test both child boxes, go to the nearer, push the farther.
                t_max = t_of(state)
                lo0 = dr.gather(Array4f, boxes, index * 4 + 0)
                hi0 = dr.gather(Array4f, boxes, index * 4 + 1)
                lo1 = dr.gather(Array4f, boxes, index * 4 + 2)
                hi1 = dr.gather(Array4f, boxes, index * 4 + 3)
                tn0, hit0 = BVHKernel._slab(Array3f(lo0.x, lo0.y, lo0.z),
                                            Array3f(hi0.x, hi0.y, hi0.z), o, inv_d, t_max)
                tn1, hit1 = BVHKernel._slab(Array3f(lo1.x, lo1.y, lo1.z),
                                            Array3f(hi1.x, hi1.y, hi1.z), o, inv_d, t_max)
                r0 = dr.reinterpret_array(UInt32, lo0.w)
                r1 = dr.reinterpret_array(UInt32, lo1.w)
                if hit0 & hit1:
                    first_is_0 = tn0 <= tn1
                    stack[sp] = dr.select(first_is_0, r1, r0)
                    sp += 1
                    ref = dr.select(first_is_0, r0, r1)
                    pop = Bool(False)
                elif hit0 | hit1:
                    ref = dr.select(hit0, r0, r1)
                    pop = Bool(False)
            if pop:
                if sp == 0:
                    ref = UInt32(_DONE)
                else:
                    sp -= 1
                    ref = stack[sp]
    return state
