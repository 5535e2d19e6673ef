"""The BVH build (instancing/accel/bvh.py): structure of SAH trees, mesh hits through them,
and refitting the top-level tree after instances move.

The structural check walks a built tree in NumPy: every item lies in exactly
one leaf, every child box contains the boxes of all items below it, leaves
hold at most ``leaf_size`` items and inner nodes lie less than STACK_SIZE deep.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.validation import reference
from instancing.accel.bvh import (FRONTIER, STACK_SIZE, BVHArrays, BVHKernel, build_bvh, build_forest,
                                  forest_trees, refit_bvh, select_trees, surface_cost, tree_costs)
from instancing.accel import sah
from instancing.accel.sah import SAH_BINS, SAH_MAX_DEPTH, box_area
from instancing.core.box import outward32
from instancing.validation.stress import MESH_FILE as STRESS_MESH
from instancing.io.mesh_file import read_mesh
from instancing.core.transform import Transform, affine_inverse, matrices_to_lanes
from scene_helpers import float32_exact

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


def check_tree(bvh: BVHArrays, lo: np.ndarray, hi: np.ndarray, leaf_size: int) -> int:
    """Assert the structure of ``bvh`` over the boxes ``lo``, ``hi``; return its depth
    (the levels of inner nodes on the longest path)."""
    slo, shi = lo[bvh.order], hi[bvh.order]
    visited, depths = [], [0]

    def walk(ref: int, depth: int) -> np.ndarray:
        # Positions (in the item order) of the items below ``ref``, checked on the way.
        index, count = ref >> 4, ref & 15
        if count:
            assert count <= leaf_size
            return np.arange(index, index + count)
        visited.append(index)
        depths.append(depth + 1)
        below = [walk(int(r), depth + 1) for r in bvh.child_ref[index]]
        for k, positions in enumerate(below):
            assert np.all(bvh.child_lo[index, k] <= slo[positions])
            assert np.all(bvh.child_hi[index, k] >= shi[positions])
        return np.concatenate(below)

    positions = walk(bvh.root_ref, 0)
    assert np.array_equal(np.sort(bvh.order), np.arange(len(lo)))
    assert np.array_equal(np.sort(positions), np.arange(len(lo)))  # each item in one leaf
    assert sorted(visited) == list(range(bvh.node_count))  # each node reached once
    assert max(depths) < STACK_SIZE
    return max(depths)


def random_boxes(rng, n, clustered=False):
    centre = rng.uniform(-10.0, 10.0, (n, 3))
    if clustered:
        centre = rng.uniform(-100.0, 100.0, (3, 3))[rng.integers(0, 3, n)] + rng.normal(0, 0.5, (n, 3))
    half = rng.uniform(0.0, 1.0, (n, 3)) ** 3
    return centre - half, centre + half


@pytest.mark.parametrize("leaf_size", [1, 4, 15])
def test_trees_of_1_to_40_random_boxes_are_valid(leaf_size):
    rng = np.random.default_rng(leaf_size)
    for n in range(1, 41):
        for clustered in (False, True):
            lo, hi = random_boxes(rng, n, clustered)
            check_tree(build_bvh(lo, hi, leaf_size), lo, hi, leaf_size)


@pytest.mark.parametrize("clustered", [False, True])
def test_tree_of_many_boxes_is_valid(clustered):
    rng = np.random.default_rng(5 + clustered)
    lo, hi = random_boxes(rng, 20_000, clustered)
    depth = check_tree(build_bvh(lo, hi, 4), lo, hi, 4)
    assert depth < SAH_MAX_DEPTH


def test_split_never_joins_distant_clusters():
    # Two tight clusters of 300 and 700 boxes, 1 000 units apart: the root's children
    # hold one cluster each (a split at the median index would put 200 of the larger
    # cluster's boxes with the smaller one, under a box 1 000 units long).
    rng = np.random.default_rng(8)
    centre = np.concatenate([rng.normal(0.0, 1.0, (300, 3)), rng.normal(1000.0, 1.0, (700, 3))])
    bvh = build_bvh(centre - 0.1, centre + 0.1, 2)
    assert bvh.root_ref & 15 == 0
    extent = bvh.child_hi[bvh.root_ref >> 4] - bvh.child_lo[bvh.root_ref >> 4]
    assert extent.max() < 20.0


def test_identical_and_flat_boxes_split_by_index():
    rng = np.random.default_rng(2)
    # Identical boxes (all centroids equal), points, and boxes on a plane (one flat axis).
    same = np.tile([[-1.0, 0.0, 2.0]], (1000, 1)), np.tile([[1.0, 0.5, 3.0]], (1000, 1))
    points = (np.zeros((37, 3)),) * 2
    flat = rng.uniform(-1, 1, (500, 3)) * [1, 1, 0]
    for lo, hi in (same, points, (flat, flat + [0.01, 0.01, 0])):
        for leaf_size in (1, 4):
            check_tree(build_bvh(lo, hi, leaf_size), lo, hi, leaf_size)


def test_sah_depth_stays_below_the_stack_on_a_geometric_sequence():
    # Centres at 2^-k: every binned SAH split peels off one item, so the depth
    # would grow with N were it not for the median splits from SAH_MAX_DEPTH on.
    x = 2.0 ** -np.arange(300.0)
    lo = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    depth = check_tree(build_bvh(lo, lo + 1e-3 * x[:, None], 1), lo, lo + 1e-3 * x[:, None], 1)
    assert SAH_MAX_DEPTH <= depth < STACK_SIZE


@pytest.mark.parametrize("scale", [1e19, 1e30, 1.5e38])
def test_sah_over_boxes_whose_float32_areas_overflow_is_valid_without_warnings(scale):
    """Mesh boxes spanning 1e19 .. 3e38 (float32 coordinates, finite) give the SAH costs
    float32 cannot hold: those nodes are split at their median index, without a NumPy
    warning; flat boxes (0 * inf) included."""
    import warnings
    rng = np.random.default_rng(11)
    lo, hi = random_boxes(rng, 500)
    lo, hi = lo / 10 * scale, hi / 10 * scale
    flat_lo, flat_hi = lo * [1, 1, 0], hi * [1, 1, 0]
    for boxes in ((lo, hi), (flat_lo, flat_hi)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_tree(build_bvh(*boxes, 4), *boxes, 4)


def brute_force_sah_split(lo, hi):
    """The binned SAH's cheapest split of one node, in float64 by trying every plane: the
    items left of it (a boolean mask) and its cost, or None when no plane has items on
    both sides."""
    centre = 0.5 * (lo + hi)
    c_lo, c_hi = centre.min(axis=0), centre.max(axis=0)
    best = None
    for plane in range(SAH_BINS - 1):  # planes first, then axes: the build's tie order
        for axis in range(3):
            extent = c_hi[axis] - c_lo[axis]
            if extent <= 0:
                continue
            b = np.minimum(((centre[:, axis] - c_lo[axis]) / extent * SAH_BINS).astype(int), SAH_BINS - 1)
            left = b <= plane
            if left.all() or not left.any():
                continue
            cost = sum(box_area(lo[side].min(axis=0), hi[side].max(axis=0)) * side.sum()
                       for side in (left, ~left))
            if best is None or cost < best[1]:
                best = (left, cost)
    return best


@pytest.mark.parametrize("seed", range(4))
def test_sah_root_split_is_the_cheapest_binned_plane(seed):
    """The root's children hold the items of the plane a float64 brute force over all
    3 (SAH_BINS - 1) planes finds cheapest."""
    rng = np.random.default_rng(seed)
    lo, hi = random_boxes(rng, 300, clustered=seed % 2 == 1)
    left, _ = brute_force_sah_split(lo, hi)
    bvh = build_bvh(lo, hi, 4)
    root = bvh.root_ref >> 4
    assert bvh.root_ref & 15 == 0
    for k, side in enumerate((left, ~left)):
        box = outward32(lo[side].min(axis=0), hi[side].max(axis=0))
        np.testing.assert_array_equal(bvh.child_lo[root, k], box[0])
        np.testing.assert_array_equal(bvh.child_hi[root, k], box[1])


def test_sah_build_is_deterministic():
    # The bins are filled by atomic minima, maxima and sums, whose result does not depend
    # on the order in which threads reach them.
    rng = np.random.default_rng(3)
    lo, hi = random_boxes(rng, 50_000)
    first, second = build_bvh(lo, hi, 4), build_bvh(lo, hi, 4)
    for name in ("child_lo", "child_hi", "child_ref", "order"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))


def test_sah_build_in_chunks_of_nodes_equals_the_build_in_one(monkeypatch):
    # Levels of more than SAH_CHUNK_NODES nodes are binned a chunk at a time (meshes of
    # about 100 000 triangles and more); here chunks of 7 nodes on 3 000 boxes.
    rng = np.random.default_rng(6)
    lo, hi = random_boxes(rng, 3_000, clustered=True)
    whole = build_bvh(lo, hi, 4)
    monkeypatch.setattr(sah, "SAH_CHUNK_NODES", 7)
    chunked = build_bvh(lo, hi, 4)
    for name in ("child_lo", "child_hi", "child_ref", "order"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))


@pytest.mark.parametrize("leaf_size", [1, 4])
def test_small_nodes_split_without_bins_as_the_binned_sweep_does(monkeypatch, leaf_size):
    # Nodes of at most SAH_SMALL_NODE items are scored from their items sorted by bin; with
    # every node binned instead (SAH_SMALL_NODE 0) the trees must be the same, bit for bit:
    # scattered and clustered boxes, centres on a lattice (many items per bin, equal
    # costs), a flat layer, coincident boxes, and a forest of small trees.
    rng = np.random.default_rng(12)
    lattice = np.round(rng.uniform(-2, 2, (2_000, 3)), 0) + rng.uniform(0, 1e-3, (2_000, 3))
    flat_lo, flat_hi = random_boxes(rng, 1_000)
    flat_lo[:, 2] = flat_hi[:, 2] = 0.0
    cases = [(random_boxes(rng, 5_000), [5_000]), (random_boxes(rng, 3_000, clustered=True), [3_000]),
             ((lattice, lattice + 0.1), [2_000]), ((flat_lo, flat_hi), [1_000]),
             ((np.zeros((30, 3)), np.ones((30, 3))), [30]),
             (random_boxes(rng, 600), [1, 2, 3, 5, 8, 9, 17, 555])]
    for (lo, hi), sizes in cases:
        direct = build_forest(lo, hi, sizes, leaf_size)
        with monkeypatch.context() as patch:
            patch.setattr(sah, "SAH_SMALL_NODE", 0)
            binned = build_forest(lo, hi, sizes, leaf_size)
        assert direct[1] == binned[1]
        for name in ("child_lo", "child_hi", "child_ref", "order"):
            np.testing.assert_array_equal(getattr(direct[0], name), getattr(binned[0], name))


def test_forest_builds_one_tree_per_run_of_boxes():
    rng = np.random.default_rng(4)
    sizes = [1, 37, 2, 500, 4, 1_000]
    lo, hi = random_boxes(rng, sum(sizes))
    arrays, roots = build_forest(lo, hi, sizes, 4)
    first = np.cumsum(sizes) - sizes
    node_ranges = []
    for root, start, size in zip(roots, first, sizes):
        run = slice(start, start + size)
        # Each tree holds exactly its run's boxes, at its run's positions, and equals the
        # tree built from the run alone.
        assert np.array_equal(np.sort(arrays.order[run]), np.arange(start, start + size))
        alone = build_bvh(lo[run], hi[run], 4)
        assert np.array_equal(arrays.order[run] - start, alone.order)
        nodes = _subtree_nodes(arrays, root)
        assert len(nodes) == alone.node_count
        if nodes:
            node_ranges.append((min(nodes), max(nodes)))
            assert max(nodes) - min(nodes) + 1 == len(nodes)  # each tree's nodes contiguous
            np.testing.assert_array_equal(arrays.child_lo[min(nodes):max(nodes) + 1], alone.child_lo)
    assert node_ranges == sorted(node_ranges)
    assert sum(b - a + 1 for a, b in node_ranges) == arrays.node_count


def test_selected_trees_of_a_forest_are_the_forest_of_their_runs():
    rng = np.random.default_rng(6)
    sizes = [1, 37, 2, 500, 4, 1_000, 3]
    lo, hi = random_boxes(rng, sum(sizes))
    arrays, roots = build_forest(lo, hi, sizes, 4)
    first = np.cumsum(sizes) - sizes
    # Node counts per tree from the forest's layout, against walking each tree.
    starts, counts = forest_trees(arrays, roots, sizes)
    assert counts.tolist() == [len(_subtree_nodes(arrays, root)) for root in roots]
    assert all(start == root >> 4 for start, root, count in zip(starts, roots, counts) if count)
    for keep in ([1, 0, 1, 0, 1, 1, 0], [0, 0, 0, 1, 0, 0, 1], [1] * 7):
        picked = np.flatnonzero(keep)
        kept, kept_roots = select_trees(arrays, roots, sizes, keep)
        runs = np.concatenate([np.arange(first[k], first[k] + sizes[k]) for k in picked])
        alone, alone_roots = build_forest(lo[runs], hi[runs], [sizes[k] for k in picked], 4)
        assert kept_roots == alone_roots and kept.root_ref == alone_roots[0]
        np.testing.assert_array_equal(kept.child_ref, alone.child_ref)
        np.testing.assert_array_equal(kept.child_lo, alone.child_lo)
        np.testing.assert_array_equal(kept.child_hi, alone.child_hi)
        np.testing.assert_array_equal(kept.order, runs[alone.order])  # the built item indices
    # Each tree's surface cost: surface_cost of the tree built alone, plus its root's box.
    area = box_area(np.stack([lo[f:f + n].min(axis=0) for f, n in zip(first, sizes)]),
                    np.stack([hi[f:f + n].max(axis=0) for f, n in zip(first, sizes)]))
    for k, cost in enumerate(tree_costs(arrays, roots, sizes, area)):
        alone = build_bvh(lo[first[k]:first[k] + sizes[k]], hi[first[k]:first[k] + sizes[k]], 4)
        packed = np.stack([alone.child_lo[:, 0], alone.child_hi[:, 0], alone.child_lo[:, 1],
                           alone.child_hi[:, 1]], axis=1)
        root_items = alone.root_ref & 15
        expected = surface_cost(packed, alone.child_ref) + area[k] * (root_items if root_items else 1)
        assert cost == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("clustered", [False, True])
def test_nodes_are_stored_in_depth_first_order(clustered):
    # Each node is followed by its left subtree's nodes, then its right one's: every
    # subtree occupies one contiguous run of nodes starting at its root.
    rng = np.random.default_rng(9)
    lo, hi = random_boxes(rng, 3_000, clustered)
    arrays = build_bvh(lo, hi, 2)
    assert arrays.root_ref & 15 == 0 and arrays.node_count > 100
    for node in range(arrays.node_count):
        below = _subtree_nodes(arrays, node << 4)
        assert below == list(range(node, node + len(below)))


def _subtree_nodes(arrays: BVHArrays, ref: int) -> list[int]:
    if ref & 15:
        return []
    node = ref >> 4
    return [node] + [n for child in arrays.child_ref[node] for n in _subtree_nodes(arrays, int(child))]


def test_forest_sizes_are_checked():
    with pytest.raises(ValueError, match="sizes must sum"):
        build_forest(np.zeros((3, 3)), np.ones((3, 3)), [1, 1])
    with pytest.raises(ValueError, match="at least one box"):
        build_forest(np.zeros((3, 3)), np.ones((3, 3)), [3, 0])


def triangle_soup(path: Path, rng, needles: bool = False) -> Path:
    """An OBJ of 300 random triangles of very different sizes, many overlapping (with
    ``needles``, slender ones 0.5 - 2 long and 0.002 - 0.05 wide, split into references)."""
    centre = rng.uniform(-1.0, 1.0, (300, 1, 3))
    if needles:
        along, across = rng.normal(size=(2, 300, 1, 3))
        along /= np.linalg.norm(along, axis=2, keepdims=True)
        across /= np.linalg.norm(across, axis=2, keepdims=True)
        shape = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0]])[None, :, :, None]
        v = (centre + shape[..., 0, :] * rng.uniform(0.5, 2.0, (300, 1, 1)) * along
             + shape[..., 1, :] * rng.uniform(0.002, 0.05, (300, 1, 1)) * across).reshape(-1, 3)
    else:
        v = (centre + rng.normal(size=(300, 3, 3)) * rng.uniform(0.01, 0.5, (300, 1, 1))).reshape(-1, 3)
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in float32_exact(v).tolist()]
    lines += [f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}" for i in range(300)]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("name", ["torus.obj", "tree.ply", "icosphere.obj", "soup", "needles"])
def test_hits_through_sah_mesh_bvh_equal_brute_force(name, tmp_path):
    rng = np.random.default_rng(len(name))
    path = (triangle_soup(tmp_path / "soup.obj", rng, name == "needles") if name in ("soup", "needles")
            else STRESS_MESH if name == "icosphere.obj" else MESHES / name)
    scene = instancing.load_scene({"models": {"m": {"type": path.suffix[1:], "filename": str(path)}},
                                   "instances": [{"model": "m"}]})
    lo, hi = scene.bounds
    # Origins around and inside the mesh, aimed at points in its bounds.
    o = float32_exact(rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo), (20_000, 3)))
    d = float32_exact(rng.uniform(lo, hi, (20_000, 3)) - o)
    hits = scene.intersect(o, d)
    mesh = read_mesh(path)
    t, _, prim = reference.intersect_object("mesh", o, d, mesh=(float32_exact(mesh.vertices), mesh.faces))
    assert np.isfinite(t).sum() > (1000 if name == "needles" else 5000)  # the sample really hits the mesh
    np.testing.assert_array_equal(np.asarray(hits.prim), prim)
    hit = np.isfinite(t)
    np.testing.assert_array_equal(np.isfinite(np.asarray(hits.t)), hit)
    np.testing.assert_allclose(np.asarray(hits.t)[hit], t[hit], rtol=1e-6)


def _tree_arrays(tree: BVHKernel, order: np.ndarray) -> BVHArrays:
    """A kernel's boxes and references read back as BVHArrays."""
    m = tree.node_count
    packed = np.asarray(tree.boxes).reshape(-1, 4, 3)[:m]
    return BVHArrays(packed[:, 0::2], packed[:, 1::2], np.asarray(tree.refs).reshape(-1, 2)[:m],
                     order, tree.root_ref)


