"""Sorting large ray batches by where they enter the grid: the counting sort against
NumPy's sort, the gathers and scatters that reorder rays and results, and the entry
keys against a float64 reference."""

from __future__ import annotations

import numpy as np

from instancing.accel.grid import ENTRY_KEY_BITS
from instancing.core.backend import Array3f, Float, UInt32
from instancing.scene.intersection import intersect_preliminary_in_passes
from instancing.accel.ray_order import counting_sort_order, gather_rays, scatter_back

from scene_helpers import load, random_affine


def test_counting_sort_orders_every_lane_once_by_ascending_key():
    rng = np.random.default_rng(41)
    keys = rng.integers(0, 300, 50_000).astype(np.uint32)
    keys[:1000] = 299  # a crowded bucket
    order = np.asarray(counting_sort_order(UInt32(keys), 300))
    np.testing.assert_array_equal(np.sort(order), np.arange(len(keys)))
    # Same key sequence as a stable sort (lanes within a bucket may come in any order).
    np.testing.assert_array_equal(keys[order], np.sort(keys))


def test_rays_are_gathered_in_order_and_results_scattered_back():
    rng = np.random.default_rng(42)
    o_np = rng.normal(size=(3, 10_001)).astype(np.float32)
    d_np = rng.normal(size=(3, 10_001)).astype(np.float32)
    order_np = rng.permutation(10_001).astype(np.uint32)
    order = UInt32(order_np)
    o, d = gather_rays(Array3f(o_np), Array3f(d_np), order)
    np.testing.assert_array_equal(np.asarray(o), o_np[:, order_np])
    np.testing.assert_array_equal(np.asarray(d), d_np[:, order_np])
    # A result computed per sorted ray lands on the ray it belongs to.
    t, lane = scatter_back((Float(o_np[0, order_np] + 1.0), UInt32(order_np)), order)
    np.testing.assert_array_equal(np.asarray(t), o_np[0] + 1.0)
    np.testing.assert_array_equal(np.asarray(lane), np.arange(10_001))


def _morton(cell: np.ndarray) -> np.ndarray:
    key = np.zeros(len(cell), np.int64)
    for bit in range(10):
        for axis in range(3):
            key |= ((cell[:, axis] >> bit) & 1) << (3 * bit + axis)
    return key


def test_entry_keys_are_the_morton_codes_of_the_entry_cells():
    rng = np.random.default_rng(43)
    scene = load(["sphere"] * 1500, [random_affine(rng, spread=10.0) for _ in range(1500)],
                 accel="grid")
    grid = scene.grid.arrays()
    res = grid.resolution
    size = (grid.hi - grid.lo) / res
    assert res.max() > 1 << ENTRY_KEY_BITS  # some cells share a coarse cell
    # Rays from cell centres inside the grid (they enter where they start), and axis-aligned
    # rays from outside the grid towards cell centres (they enter in the first or last
    # cell along their axis, elsewhere at their origin's cell).
    cell = rng.integers(0, res, (3000, 3))
    o = grid.lo + (cell + 0.5) * size
    d = rng.normal(size=(3000, 3))
    axis = rng.integers(0, 3, 1000)
    outside = np.arange(2000, 3000)
    sign = rng.choice([-1.0, 1.0], 1000)
    d[outside] = 0.0
    d[outside, axis] = sign
    o[outside, axis] = np.where(sign > 0, grid.lo[axis] - 5.0, grid.hi[axis] + 5.0)
    cell[outside, axis] = np.where(sign > 0, 0, res[axis] - 1)
    keys = np.asarray(scene.grid.entry_keys(Array3f(o.T.astype(np.float32)),
                                                        Array3f(d.T.astype(np.float32))))
    coarse = cell * (1 << ENTRY_KEY_BITS) // res
    np.testing.assert_array_equal(keys, _morton(coarse))
    assert len(np.unique(keys)) > 100


def test_sorted_walk_handles_rays_that_miss_or_are_degenerate():
    """Rays outside the grid, along an axis, with zero or non-finite components get keys
    in range and the hits of the one-loop walk."""
    rng = np.random.default_rng(44)
    scene = load(["sphere", "cube"] * 100, [random_affine(rng, spread=8.0) for _ in range(200)],
                 accel="grid")
    lo, hi = scene.bounds
    o = rng.uniform(lo - 5.0, hi + 5.0, (4000, 3))
    d = rng.normal(size=(4000, 3))
    d[:500, 1:] = 0.0                   # along x
    d[500:600] = 0.0                    # no direction at all
    o[600:700, 0] = np.nan              # undefined origin
    d[700:800, 2] = np.inf              # infinite direction component
    o[800:900] = hi + 100.0             # far outside, pointing anywhere
    o, d = Array3f(o.T.astype(np.float32)), Array3f(d.T.astype(np.float32))
    keys = np.asarray(scene.grid.entry_keys(o, d))
    assert keys.max() < 1 << (3 * ENTRY_KEY_BITS)
    one = scene.intersect_preliminary(o, d)
    assert (np.asarray(one.instance) != 0xFFFFFFFF).sum() > 500
    for pass_steps in (2, 16):
        ordered = intersect_preliminary_in_passes(scene.instances, scene.grid, o, d, pass_steps,
                                                  sort_rays=True)
        for field in ("t", "instance", "position"):
            np.testing.assert_array_equal(np.asarray(getattr(ordered, field)),
                                          np.asarray(getattr(one, field)))
