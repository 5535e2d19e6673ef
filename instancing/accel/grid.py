"""Uniform grid over the instances' world bounding boxes (lecture: "Grids and
Transformed Objects").

Each cell stores references to the instances whose world box overlaps it
(compressed sparse rows: the items of cell ``c`` are
``cell_items[cell_start[c]:cell_start[c + 1]]``). A ray walks the cells it
crosses in order with a 3D DDA (Amanatides & Woo, "A Fast Voxel Traversal
Algorithm", 1987) and stops as soon as its closest hit lies before the exit
of the current cell. The DDA runs one cell ahead of the item tests, so that
the next cell's range is already on its way from memory while the current
cell's items are tested. The walk can stop after a number of loop iterations
and resume from its saved state (:class:`WalkState`), which large ray batches
use to walk in passes
(:func:`instancing.scene.intersection.intersect_preliminary_in_passes`), sorted by
their entry cell (:meth:`GridKernel.entry_keys`) in large scenes. When a few
instances move (optimisation steps), :func:`update_grid` moves their
references instead of building the grid anew.

We write the DDA ourselves rather than using ``drjit.dda``: that helper's
callback interface nested with our per-cell item loop gave run-to-run
differing hit counts in a prototype (Dr.Jit 1.5), while this loop matched
brute force exactly; it also lets the termination test use our hit distance.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable

import numpy as np

from ..core.backend import (Array3b, Array3f, Array3i, Array3u, Bool, Float, UInt32, device_arrays,
                            dr)
from ..core.box import slab_span

#: Target number of cells per instance: fastest at 100 000 instances and half the cell
#: memory of 8 (benchmarks/intersect.py sphere fields; docs/how-it-works.md).
CELLS_PER_INSTANCE = 4.0
#: Largest resolution along one axis and largest number of references.
MAX_RESOLUTION = 1024
MAX_REFERENCES = 64_000_000
#: Relative slack of the early-exit test against the cell's exit distance, so
#: that rounding in the DDA never stops the walk before a boundary hit.
EXIT_SLACK = 1e-5
#: Bits per axis of the entry-cell code that orders large ray batches
#: (:meth:`GridKernel.entry_keys`), 2^12 buckets: the fastest sorted walk at 100 000 spheres
#: (benchmarks/intersect.py; docs/how-it-works.md).
ENTRY_KEY_BITS = 4


@dataclass(frozen=True)
class GridArrays:
    """A built grid in NumPy form."""

    lo: np.ndarray  # (3,) float64 grid box
    hi: np.ndarray
    resolution: np.ndarray  # (3,) int64 cells per axis (x, y, z)
    cell_start: np.ndarray  # (C + 1,) uint32, C = prod(resolution); cell_start[C] = R
    cell_items: np.ndarray  # (R,) uint32 instance indices

    @property
    def cell_count(self) -> np.ndarray:
        """(C,) number of items in each cell."""
        return np.diff(self.cell_start.astype(np.int64))


def grid_resolution(lo: np.ndarray, hi: np.ndarray, n: int) -> np.ndarray:
    """Cells per axis so that the grid has about CELLS_PER_INSTANCE * n cubic cells."""
    extent = hi - lo
    # Flat scenes: give degenerate axes a sliver of thickness so the volume is non-zero.
    extent = np.maximum(extent, 1e-3 * max(extent.max(), 1e-30))
    cell = (np.prod(extent) / (CELLS_PER_INSTANCE * n)) ** (1.0 / 3.0)
    return np.clip(np.round(extent / cell), 1, MAX_RESOLUTION).astype(np.int64)


def build_grid(lo: np.ndarray, hi: np.ndarray) -> GridArrays | None:
    """Insert N world boxes (N, 3) into a uniform grid.

    Returns None when the grid would need more than MAX_REFERENCES
    references (huge overlapping instances); the scene then uses its BVH.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    n = len(lo)
    g_lo, g_hi = lo.min(axis=0), hi.max(axis=0)
    res = grid_resolution(g_lo, g_hi, n)
    # Widen the grid box a little so that hits on its faces lie inside it.
    pad = 1e-6 * (g_hi - g_lo).max() + 1e-7 * max(np.abs(g_lo).max(), np.abs(g_hi).max())
    g_lo, g_hi = g_lo - pad, g_hi + pad
    cells, items = _references(lo, hi, g_lo, g_hi, res, np.arange(n))
    if cells is None:
        return None
    order = np.argsort(cells, kind="stable")
    counts = np.bincount(cells, minlength=int(np.prod(res)))
    starts = np.concatenate([[0], np.cumsum(counts)])
    return GridArrays(g_lo, g_hi, res, starts.astype(np.uint32), items[order].astype(np.uint32))