def _item_unions(bvh: BVHArrays, lo: np.ndarray, hi: np.ndarray):
    """Per node slot, the float64 union of the boxes of the items below it, by recursion."""
    out_lo, out_hi = np.zeros(bvh.child_lo.shape), np.zeros(bvh.child_hi.shape)

    def walk(ref: int):
        index, count = ref >> 4, ref & 15
        if count:
            items = bvh.order[index:index + count]
            return lo[items].min(axis=0), hi[items].max(axis=0)
        for k, child in enumerate(bvh.child_ref[index]):
            out_lo[index, k], out_hi[index, k] = walk(int(child))
        return out_lo[index].min(axis=0), out_hi[index].max(axis=0)

    walk(bvh.root_ref)
    return out_lo, out_hi


def test_refit_gives_every_box_the_union_of_the_moved_items_below_it():
    rng = np.random.default_rng(11)
    lo, hi = random_boxes(rng, 600)
    arrays = build_bvh(lo, hi, 2)
    tree = BVHKernel(arrays)
    moved = rng.choice(600, 40, replace=False)
    shift = rng.normal(0.0, 0.02, (40, 3))
    lo, hi = lo.copy(), hi.copy()
    lo[moved] += shift
    hi[moved] += shift
    refitted = refit_bvh(tree, arrays.order, moved, lambda items: (lo[items], hi[items]))
    assert refitted is not None
    after = _tree_arrays(refitted, arrays.order)
    np.testing.assert_array_equal(after.child_ref, arrays.child_ref)  # the shape is kept
    check_tree(after, lo, hi, 2)
    # Exactly the float32 outward rounding of each slot's float64 union (rounding down is
    # monotone, so the union of rounded child boxes equals the rounded union).
    want_lo, want_hi = outward32(*_item_unions(after, lo, hi))
    np.testing.assert_array_equal(after.child_lo, want_lo)
    np.testing.assert_array_equal(after.child_hi, want_hi)
    assert refitted.cost >= tree.cost * 0.99  # cost tracked, not reset by the refit
    packed = np.stack([after.child_lo[:, 0], after.child_hi[:, 0], after.child_lo[:, 1], after.child_hi[:, 1]],
                      axis=1)
    np.testing.assert_allclose(refitted.cost, surface_cost(packed, after.child_ref), rtol=1e-9)


