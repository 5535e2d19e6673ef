"""The uniform grid: its cell lists, its traversal against brute force on hard cases, and the
walk in passes for large batches against the walk in one loop."""

from __future__ import annotations

import numpy as np
import pytest

import instancing.scene.scene
from instancing.accel.grid import build_grid, update_grid
from instancing.core.backend import Array3f, Float, Int32, dr
from instancing.core.kernel_recording import jit_state
from instancing.scene.intersection import intersect_preliminary_in_passes
from instancing.scene.scene import PASSES_MIN_RAYS

from scene_helpers import float32_exact, load, random_affine, random_rays


def test_cells_list_every_overlapping_box_and_only_nearby_ones():
    rng = np.random.default_rng(5)
    lo = rng.uniform(-10, 10, (300, 3))
    hi = lo + rng.uniform(0.01, 3.0, (300, 3))
    grid = build_grid(lo, hi)
    res = grid.resolution
    assert grid.cell_start.shape == (np.prod(res) + 1,)
    assert grid.cell_start[0] == 0 and grid.cell_start[-1] == len(grid.cell_items)
    assert np.all(np.diff(grid.cell_start.astype(np.int64)) >= 0)
    cell = (grid.hi - grid.lo) / res

    def items_of(index):
        flat = (index[2] * res[1] + index[1]) * res[0] + index[0]
        return grid.cell_items[grid.cell_start[flat]:grid.cell_start[flat + 1]]

    # Every box is listed in the cells that hold its corners...
    for i in range(len(lo)):
        for corner in (lo[i], hi[i]):
            index = np.clip(np.floor((corner - grid.lo) / cell), 0, res - 1).astype(int)
            assert i in items_of(index)
    # ...and no cell lists a box that stays more than a rounding slack away from it.
    counts = grid.cell_count
    flat = np.repeat(np.arange(np.prod(res)), counts)
    index = np.stack([flat % res[0], (flat // res[0]) % res[1], flat // (res[0] * res[1])], 1)
    cell_lo = grid.lo + index * cell - 1e-3 * cell
    cell_hi = cell_lo + 1.002 * cell
    items = grid.cell_items
    assert np.all((lo[items] <= cell_hi) & (hi[items] >= cell_lo))


def _cell_sets(grid):
    """Per cell, the set of listed items."""
    return [set(grid.cell_items[a:b].tolist()) for a, b in zip(grid.cell_start[:-1], grid.cell_start[1:])]


def test_update_moves_references_into_exactly_the_cells_of_the_new_boxes():
    rng = np.random.default_rng(8)
    lo = rng.uniform(-10, 10, (400, 3))
    hi = lo + rng.uniform(0.01, 2.0, (400, 3))
    grid = build_grid(lo, hi)
    moved = rng.choice(400, 9, replace=False)
    new_lo, new_hi = lo.copy(), hi.copy()
    shift = rng.uniform(-1.5, 1.5, (9, 3))
    new_lo[moved] = np.clip(lo[moved] + shift, grid.lo + 0.01, None)
    new_hi[moved] = np.clip(new_lo[moved] + (hi - lo)[moved], None, grid.hi - 0.01)
    updated = update_grid(grid, moved, new_lo[moved], new_hi[moved])
    assert updated is not None
    assert np.array_equal(updated.resolution, grid.resolution) and np.array_equal(updated.lo, grid.lo)
    assert updated.cell_start[-1] == len(updated.cell_items)
    # Independent reference: per cell, the boxes overlapping it (the build's rule, widened by
    # its rounding slack), from the final boxes, in the same grid.
    res, cell = grid.resolution, (grid.hi - grid.lo) / grid.resolution
    flat = np.arange(np.prod(res))
    index = np.stack([flat % res[0], (flat // res[0]) % res[1], flat // (res[0] * res[1])], 1)
    cell_lo, cell_hi = grid.lo + index * cell, grid.lo + (index + 1) * cell
    slack = 1e-4 * cell
    overlap = ((new_lo[None] - slack < cell_hi[:, None]) & (new_hi[None] + slack >= cell_lo[:, None])).all(-1)
    expected = [set(np.flatnonzero(row).tolist()) for row in overlap]
    assert _cell_sets(updated) == expected
    # The same as rebuilding the moved boxes' references from scratch in that grid.
    assert sum(map(len, expected)) == len(updated.cell_items)


def test_update_declines_when_a_box_leaves_the_grid():
    rng = np.random.default_rng(9)
    lo = rng.uniform(-10, 10, (100, 3))
    hi = lo + 1.0
    grid = build_grid(lo, hi)
    assert update_grid(grid, np.array([3]), grid.hi[None] - 0.5, grid.hi[None] + 0.5) is None


def _two_corner_scene(rng):
    """Spheres packed into two opposite corners of a large box: most cells are empty."""
    matrices = []
    for corner in (np.array([-50.0, -50.0, -50.0]), np.array([50.0, 50.0, 50.0])):
        for _ in range(150):
            m = np.eye(4)
            m[:3, :3] *= rng.uniform(0.2, 1.0)
            m[:3, 3] = corner + rng.uniform(-5, 5, 3)
            matrices.append(m)
    return load(["sphere"] * len(matrices), matrices, accel="brute")


def _hard_rays(rng, lo, hi, n):
    """Rays that start outside the grid, run along the axes, or cross the empty middle."""
    centre, size = (lo + hi) / 2, hi - lo
    # From outside the box towards a random point inside it.
    target = rng.uniform(lo, hi, (n, 3))
    start = centre + rng.normal(size=(n, 3)) / np.sqrt(3) * 2 * size
    outside_o, outside_d = start, target - start
    # Axis-parallel rays (two direction components exactly zero), both senses.
    axis_o = rng.uniform(lo - 0.1 * size, hi + 0.1 * size, (n, 3))
    axis_d = np.zeros((n, 3))
    axis_d[np.arange(n), rng.integers(0, 3, n)] = rng.choice([-1.0, 1.0], n)
    # From one cluster towards the other, across the empty cells.
    diagonal_o = rng.uniform(lo, lo + 0.1 * size, (n, 3))
    diagonal_d = rng.uniform(hi - 0.1 * size, hi, (n, 3)) - diagonal_o
    o = np.concatenate([outside_o, axis_o, diagonal_o])
    d = np.concatenate([outside_d, axis_d, diagonal_d])
    return float32_exact(o), float32_exact(d)


def test_grid_over_mostly_empty_space_returns_exactly_the_brute_force_hits():
    rng = np.random.default_rng(17)
    scene = _two_corner_scene(rng)
    o, d = _hard_rays(rng, *scene.bounds, 10_000)
    brute = scene.intersect(o, d)
    assert np.isfinite(brute.t).sum() > 3000  # the sample really hits things
    scene.set_accel("grid")
    assert scene.accel == "grid"
    hits = scene.intersect(o, d)
    for field in ("t", "instance", "prim"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(brute, field), err_msg=field)


@pytest.mark.parametrize("t_max", [0.5, 5.0, 60.0])
def test_grid_shadow_rays_with_t_max_equal_brute_force(t_max):
    rng = np.random.default_rng(23)
    scene = _two_corner_scene(rng)
    o_np, d_np = _hard_rays(rng, *scene.bounds, 5_000)
    d_np /= np.linalg.norm(d_np, axis=1, keepdims=True)
    o = Array3f(*[np.float32(o_np[:, k]) for k in range(3)])
    d = Array3f(*[np.float32(d_np[:, k]) for k in range(3)])
    limit = Float(t_max) + dr.zeros(Float, len(o_np))
    brute = scene.intersect_preliminary(o, d, True, limit)
    scene.set_accel("grid")
    grid = scene.intersect_preliminary(o, d, True, limit)
    np.testing.assert_array_equal(np.asarray(grid.t), np.asarray(brute.t))
    np.testing.assert_array_equal(np.asarray(grid.instance), np.asarray(brute.instance))


def _mixed_grid_scene(rng, n=150):
    kinds = [("sphere", "cube", "cylinder", "rectangle", "mesh")[i % 5] for i in range(n)]
    matrices = [random_affine(rng, spread=12.0) for _ in range(n)]
    return load(kinds, matrices, accel="grid")


@pytest.mark.parametrize("pass_steps, sort_rays", [(1, False), (3, False), (16, False), (3, True),
                                                    (16, True)])
def test_walking_in_passes_gives_the_hits_of_one_loop(pass_steps, sort_rays):
    rng = np.random.default_rng(21)
    scene = _mixed_grid_scene(rng)
    o, d = random_rays(rng, *scene.bounds, 20_000)
    o, d = Array3f(o.T), Array3f(d.T)
    one = scene.intersect_preliminary(o, d)
    passes = intersect_preliminary_in_passes(scene.instances, scene.grid, o, d, pass_steps,
                                             sort_rays)
    assert (np.asarray(one.instance) != 0xFFFFFFFF).mean() > 0.2  # 28 %: many rays hit
    for field in ("t", "instance", "position"):
        np.testing.assert_array_equal(np.asarray(getattr(passes, field)), np.asarray(getattr(one, field)))


@pytest.mark.parametrize("pass_steps", [0, -2, 1.5])
def test_passes_of_no_steps_are_rejected(pass_steps):
    scene = _mixed_grid_scene(np.random.default_rng(23), n=20)
    o = Array3f(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="pass_steps"):
        intersect_preliminary_in_passes(scene.instances, scene.grid, o, o + 1.0, pass_steps)


def test_scene_intersect_walks_large_batches_in_passes_but_not_when_recorded(monkeypatch):
    """Large batches walk in passes (sorted in large scenes) with the hits of one loop."""
    rng = np.random.default_rng(22)
    scene = _mixed_grid_scene(rng)
    o_np, d_np = random_rays(rng, *scene.bounds, PASSES_MIN_RAYS)
    o, d = Array3f(o_np.T), Array3f(d_np.T)
    calls = []
    monkeypatch.setattr(instancing.scene.scene, "intersect_preliminary_in_passes",
                        lambda *args, **kwargs: calls.append(kwargs["sort_rays"])
                        or intersect_preliminary_in_passes(*args, **kwargs))
    want = scene.intersect_surface(o, d)
    got = scene.intersect(o_np, d_np)
    # A small scene's rays are walked as they come; from SORT_MIN_WALK_BYTES, sorted.
    monkeypatch.setattr(instancing.scene.scene, "SORT_MIN_WALK_BYTES", scene._walk_bytes())
    sorted_got = scene.intersect(o_np, d_np)
    assert calls == [False, True]
    for field in ("t", "p", "n", "instance", "prim"):
        np.testing.assert_array_equal(getattr(sorted_got, field), getattr(got, field))
    np.testing.assert_array_equal(got.t, np.asarray(want.t))
    np.testing.assert_array_equal(got.instance, np.asarray(dr.select(want.valid, Int32(want.instance), -1)))
    np.testing.assert_array_equal(got.n, np.asarray(want.n).T)
    # In a dr.freeze recording (which cannot replay data-dependent passes) and in a
    # smaller batch, one traced loop.
    frozen = dr.freeze(lambda o, d: scene.intersect(o, d).t, state_fn=lambda *args: jit_state(scene))
    for _ in range(3):
        np.testing.assert_array_equal(np.asarray(frozen(o, d)), np.asarray(want.t))
    scene.intersect(o_np[:1000], d_np[:1000])
    assert calls == [False, True]
