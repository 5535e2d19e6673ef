"""Binary bounding volume hierarchy: level-by-level build, Dr.Jit traversal.

One structure serves both levels of the two-level acceleration: a BVH over
the world bounds of instances (top level) and one per mesh model over its
triangles in object space (bottom level, shared by all instances).

Build (:mod:`~instancing.accel.sah`, Dr.Jit kernels): items are sorted along a Morton
(Z-order) curve of their box centres, then split one tree level at a time, every pending
node of a level at once (no Python loop over items or nodes), at the plane of least
expected cost under the binned surface area heuristic, which places planes where the
geometry leaves space empty, not where the item count halves. Both levels use it (for
the top level, the trade against faster builds is in docs/how-it-works.md).

:func:`build_forest` builds one tree per run of items in the same passes (a scene's
meshes: the levels of all their trees split together), each tree's nodes contiguous.

Layout: each node stores the boxes of *both* children (so one traversal step
tests two boxes and visits the nearer child first) and two child references
``ref = index << 4 | count``: ``count == 0`` means an inner node ``index``,
``count > 0`` a leaf holding items ``index .. index + count - 1`` of the
item order. The nodes are stored tree by tree, each tree in depth-first order (a node,
then its left subtree, then its right one), so that a walk down a subtree reads nodes
that lie together. Boxes are rounded outward to float32. A node's 12 box coordinates
are read by 12 scalar gathers, which load for the lanes taking a step only (a
float4 packet load, one vector load per lane and a transpose, loads for every
lane of the packet, and a walk's packets have few lanes stepping at a time), and
its references as one uint2 packet load
(:func:`~instancing.core.backend.device_array`).

Traversal keeps a per-lane stack in Dr.Jit local memory and runs inside one
symbolic loop per ray batch; leaves call back into the caller's item test. A walk
from the tree's own root starts at its frontier (:data:`FRONTIER`): the boxes of the
top few subtrees, tested before the loop from scalar kernel inputs, the hit ones
pushed nearest first (sorted and pushed in a branch that a packet none of whose rays
meets one skips), so that a ray into the empty space between them does not enter the loop.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from ..core.backend import Array2u, Array3f, Bool, Float, UInt32, dr, device_array
from ..core.box import outward32, ray_box
from ..core.sorting_network import sort_by_key
from .sah import SAH_MAX_DEPTH, box_area, sah_levels

#: Items per leaf at most (the reference packs the count into 4 bits).
MAX_LEAF_SIZE = 15
_REF_SHIFT = 4
#: Bits of a reference's item or node index (items per tree below 2^28).
_INDEX_BITS = 32 - _REF_SHIFT
#: A refitted tree (:func:`refit_bvh`) is kept while its surface cost stays within this
#: factor of its cost when built, past which traversal slows measurably (benchmarks/scale.py
#: clustered field; sweep in docs/how-it-works.md, "Tuned constants").
REFIT_MAX_COST_GROWTH = 1.005
#: Subtrees of a tree's frontier: from the root's two children, the inner node with the
#: largest box is replaced by its children until there are this many. A ray tests their
#: boxes before its walk (no per-lane gathers; a sorting network puts the hit ones nearest
#: first), and one that hits none never enters the loop: the fastest on clustered fields
#: (sweep in docs/how-it-works.md, "Tuned constants").
FRONTIER = 8
#: Entries of the per-lane traversal stack. At an inner node of depth d (the root has
#: depth 0) the stack holds at most one entry per ancestor, so after the push at most
#: d + 1. A walk from the frontier holds at most FRONTIER - 1 of its subtrees (each at
#: depth >= 1) below the path's entries, which then number one per ancestor below its
#: subtree's top: at most FRONTIER - 1 + d entries after the push. The build splits at
#: the median from depth sah.SAH_MAX_DEPTH on, which halves a node's items (fewer than
#: 2^28) per level, and an inner node holds at least 2: d < SAH_MAX_DEPTH + 28.
STACK_SIZE = FRONTIER - 1 + SAH_MAX_DEPTH + _INDEX_BITS - 1


@dataclass(frozen=True)
class BVHArrays:
    """Flat NumPy arrays of a built BVH (see the module docstring for the layout)."""

    child_lo: np.ndarray  # (M, 2, 3) float32
    child_hi: np.ndarray  # (M, 2, 3) float32
    child_ref: np.ndarray  # (M, 2) uint32
    order: np.ndarray  # (N,) int64: item at leaf position j is order[j]
    root_ref: int

    @property
    def node_count(self) -> int:
        return len(self.child_ref)


class Level(NamedTuple):
    """One level of a build: the pending nodes, ranges ``[start, start + count)`` of the
    item order, and how they were split."""

    start: np.ndarray  # (K,) int64
    count: np.ndarray  # (K,) int64
    is_leaf: np.ndarray  # (K,) bool
    mid: np.ndarray  # (K,) int64: where inner nodes split their range
    child_lo: np.ndarray  # (K_inner, 2, 3): the boxes of the inner nodes' children
    child_hi: np.ndarray


def morton_codes(centres: np.ndarray, lo: np.ndarray | None = None,
                 hi: np.ndarray | None = None) -> np.ndarray:
    """30-bit Morton codes of points (10 bits per axis) in the box (lo, hi): per point
    (N, 3), or one for all, by default the points' bounding box."""
    lo = centres.min(axis=0) if lo is None else lo
    hi = centres.max(axis=0) if hi is None else hi
    extent = np.where(hi > lo, hi - lo, 1.0)
    q = np.clip(((centres - lo) / extent * 1023.0).astype(np.int64), 0, 1023)

    def spread(v: np.ndarray) -> np.ndarray:
        # Interleave two zero bits between the ten bits of v.
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    return (spread(q[:, 0]) << 2) | (spread(q[:, 1]) << 1) | spread(q[:, 2])