def test_refit_declines_far_moves_and_trees_without_inner_nodes():
    rng = np.random.default_rng(12)
    lo, hi = random_boxes(rng, 300)
    arrays = build_bvh(lo, hi, 2)
    moved = np.arange(0, 300, 3)
    far_lo, far_hi = lo.copy(), hi.copy()
    far_lo[moved] = -far_lo[moved]  # mirrored through the origin: boxes across the tree
    far_hi[moved] = -far_lo[moved] + (hi - lo)[moved]
    assert refit_bvh(BVHKernel(arrays), arrays.order, moved,
                     lambda items: (far_lo[items], far_hi[items])) is None
    leaf_only = build_bvh(lo[:1], hi[:1], 2)
    assert refit_bvh(BVHKernel(leaf_only), leaf_only.order, np.array([0]),
                     lambda items: (lo[items], hi[items])) is None


def _clustered_spheres(rng, n):
    centres = rng.uniform(-40.0, 40.0, (4, 3))[rng.integers(0, 4, n)] + rng.normal(0, 1.0, (n, 3))
    m = np.zeros((n, 4, 4))
    m[:, [0, 1, 2], [0, 1, 2]] = rng.uniform(0.1, 0.3, n)[:, None]
    m[:, :3, 3] = centres
    m[:, 3, 3] = 1.0
    return m