def update_grid(arrays: GridArrays, moved: np.ndarray, lo: np.ndarray,
                hi: np.ndarray) -> GridArrays | None:
    """The grid with the instances ``moved`` (K indices) now in the world boxes ``lo``,
    ``hi`` (K, 3): their references are taken out of every cell and put into the cells
    their new boxes overlap, at the end of each cell's list; the other cells' lists
    and the grid's box and resolution stay. O(references) NumPy work, against the sort
    of a full build (measured at 1e6 instances: 2.3 s per build).

    Returns None when a new box leaves the grid's box or the references would exceed
    MAX_REFERENCES: the caller then builds the grid anew.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if (lo < arrays.lo).any() or (hi > arrays.hi).any():
        return None
    res = arrays.resolution
    cell_count = int(np.prod(res))
    # Take the moved instances' references out (a cell per reference from the CSR rows).
    keep = ~np.isin(arrays.cell_items, moved)
    ref_cell = np.repeat(np.arange(cell_count), arrays.cell_count)
    kept_counts = np.bincount(ref_cell[keep], minlength=cell_count)
    kept = arrays.cell_items[keep]
    # Put them into the cells of their new boxes, after each cell's kept items.
    cells, items = _references(lo, hi, arrays.lo, arrays.hi, res, np.asarray(moved, np.int64))
    if cells is None or len(kept) + len(cells) > MAX_REFERENCES:
        return None
    order = np.argsort(cells, kind="stable")
    cells, items = cells[order], items[order]
    merged = np.insert(kept, np.cumsum(kept_counts)[cells], items.astype(np.uint32))
    counts = kept_counts + np.bincount(cells, minlength=cell_count)
    starts = np.concatenate([[0], np.cumsum(counts)])
    return GridArrays(arrays.lo, arrays.hi, res, starts.astype(np.uint32), merged)


def _references(lo, hi, g_lo, g_hi, res, ids):
    """Every (cell index, instance id) pair of the boxes ``lo``, ``hi`` (K, 3) of instances
    ``ids`` in the grid (g_lo, g_hi, res), instance by instance; (None, None) past
    MAX_REFERENCES."""
    cell = (g_hi - g_lo) / res
    # Cell ranges of each box, widened by a small fraction of a cell against rounding in the DDA.
    slack = 1e-4 * cell
    i0 = np.clip(np.floor((lo - slack - g_lo) / cell), 0, res - 1).astype(np.int64)
    i1 = np.clip(np.floor((hi + slack - g_lo) / cell), 0, res - 1).astype(np.int64)
    span = i1 - i0 + 1
    per_item = np.prod(span, axis=1)
    total = int(per_item.sum())
    if total > MAX_REFERENCES:
        return None, None
    # Enumerate every (item, cell) pair without a Python loop: local offset j of
    # each reference within its item's box of cells, unravelled to (jx, jy, jz).
    item = np.repeat(np.arange(len(lo)), per_item)
    first = np.cumsum(per_item) - per_item
    j = np.arange(total) - np.repeat(first, per_item)
    sx, sy = span[item, 0], span[item, 1]
    jx = j % sx
    jy = (j // sx) % sy
    jz = j // (sx * sy)
    cx, cy, cz = i0[item, 0] + jx, i0[item, 1] + jy, i0[item, 2] + jz
    return (cz * res[1] + cy) * res[0] + cx, ids[item]


class GridKernel:
    """Dr.Jit-side grid: CSR arrays and the DDA traversal loop."""

    def __init__(self, arrays: GridArrays):
        self.lo = [float(v) for v in arrays.lo]
        self.hi = [float(v) for v in arrays.hi]
        self.resolution = [int(r) for r in arrays.resolution]
        # In Dr.Jit's own storage (backend.device_arrays), not wrapping NumPy buffers.
        self.cell_start, self.items = device_arrays(UInt32, arrays.cell_start, arrays.cell_items)
        # The grid's box and resolution enter kernels as opaque values, not literals:
        # a grid rebuilt for moved instances reuses the compiled kernels, and a
        # recorded optimisation step (instancing.ad.optimisation) reads them as inputs.
        cell_size = [float(v) for v in (arrays.hi - arrays.lo) / arrays.resolution]
        self._opaque_box = (dr.opaque(Array3f, self.lo), dr.opaque(Array3f, self.hi),
                            dr.opaque(Array3f, cell_size), dr.opaque(Array3i, self.resolution))

    def arrays(self) -> GridArrays:
        """The grid in NumPy form, read back (the host copy is not kept: memory)."""
        return GridArrays(np.array(self.lo), np.array(self.hi), np.array(self.resolution, np.int64),
                          np.asarray(self.cell_start), np.asarray(self.items))

    def traverse(self, o: Array3f, d: Array3f, active: Bool, state: Any,
                 t_of: Callable[[Any], Float], test_item: Callable[[UInt32, Any], Any]) -> Any:
        """Walk the cells along the ray front to back, testing each cell's items.

        Args and return value as :meth:`BVHKernel.traverse`; ``test_item``
        receives positions into :attr:`items`.
        """
        walk = self.start(o, d, active)
        return self.resume(d, walk, state, t_of, test_item)[1]

    def entry_keys(self, o: Array3f, d: Array3f) -> UInt32:
        """Per ray, the Morton code of the cell where it enters the grid, on a coarser
        lattice of at most 2^ENTRY_KEY_BITS cells per axis (3 * ENTRY_KEY_BITS bits;
        rays that miss the grid box count as entering at its nearest cell). Rays with
        close codes start their walks close to each other."""
        g_lo, g_hi, cell_size, res = self._opaque_box
        res_i = Array3i(*res)
        cell = _entry_cell(o, d, dr.rcp(d), g_lo, g_hi, cell_size, res_i)[2]
        coarse = Array3u(cell * (1 << ENTRY_KEY_BITS)) // Array3u(res_i)
        return _spread_bits(coarse.x) | (_spread_bits(coarse.y) << 1) | (_spread_bits(coarse.z) << 2)

    def start(self, o: Array3f, d: Array3f, active: Bool) -> WalkState:
        """The rays' walks, at their first cell."""
        return _walk_start(o, d, Bool(active), *self._opaque_box, self.cell_start)

    def resume(self, d: Array3f, walk: WalkState, state: Any, t_of: Callable[[Any], Float],
               test_item: Callable[[UInt32, Any], Any],
               max_steps: int | None = None) -> tuple[WalkState, Any]:
        """Go on with walks from ``walk`` for at most ``max_steps`` loop iterations (one item
        test or cell step each; None: to the end). A walk has ended where ``walk.active``
        is False or ``t_of(state)`` is negative."""
        return _walk_loop(d, walk, state, t_of, test_item, self._opaque_box[2],
                          self._opaque_box[3], self.cell_start, max_steps)