def build_bvh(lo: np.ndarray, hi: np.ndarray, leaf_size: int = 4) -> BVHArrays:
    """Build a BVH over N axis-aligned boxes.

    Args:
        lo, hi: (N, 3) float64 box corners, N >= 1, finite.
        leaf_size: items per leaf at most (1 .. MAX_LEAF_SIZE).

    Returns:
        BVHArrays; a tree whose root is a leaf (N <= leaf_size, or an SAH leaf)
        has no nodes.
    """
    return build_forest(lo, hi, [len(lo)], leaf_size)[0]


def build_forest(lo: np.ndarray, hi: np.ndarray, sizes,
                 leaf_size: int = 4) -> tuple[BVHArrays, list[int]]:
    """Build one BVH per run of consecutive boxes, all in one pass (see :func:`build_bvh`).

    Args:
        sizes: the number of boxes of each tree, >= 1 each, summing to N.

    Returns:
        The trees' nodes in one BVHArrays (each tree's nodes contiguous, in the order of
        ``sizes``; ``root_ref`` is the first tree's root), and each
        tree's root reference. The items of tree g keep the positions of its run:
        ``order[j]`` for j in the run is one of the run's indices.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    sizes = np.asarray(sizes, np.int64)
    if len(lo) == 0:
        raise ValueError("build_bvh needs at least one box")
    if sizes.min() < 1 or sizes.sum() != len(lo):
        raise ValueError("each tree needs at least one box, and the sizes must sum to the boxes")
    if not 1 <= leaf_size <= MAX_LEAF_SIZE:
        raise ValueError(f"leaf_size must be in 1..{MAX_LEAF_SIZE}")
    # Step 1: order each tree's items along the Morton curve of their centres in its
    # bounds (the SAH partitions are stable, so its index splits fall back to Morton
    # order too); the tree's index above the 30 bits keeps the runs apart.
    first = np.cumsum(sizes) - sizes
    tree = np.repeat(np.arange(len(sizes)), sizes)
    centre = 0.5 * (lo + hi)
    c_lo, c_hi = np.minimum.reduceat(centre, first), np.maximum.reduceat(centre, first)
    codes = morton_codes(centre, c_lo[tree], c_hi[tree]) | (tree << 30)
    order = np.argsort(codes, kind="stable")
    # Step 2: split one tree level at a time into ranges of the (re)ordered items.
    split, split_order = sah_levels(*outward32(lo[order], hi[order]), first, sizes, leaf_size)
    levels, order = [Level(*level) for level in split], order[split_order]
    # Step 3: inner nodes get ids level by level; every node's reference goes into its
    # parent's child slot (the roots' into root_refs).
    m = sum(int((~level.is_leaf).sum()) for level in levels)
    child_ref = np.zeros((m, 2), np.uint64)
    level_ids = []
    parents, next_id, root_refs = None, 0, None
    for level in levels:
        inner = ~level.is_leaf
        ids = next_id + np.cumsum(inner) - 1
        next_id += int(inner.sum())
        ref = np.where(level.is_leaf, (level.start << _REF_SHIFT) | level.count, ids << _REF_SHIFT)
        if parents is None:
            root_refs = ref.astype(np.uint64)
        else:
            child_ref[parents] = ref.reshape(-1, 2)
        parents = ids[inner]
        level_ids.append(parents)
    # Step 4: renumber the nodes tree by tree, each in depth-first order (a node, then its
    # left subtree, then its right one): the inner nodes below each node (bottom-up), then
    # each node's position from its parent's (top-down).
    # A leaf child points at the entry m, which holds no nodes.
    below = [np.where((child_ref[:, k] & 15) == 0, (child_ref[:, k] >> _REF_SHIFT).astype(np.int64), m)
             for k in (0, 1)]
    size = np.append(np.ones(m, np.int64), 0)
    for ids in reversed(level_ids):
        size[ids] += size[below[0][ids]] + size[below[1][ids]]
    renumber = np.zeros(m + 1, np.int64)
    renumber[level_ids[0]] = np.cumsum(size[level_ids[0]]) - size[level_ids[0]]
    for ids in level_ids:
        left, right = below[0][ids], below[1][ids]
        renumber[left] = renumber[ids] + 1
        renumber[right] = renumber[ids] + 1 + size[left]
    renumber = renumber[:m]
    # The nodes' child boxes (float32 from the build) and references at their new places.
    child_lo, child_hi = np.empty((m, 2, 3), np.float32), np.empty((m, 2, 3), np.float32)
    for level, ids in zip(levels, level_ids):
        child_lo[renumber[ids]], child_hi[renumber[ids]] = level.child_lo, level.child_hi
    child_ref[renumber] = child_ref.copy()
    renumber = renumber.astype(np.uint64)
    for refs in (child_ref, root_refs):
        inner = (refs & 15) == 0
        refs[inner] = renumber[(refs[inner] >> _REF_SHIFT).astype(np.int64)] << _REF_SHIFT
    if int(max(root_refs.max(), child_ref.max(initial=0))) >= 2**32:
        raise ValueError("BVH too large for 32-bit references")
    arrays = BVHArrays(child_lo, child_hi, child_ref.astype(np.uint32), order, int(root_refs[0]))
    return arrays, [int(r) for r in root_refs]


def forest_trees(arrays: BVHArrays, root_refs: list[int], sizes) -> tuple[np.ndarray, np.ndarray]:
    """Each tree's nodes in a forest of :func:`build_forest` (the trees of ``sizes`` items and
    roots ``root_refs``): (first node, node count) per tree. A tree's nodes are contiguous, its
    root first, and it has one inner node fewer than leaves (none where its root is a leaf)."""
    sizes = np.asarray(sizes, np.int64)
    roots = np.asarray(root_refs, np.int64)
    refs = arrays.child_ref.astype(np.int64).ravel()
    leaf_start = (refs >> _REF_SHIFT)[(refs & 15) > 0]
    item_end = np.cumsum(sizes)
    leaves = np.bincount(np.searchsorted(item_end, leaf_start, side="right"), minlength=len(sizes))
    inner_root = (roots & 15) == 0
    return np.where(inner_root, roots >> _REF_SHIFT, 0), np.where(inner_root, leaves - 1, 0)


def tree_costs(arrays: BVHArrays, root_refs: list[int], sizes, root_area: np.ndarray) -> np.ndarray:
    """Each tree's surface cost in a forest (:func:`surface_cost`, with its root box of area
    ``root_area``: one box test pair, or the root leaf's items, for every ray that enters it)."""
    first, count = forest_trees(arrays, root_refs, sizes)
    nodes = np.concatenate([np.arange(f, f + c) for f, c in zip(first, count)]).astype(np.int64)
    area = _box_area(arrays.child_lo[nodes], arrays.child_hi[nodes])
    below = np.bincount(np.repeat(np.arange(len(first)), count),
                        (area * _visit_work(arrays.child_ref[nodes])).sum(axis=1), len(first))
    return below + np.asarray(root_area) * _visit_work(np.asarray(root_refs, np.int64))