@pytest.mark.parametrize("offset, refitted", [(0.05, True), (60.0, False)])
def test_moved_instances_in_a_bvh_scene_are_hit_as_by_brute_force(offset, refitted):
    rng = np.random.default_rng(13)
    m = _clustered_spheres(rng, 2000)
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": m}]}, accel="bvh")
    refs = scene.bvh.refs
    moved = rng.choice(2000, 6, replace=False)
    new = m[moved].copy()
    new[:, :3, 3] += rng.normal(0.0, offset, (6, 3))
    scene.set_transforms(Transform(matrices_to_lanes(new), matrices_to_lanes(affine_inverse(new))),
                         new, changed=moved)
    assert scene.accel == "bvh"
    # Small moves refit the tree (same references); far ones build it anew.
    assert (scene.bvh.refs is refs) == refitted
    m[moved] = new
    brute = instancing.load_scene({"instances": [{"model": "sphere", "to_world": m}]}, accel="brute")
    # Rays from random origins, half aimed at the moved spheres' centres.
    o = float32_exact(rng.uniform(-50.0, 50.0, (8192, 3)))
    aim = np.where(np.arange(8192)[:, None] % 2 == 0, new[np.arange(8192) % 6, :3, 3],
                   m[rng.integers(0, 2000, 8192), :3, 3])
    d = float32_exact(aim - o)
    got, want = scene.intersect(o, d), brute.intersect(o, d)
    assert (np.asarray(want.instance) != 0xFFFFFFFF).mean() > 0.4
    np.testing.assert_array_equal(np.asarray(got.instance), np.asarray(want.instance))
    np.testing.assert_array_equal(np.asarray(got.t), np.asarray(want.t))