def _cell_range(cell_start: UInt32, cell: Array3i, res: Array3i,
                active: Bool) -> tuple[UInt32, UInt32]:
    """Positions [first, end) in the item list of each lane's cell.

    Two gathers from one array, mostly within one cache line.
    """
    index = UInt32((cell.z * res[1] + cell.y) * res[0] + cell.x)
    return (dr.gather(UInt32, cell_start, index, active),
            dr.gather(UInt32, cell_start, index + 1, active))


def _spread_bits(v: UInt32) -> UInt32:
    """The low 10 bits of ``v`` moved to every third bit (bit i to bit 3 i): one axis of
    a 3D Morton code."""
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


def _dda_step(cell: Array3i, t_next: Array3f, step: Array3i, t_delta: Array3f,
              res_i: Array3i) -> tuple[Array3i, Array3f, Bool]:
    """One DDA step across the nearest cell boundary; also whether the new cell is in the grid."""
    on_x = (t_next.x <= t_next.y) & (t_next.x <= t_next.z)
    on_y = ~on_x & (t_next.y <= t_next.z)
    axis = Array3b(on_x, on_y, ~on_x & ~on_y)
    cell = dr.select(axis, cell + step, cell)
    t_next = dr.select(axis, t_next + t_delta, t_next)
    return cell, t_next, dr.all((cell >= 0) & (cell < res_i))


@dataclass
class WalkState:
    """Where a ray's grid walk stands between loop iterations (see :func:`_walk_start`):
    whether it goes on, where it leaves the grid, the cell after the current one and its
    next boundary per axis, the current cell's remaining items and exit distance, and
    the following cell's items (fetched ahead). A dataclass, which Dr.Jit traverses
    as a PyTree (it does not traverse a NamedTuple's fields)."""

    active: Bool
    t_leave: Float
    cell: Array3i
    t_next: Array3f
    item: UInt32
    end: UInt32
    t_exit: Float
    ahead_inside: Bool
    next_item: UInt32
    next_end: UInt32