def select_trees(arrays: BVHArrays, root_refs: list[int], sizes, keep) -> tuple[BVHArrays, list[int]]:
    """The trees ``keep`` (a mask over the trees) of a forest, as a forest of their own: their
    nodes and leaf positions moved together, ``order`` keeping the built item indices."""
    sizes, keep = np.asarray(sizes, np.int64), np.asarray(keep, bool)
    first, count = forest_trees(arrays, root_refs, sizes)
    item_first = np.cumsum(sizes) - sizes
    node_shift = first - (np.cumsum(np.where(keep, count, 0)) - np.where(keep, count, 0))
    item_shift = item_first - (np.cumsum(np.where(keep, sizes, 0)) - np.where(keep, sizes, 0))
    nodes = np.concatenate([np.arange(f, f + c) for f, c, k in zip(first, count, keep) if k]).astype(np.int64)
    node_tree = np.repeat(np.flatnonzero(keep), count[keep])

    def moved(refs: np.ndarray, tree: np.ndarray) -> np.ndarray:
        refs = refs.astype(np.int64)
        leaf = (refs & 15) > 0
        shift = np.where(leaf, item_shift[tree], node_shift[tree])
        return (((refs >> _REF_SHIFT) - shift) << _REF_SHIFT) | (refs & 15)

    child_ref = moved(arrays.child_ref[nodes], node_tree[:, None]).astype(np.uint32)
    roots = moved(np.asarray(root_refs)[keep], np.flatnonzero(keep))
    order = np.concatenate([arrays.order[f:f + n] for f, n, k in zip(item_first, sizes, keep) if k])
    kept = BVHArrays(arrays.child_lo[nodes], arrays.child_hi[nodes], child_ref, order, int(roots[0]))
    return kept, [int(r) for r in roots]