@pytest.mark.parametrize("size", [2, 3, 5, FRONTIER])
@pytest.mark.parametrize("clustered", [False, True])
def test_frontier_subtrees_cover_every_item_once_inside_their_boxes(size, clustered):
    rng = np.random.default_rng(21)
    lo, hi = random_boxes(rng, 300, clustered)
    arrays = build_bvh(lo, hi, 4)
    frontier = BVHKernel(arrays, frontier=size).frontier()
    inner = int((arrays.child_ref & 15 == 0).sum()) + 1  # inner nodes, the root included
    # Each replacement of a subtree by its children adds one: size subtrees, or all the
    # leaves when the tree has fewer.
    assert len(frontier) == min(size, inner + 1)
    slo, shi = lo[arrays.order], hi[arrays.order]
    covered = []

    def positions(ref: int) -> np.ndarray:
        index, count = ref >> 4, ref & 15
        if count:
            return np.arange(index, index + count)
        return np.concatenate([positions(int(r)) for r in arrays.child_ref[index]])

    for ref, box_lo, box_hi in frontier:
        below = positions(ref)
        assert np.all(box_lo <= slo[below]) and np.all(box_hi >= shi[below])
        covered.append(below)
    assert np.array_equal(np.sort(np.concatenate(covered)), np.arange(300))