def _ray_steps(d, cell_size):
    """Per-axis DDA constants of the rays: 1 / d, the cell step and the distance per cell."""
    inv_d = dr.rcp(d)
    step = dr.select(d >= 0, Array3i(1), Array3i(-1))
    return inv_d, step, dr.abs(cell_size * inv_d)


def _entry_cell(o, d, inv_d, g_lo, g_hi, cell_size, res_i):
    """Steps 1 - 2a of the walk: where the ray enters and leaves the grid box, whether it
    meets the box, and its first cell."""
    # Step 1: clip the ray to the grid box.
    t_enter, t_leave = slab_span(g_lo, g_hi, o, inv_d)
    # Step 2a: the cell of the entry point.
    p = dr.fma(d, t_enter, o)
    cell = dr.clip(Array3i(dr.floor((p - g_lo) / cell_size)), 0, res_i - 1)
    return t_leave, t_enter <= t_leave, cell


def _walk_start(o, d, active, g_lo, g_hi, cell_size, res, cell_start) -> WalkState:
    """Steps 1 - 3 of the walk: the ray's first cell and what the loop needs."""
    inv_d, step, t_delta = _ray_steps(d, cell_size)
    res_i = Array3i(*res)
    t_leave, meets, cell = _entry_cell(o, d, inv_d, g_lo, g_hi, cell_size, res_i)
    active &= meets
    # Step 2b: the distances to the next cell boundary per axis.
    boundary = g_lo + (Array3f(cell) + dr.select(d >= 0, 1.0, 0.0)) * cell_size
    t_next = (boundary - o) * inv_d
    # Axes the ray does not move along never reach their next boundary.
    t_next = dr.select(d == 0, dr.inf, t_next)
    # Step 3: the current cell's item range and exit distance; then the DDA
    # moves one cell ahead and fetches that cell's range. From here on the DDA
    # state (cell, t_next) describes the cell after the current one: its range
    # is gathered while the current cell's items are tested, which hides the
    # gather's memory latency (measured 1.17x faster at 100 000 instances
    # than gathering after the step).
    item, end = _cell_range(cell_start, cell, res, active)
    t_exit = dr.min(t_next)
    cell, t_next, ahead_inside = _dda_step(cell, t_next, step, t_delta, res_i)
    next_item, next_end = _cell_range(cell_start, cell, res, active & ahead_inside)
    return WalkState(active, t_leave, cell, t_next, item, end, t_exit, ahead_inside,
                     next_item, next_end)


@dr.syntax
def _walk_loop(d, walk, state, t_of, test_item, cell_size, res, cell_start, max_steps):
    """Step 4 of the walk, for at most ``max_steps`` loop iterations (None: to the end)."""
    _, step, t_delta = _ray_steps(d, cell_size)
    res_i = Array3i(*res)
    active, t_leave, cell, t_next, item, end, t_exit, ahead_inside, next_item, next_end = (
        getattr(walk, f.name) for f in fields(walk))
    # Without a limit, 2^32 - 1 iterations: more than any walk takes.
    steps_left = UInt32(0xFFFFFFFF if max_steps is None else max_steps)
    # Step 4: one flat loop; each iteration tests one item of the current cell
    # and, once the cell is exhausted, moves on to the next one. (Flattening the
    # cell and item loops keeps SIMD lanes busy: measured 1.3x faster than
    # nested loops at 1 000 instances.) The walk stops once the closest hit
    # lies before the current cell's exit: nothing farther can be closer; and
    # at once where t_of is negative (an any-hit query that found a hit).
    # The loop's state is what it changes; what it only reads stays out of it (and out of the
    # branches' state), so that the body is traced once.
    while dr.hint(active & (t_of(state) >= 0) & (steps_left > 0),
                  exclude=[t_leave, step, t_delta, res_i, cell_start, res, t_of, test_item]):
        steps_left -= 1
        if dr.hint(item < end, exclude=[test_item]):
            state = test_item(item, state)
            item += 1
        if dr.hint(item >= end, exclude=[t_leave, step, t_delta, res_i, cell_start, res, t_of]):
            # The cell is exhausted: stop, or make the fetched cell current and fetch the next.
            active = (ahead_inside & (t_of(state) > t_exit * (1.0 - EXIT_SLACK))
                      & (t_exit <= t_leave))
            item, end = next_item, next_end
            t_exit = dr.min(t_next)
            cell, t_next, ahead_inside = _dda_step(cell, t_next, step, t_delta, res_i)
            next_item, next_end = _cell_range(cell_start, cell, res, active & ahead_inside)
    return WalkState(active, t_leave, cell, t_next, item, end, t_exit, ahead_inside,
                     next_item, next_end), state