class BVHKernel:
    """Dr.Jit-side BVH: node arrays as flat jit arrays, and the traversal loop.

    Args:
        arrays: the built tree.
        frontier: subtrees of the frontier that a walk from the root starts at, at most
            :data:`FRONTIER` (the stack's bound, see STACK_SIZE); 0 for none: a node array
            shared by several trees, whose walks start at the caller's root.
        nested: walk in two loops per leaf (steps to a leaf, then its items) instead of one
            flat loop: faster where an item test costs much more than a step (a mesh's
            triangles, an instance BVH's meshes), slower where it costs about as much (an
            instance BVH's spheres).
    """

    def __init__(self, arrays: BVHArrays, frontier: int = FRONTIER, nested: bool = False):
        if not (isinstance(frontier, int) and 0 <= frontier <= FRONTIER):
            raise ValueError(f"frontier must be an integer from 0 to {FRONTIER} subtrees, got {frontier!r}")
        m = arrays.node_count
        # Per node: the 12 coordinates of both child boxes (lo0, hi0, lo1, hi1), and the
        # two references, read as one uint2 packet.
        packed = np.zeros((max(m, 1), 4, 3), np.float32)
        packed[:m, 0] = arrays.child_lo[:, 0]
        packed[:m, 1] = arrays.child_hi[:, 0]
        packed[:m, 2] = arrays.child_lo[:, 1]
        packed[:m, 3] = arrays.child_hi[:, 1]
        refs = np.zeros((max(m, 1), 2), np.uint32)
        refs[:m] = arrays.child_ref
        self.node_count = m
        self.nested = nested
        self.refs = device_array(UInt32, refs.ravel())
        self.root_ref = int(arrays.root_ref)
        # Opaque, like the grid's box: a rebuilt tree's root is read, not compiled in.
        self._opaque_root = dr.opaque(UInt32, self.root_ref)
        self._frontier = _frontier_slots(arrays, frontier)
        self._frontier_refs = [dr.opaque(UInt32, int(arrays.child_ref[node, slot]))
                               for node, slot in self._frontier]
        self._set_boxes(packed)
        # The surface cost at build and now (:func:`surface_cost`): set by the first refit,
        # which alone reads them (a mesh's tree is never refitted).
        self.built_cost: float | None = None
        self.cost: float | None = None

    def _set_boxes(self, packed: np.ndarray) -> None:
        self.boxes = device_array(Float, packed.ravel())
        # The frontier's boxes as opaque scalars: loaded once per packet, and a refitted
        # tree's boxes leave the kernel as it is.
        self._frontier_boxes = [
            tuple(Array3f(*[dr.opaque(Float, float(v)) for v in packed[node, 2 * slot + k]])
                  for k in (0, 1)) for node, slot in self._frontier]

    def frontier(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """The subtrees that a walk from the root starts at, as the kernel reads them:
        (reference, float32 box lo, box hi) each."""
        return [(int(ref[0]), np.array(lo).ravel(), np.array(hi).ravel())
                for ref, (lo, hi) in zip(self._frontier_refs, self._frontier_boxes)]

    def refitted(self, packed: np.ndarray, cost: float) -> BVHKernel:
        """This tree with the node boxes ``packed`` (M, 4, 3) and their surface cost
        (references, root and build cost shared)."""
        tree = copy.copy(self)
        tree._set_boxes(packed)
        tree.cost = cost
        return tree

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
        active = Bool(active)
        stack = dr.alloc_local(UInt32, STACK_SIZE)
        if root_ref is None and self._frontier:
            ref, sp = self._start_at_frontier(stack, o, inv_d, active, t_of(state))
        else:
            ref = dr.zeros(UInt32, dr.width(o)) + (self._opaque_root if root_ref is None else root_ref)
            sp = dr.zeros(UInt32, dr.width(o))
        walk = _traverse_nested if self.nested else _traverse
        return walk(self.boxes, self.refs, o, inv_d, ref, stack, sp, active & (ref != _DONE),
                    state, t_of, test_item)

    def nearest(self, o: Array3f, d: Array3f, t_max: Float, active: Bool, root_ref: UInt32,
                any_hit: bool, distance: Callable[[UInt32, Float], Float]) -> tuple[Float, UInt32]:
        """The nearest item hit by each ray in (0, t_max), walking from ``root_ref``:
        ``(t, position)`` with t = inf where none is; ``distance(position, t_best)`` is an
        item's hit distance, inf where it is not hit before ``t_best``. With ``any_hit``
        (shadow rays) the walk stops at the first item hit, whose t is returned."""
        def test_item(position, state):
            t_best, best = state
            t = distance(position, t_best)
            closer = t < t_best
            # Any-hit: record the hit as -t, which ends the lane's walk (it runs while
            # t_of >= 0; t > 0, so -t < 0).
            return dr.select(closer, -t if any_hit else t, t_best), dr.select(closer, position, best)

        t, position = self.traverse(o, d, active, (Float(t_max), UInt32(0)), lambda s: s[0], test_item,
                                    root_ref)
        if any_hit:
            return dr.select(t < 0, -t, dr.inf), position
        return dr.select(t < t_max, t, dr.inf), position

    def _start_at_frontier(self, stack, o: Array3f, inv_d: Array3f, active: Bool,
                           t_max: Float) -> tuple[UInt32, UInt32]:
        """Test the frontier's boxes, push the hit subtrees farthest first and pop the
        nearest: (the walk's first reference, or _DONE where none is hit; stack pointer).
        The sort and the pushes run in a branch that a packet none of whose rays meets a
        frontier box skips."""
        entries = []
        some = Bool(False)
        for ref, (lo, hi) in zip(self._frontier_refs, self._frontier_boxes):
            t_near, hit = ray_box(lo, hi, o, inv_d, t_max)
            hit &= active
            entries.append((dr.select(hit, t_near, dr.inf), ref))
            some |= hit
        width = dr.width(o)
        return dr.if_stmt(
            (), some, lambda: _push_nearest_first(stack, entries, width),
            lambda: (dr.full(UInt32, _DONE, width), dr.zeros(UInt32, width)))


def _push_nearest_first(stack, entries, width):
    """Push the hit ones of the frontier ``entries`` (distance, ref; a missed one at distance
    inf) farthest first and pop the nearest: (its reference, or _DONE where none is hit;
    stack pointer)."""
    sp = dr.zeros(UInt32, width)
    for distance, ref in reversed(sort_by_key(entries)):
        stack[sp] = ref  # written at every lane, kept (sp moved on) where hit
        sp += dr.select(distance < dr.inf, 1, 0)
    some = sp > 0
    sp -= dr.select(some, 1, 0)
    return dr.select(some, stack[sp], _DONE), sp


#: Reference meaning "stack exhausted": no node or leaf is left to visit.
_DONE = 0xFFFFFFFF


@dr.syntax
def _traverse(boxes, refs, o, inv_d, ref, stack, sp, active, state, t_of, test_item):
    # Loop state at the full ray width. The stack is left uninitialised (only entries
    # below sp, written first, are read): filling it was a 4 KiB memset per 16-lane packet
    # at every entry, i.e. per mesh instance visited in a top-level walk (measured: forest,
    # 128x96, kernel time direct 310 -> 281 ms at 16 spp, path 254 -> 238 ms at 4 spp).
    width = dr.width(o)
    item = dr.zeros(UInt32, width)
    end = dr.zeros(UInt32, width)
    # One flat loop: each iteration tests one item of the current leaf or, when
    # the leaf is exhausted, takes one step through the tree (as the grid walk;
    # flattening keeps SIMD lanes busy). A negative t_of ends the lane (any-hit
    # queries set it once they have found a hit). What the loops only read stays out of
    # their state, so that each body is traced once (Dr.Jit traces a loop again to drop
    # state that comes out unchanged), and out of the branches' state (the branches of
    # the flat loop are a function of their own for that).
    while dr.hint(active & (t_of(state) >= 0), exclude=[boxes, refs, o, inv_d, t_of, test_item]):
        active, ref, sp, item, end, state = _item_or_step(boxes, refs, o, inv_d, stack, active, ref, sp,
                                                          item, end, state, t_of, test_item)
    return state


@dr.syntax
def _item_or_step(boxes, refs, o, inv_d, stack, active, ref, sp, item, end, state, t_of, test_item):
    """One iteration of the flat walk: the current leaf's next item, else the next step."""
    if item < end:
        state = test_item(item, state)
        item += 1
    elif ref == _DONE:
        active = Bool(False)
    else:
        ref, sp, item, end = _visit(boxes, refs, o, inv_d, ref, stack, sp, item, end, t_of(state))
    return active, ref, sp, item, end, state


@dr.syntax
def _traverse_nested(boxes, refs, o, inv_d, ref, stack, sp, active, state, t_of, test_item):
    # As _traverse, in two loops per leaf: steps through the tree until a leaf's items are
    # scheduled, then its items. An iteration of either loop does one kind of work, where
    # the flat loop's iterations pay for both kinds when a packet's lanes need both.
    width = dr.width(o)
    item = dr.zeros(UInt32, width)
    end = dr.zeros(UInt32, width)
    while dr.hint(active & (t_of(state) >= 0), exclude=[boxes, refs, o, inv_d, t_of, test_item]):
        while dr.hint(active & (item >= end) & (ref != _DONE) & (t_of(state) >= 0),
                      exclude=[active, boxes, refs, o, inv_d, state, t_of, test_item]):
            ref, sp, item, end = _visit(boxes, refs, o, inv_d, ref, stack, sp, item, end, t_of(state))
        while dr.hint(active & (item < end) & (t_of(state) >= 0), exclude=[active, end, t_of, test_item]):
            state = test_item(item, state)
            item += 1
        if (ref == _DONE) & (item >= end):
            active = Bool(False)
    return state


@dr.syntax
def _visit(boxes, refs, o, inv_d, ref, stack, sp, item, end, t_max):
    """One step of a walk at ``ref``: a leaf schedules its items (item .. end - 1); an inner
    node tests both child boxes in front of ``t_max``, goes to the nearer and pushes the
    farther. Unless it went down to a child, the next reference is popped (_DONE when the
    stack is empty). Returns (ref, sp, item, end)."""
    count = ref & 15
    index = ref >> _REF_SHIFT
    pop = Bool(True)
    if count > 0:
        item = UInt32(index)
        end = index + count
    else:
        lo0, hi0, lo1, hi1 = (dr.gather(Array3f, boxes, index * 4 + k) for k in range(4))
        tn0, hit0 = ray_box(lo0, hi0, o, inv_d, t_max)
        tn1, hit1 = ray_box(lo1, hi1, o, inv_d, t_max)
        r0, r1 = dr.gather(Array2u, refs, index)
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
    return ref, sp, item, end


def _frontier_slots(arrays: BVHArrays, size: int) -> list[tuple[int, int]]:
    """The (node, child slot) of each subtree of the frontier of ``size`` subtrees (see
    :data:`FRONTIER`); none for a tree whose root is a leaf or for ``size`` < 2."""
    if size < 2 or arrays.root_ref & ((1 << _REF_SHIFT) - 1) or arrays.node_count == 0:
        return []
    area = _box_area(arrays.child_lo, arrays.child_hi)  # (M, 2)
    root = arrays.root_ref >> _REF_SHIFT
    slots = [(root, 0), (root, 1)]
    while len(slots) < size:
        inner = [k for k, (node, slot) in enumerate(slots)
                 if arrays.child_ref[node, slot] & ((1 << _REF_SHIFT) - 1) == 0]
        if not inner:
            break
        k = max(inner, key=lambda k: area[slots[k]])
        child = int(arrays.child_ref[slots[k]]) >> _REF_SHIFT
        slots[k:k + 1] = [(child, 0), (child, 1)]
    return [(int(node), slot) for node, slot in slots]


def surface_cost(packed: np.ndarray, refs: np.ndarray) -> float:
    """Surface-area cost of a tree from its node boxes (M, 4, 3) and references (M, 2):
    the child boxes' areas, a leaf's weighted by its item count (one box test pair per
    inner node visited, one item test per leaf item; the probability of a visit is
    proportional to the box's area, as in the SAH)."""
    area = _box_area(packed[:, 0::2], packed[:, 1::2])  # (M, 2)
    return float((area * _visit_work(refs)).sum())


def _visit_work(refs: np.ndarray) -> np.ndarray:
    """The tests a ray makes on entering the boxes of references ``refs``: one box test
    pair for an inner node, one item test per item of a leaf."""
    count = (np.asarray(refs) & ((1 << _REF_SHIFT) - 1)).astype(np.float64)
    return np.where(count > 0, count, 1.0)


def refit_bvh(tree: BVHKernel, order: np.ndarray, moved: np.ndarray,
              item_bounds: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> BVHKernel | None:
    """``tree`` with the boxes on the paths from the leaves of the items ``moved`` to the
    root recomputed, the tree's shape kept (as Embree's and OptiX's refit/update).

    Args:
        tree: a built tree (its boxes and references are read back).
        order: (N,) the item order of its leaves.
        moved: item indices whose boxes changed.
        item_bounds: ``item_bounds(items) -> (lo, hi)``, float64 (K, 3) boxes of items.

    Returns:
        The refitted tree, or None when refitting cannot keep the tree good: a tree
        without inner nodes, or a surface cost (:func:`surface_cost`, the SAH's estimate
        of the work per ray) grown past REFIT_MAX_COST_GROWTH times the cost at build;
        the caller then builds anew.
    """
    m = tree.node_count
    if m == 0:
        return None
    packed = np.array(tree.boxes, np.float32).reshape(-1, 4, 3)[:m]
    refs = np.asarray(tree.refs).reshape(-1, 2)[:m]
    if tree.built_cost is None:
        tree.built_cost = tree.cost = surface_cost(packed, refs)
    count = refs & ((1 << _REF_SHIFT) - 1)
    index = (refs >> _REF_SHIFT).astype(np.int64)
    # Step 1: every node's parent and slot there (the root has none).
    inner_node, inner_slot = np.nonzero(count == 0)
    parent = np.full(m, -1, np.int64)
    parent_slot = np.zeros(m, np.int64)
    parent[index[inner_node, inner_slot]] = inner_node
    parent_slot[index[inner_node, inner_slot]] = inner_slot
    # Step 2: the leaves holding the moved items (leaves cover the item order in
    # contiguous ranges: the last leaf starting at or before an item's position).
    leaf_node, leaf_slot = np.nonzero(count > 0)
    leaf_start = index[leaf_node, leaf_slot]
    by_start = np.argsort(leaf_start)
    position = np.flatnonzero(np.isin(order, moved))
    leaves = np.unique(by_start[np.searchsorted(leaf_start[by_start], position, side="right") - 1])
    node, slot = leaf_node[leaves], leaf_slot[leaves]
    start, size = leaf_start[leaves], count[node, slot].astype(np.int64)
    # Step 3: the leaves' boxes from all their items' current boxes, rounded outward.
    first = np.cumsum(size) - size
    items = order[np.repeat(start - first, size) + np.arange(size.sum())]
    lo, hi = item_bounds(items)
    leaf_lo, leaf_hi = outward32(np.minimum.reduceat(lo, first), np.maximum.reduceat(hi, first))
    cost = tree.cost + _write_slots(packed, node, slot, leaf_lo, leaf_hi, size)
    # Step 4: up the tree, each changed node's box (the union of its two child boxes,
    # exact in float32) into its parent's slot, until the root; a node reached again
    # through a deeper path is written again, so every box ends up current.
    changed = np.unique(node)
    while len(changed := changed[parent[changed] >= 0]):
        lo = np.minimum(packed[changed, 0], packed[changed, 2])
        hi = np.maximum(packed[changed, 1], packed[changed, 3])
        cost += _write_slots(packed, parent[changed], parent_slot[changed], lo, hi, 1)
        changed = np.unique(parent[changed])
    if cost > REFIT_MAX_COST_GROWTH * tree.built_cost:
        return None
    return tree.refitted(packed, cost)


def _write_slots(packed, node, slot, lo, hi, weight) -> float:
    """Store child boxes (lo, hi) in slots (node, slot) of ``packed``; returns the change of
    their weighted surface area (see :func:`surface_cost`)."""
    before = _box_area(packed[node, 2 * slot], packed[node, 2 * slot + 1])
    packed[node, 2 * slot], packed[node, 2 * slot + 1] = lo, hi
    return float((weight * (_box_area(lo, hi) - before)).sum())


def _box_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Surface area (float64) of boxes (..., 3)."""
    return box_area(lo.astype(np.float64), hi.astype(np.float64))