def test_trees_with_a_leaf_root_or_no_frontier_start_at_the_root():
    rng = np.random.default_rng(22)
    lo, hi = random_boxes(rng, 40)
    assert BVHKernel(build_bvh(lo[:1], hi[:1], 4)).frontier() == []
    assert BVHKernel(build_bvh(lo, hi, 4), frontier=0).frontier() == []
    for bad in (FRONTIER + 1, -1, 2.0):  # more subtrees than the stack bound allows
        with pytest.raises(ValueError, match="frontier must be an integer from 0 to 8"):
            BVHKernel(build_bvh(lo, hi, 4), frontier=bad)


def test_refit_moves_the_frontier_boxes_with_the_tree():
    rng = np.random.default_rng(23)
    lo, hi = random_boxes(rng, 600, clustered=True)
    arrays = build_bvh(lo, hi, 2)
    tree = BVHKernel(arrays)
    moved = rng.choice(600, 40, replace=False)
    lo, hi = lo.copy(), hi.copy()
    shift = rng.normal(0.0, 0.02, (40, 3))
    lo[moved] += shift
    hi[moved] += shift
    refitted = refit_bvh(tree, arrays.order, moved, lambda items: (lo[items], hi[items]))
    assert refitted is not None
    after = _tree_arrays(refitted, arrays.order)
    slots = {int(after.child_ref[node, slot]): (after.child_lo[node, slot], after.child_hi[node, slot])
             for node, slot in zip(*np.nonzero(np.ones(after.child_ref.shape, bool)))}
    assert [ref for ref, _, _ in refitted.frontier()] == [ref for ref, _, _ in tree.frontier()]
    for ref, box_lo, box_hi in refitted.frontier():
        np.testing.assert_array_equal(box_lo, slots[ref][0])
        np.testing.assert_array_equal(box_hi, slots[ref][1])


@pytest.mark.parametrize("frontier", [0, 2, FRONTIER])
def test_walks_from_the_frontier_hit_and_shadow_as_brute_force(frontier):
    # Rays through a sparse clustered field (most miss every subtree, some cross several
    # clusters) and rays aimed at spheres: nearest hits, and shadow queries stopping at
    # t_max, as by brute force, whatever the frontier (0: every walk from the root).
    rng = np.random.default_rng(24)
    m = _clustered_spheres(rng, 3000)
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": m}]}, accel="bvh")
    scene.bvh = BVHKernel(_tree_arrays(scene.bvh, np.arange(3000)), frontier=frontier)
    assert len(scene.bvh.frontier()) == frontier
    brute = instancing.load_scene({"instances": [{"model": "sphere", "to_world": m}]}, accel="brute")
    o = float32_exact(rng.uniform(-60.0, 60.0, (8192, 3)))
    d = float32_exact(np.where(np.arange(8192)[:, None] % 4 == 0,
                               m[rng.integers(0, 3000, 8192), :3, 3] - o, rng.normal(size=(8192, 3))))
    got, want = scene.intersect(o, d), brute.intersect(o, d)
    hit = np.isfinite(np.asarray(want.t))
    assert 0.2 < hit.mean() < 0.5
    np.testing.assert_array_equal(np.asarray(got.instance), np.asarray(want.instance))
    np.testing.assert_array_equal(np.asarray(got.t), np.asarray(want.t))
    jo, jd = (instancing.core.backend.Array3f(*a.T) for a in (o - scene.origin, d))
    t_max = instancing.core.backend.Float(np.where(hit, np.asarray(want.t) * rng.uniform(0.5, 1.5, 8192),
                                                   100.0).astype(np.float32))
    shadow = np.asarray(scene.occluded(jo, jd, t_max))
    np.testing.assert_array_equal(shadow, np.asarray(brute.occluded(jo, jd, t_max)))
    assert 0.1 < shadow.mean() < hit.mean()
