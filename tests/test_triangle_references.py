"""Triangle references (instancing/accel/triangle_references.py): how many each triangle gets,
that their boxes hold the triangle, and that a mesh of split triangles is sampled by area as
before (the walks through such meshes: tests/test_mesh_model.py and tests/test_bvh.py)."""

from __future__ import annotations

import numpy as np

import instancing
from instancing.accel.bvh import build_bvh, surface_cost
from instancing.accel.sah import box_area
from instancing.accel.triangle_references import (MAX_PIECES, MAX_REFERENCES, SAMPLE_WINDOW, SAMPLE_WINDOWS,
                                                  SPLIT_MIN_EXCESS, mesh_forest, piece_counts,
                                                  triangle_references)
from instancing.core.backend import Float, UInt32, device_arrays
from instancing.io.mesh_file import read_mesh
from instancing.models.mesh import MeshLibrary
from instancing.validation import reference
from scene_helpers import MESH_DIR, float32_exact, sliver_sphere


def needle(length: float, width: float, turn: np.ndarray) -> np.ndarray:
    """A triangle (3 corners, 3) of base ``width`` and height ``length`` turned by ``turn``."""
    return np.array([[0.0, 0.0, 0.0], [width, 0.0, 0.0], [0.5 * width, length, 0.0]]) @ turn.T


def rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def test_piece_counts_follow_the_box_excess_within_the_budget():
    rng = np.random.default_rng(3)
    turn = rotation(rng)
    right = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # box excess 2
    degenerate = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    # Turned needles 10 long: box excess from the closed form, area 10 w / 2.
    slivers = np.stack([needle(10.0, w, turn) for w in (10.0, 1.0, 0.1, 0.01)])
    excess = box_area(slivers.min(axis=1), slivers.max(axis=1)) / (10.0 * np.array([10.0, 1.0, 0.1, 0.01]))
    assert excess[0] < SPLIT_MIN_EXCESS < excess[1]
    # Among forty right triangles the budget does not bind: each sliver gets the most pieces.
    corners = np.stack([*[right] * 40, degenerate, *slivers])
    np.testing.assert_array_equal(piece_counts(corners), [1] * 42 + [MAX_PIECES] * 3)
    # Many slivers: the budget binds, and one factor D gives every count (1 + floor(D w),
    # at most MAX_PIECES, w the cube root of the box area beyond the triangle's faces).
    many = np.stack([needle(10.0, rng.uniform(0.001, 0.5), rotation(rng)) for _ in range(200)])
    counts = piece_counts(many)
    assert MAX_REFERENCES * len(many) - len(many) < counts.sum() <= MAX_REFERENCES * len(many)
    area2 = np.linalg.norm(np.cross(many[:, 1] - many[:, 0], many[:, 2] - many[:, 0]), axis=1)
    boxes = box_area(many.min(axis=1), many.max(axis=1))
    split = boxes >= SPLIT_MIN_EXCESS * area2
    assert split.sum() > 150 and np.all(counts[~split] == 1)
    w = (boxes[split] - area2[split]) ** (1 / 3)
    uncapped = counts[split] < MAX_PIECES
    lowest = np.max(np.where(uncapped, (counts[split] - 1) / w, (MAX_PIECES - 1) / w))
    highest = np.min(np.where(uncapped, counts[split] / w, np.inf))
    assert lowest < highest


def test_references_hold_their_triangles_in_tighter_boxes():
    rng = np.random.default_rng(5)
    corners = float32_exact(np.concatenate([
        np.stack([needle(rng.uniform(1, 20), rng.uniform(0.005, 1), rotation(rng)) for _ in range(150)]),
        rng.normal(size=(150, 3, 3))]) + rng.uniform(-50, 50, (300, 1, 3)))
    triangle, lo, hi = triangle_references(corners)
    counts = np.bincount(triangle, minlength=len(corners))
    np.testing.assert_array_equal(counts, piece_counts(corners))
    assert (counts > 1).sum() > 100
    # Every point of a triangle (corners, edges, inside) lies in one of its references' boxes.
    b = rng.dirichlet(np.ones(3), (len(corners), 400))
    b[:, :3] = np.eye(3)
    b[:, 3:100, 2] = 0.0
    b[:, 3:100, :2] /= b[:, 3:100, :2].sum(axis=2, keepdims=True)
    points = np.einsum("fsc,fcj->fsj", b, corners)
    held = np.zeros(points.shape[:2], bool)
    for r in range(len(triangle)):
        f = triangle[r]
        held[f] |= np.all((points[f] >= lo[r]) & (points[f] <= hi[r]), axis=1)
    assert held.all()
    # Inside the triangle's box, and in all less box area where split.
    t_lo, t_hi = corners.min(axis=1), corners.max(axis=1)
    assert np.all(lo >= t_lo[triangle] - 1e-9) and np.all(hi <= t_hi[triangle] + 1e-9)
    split = counts > 1
    areas = np.bincount(triangle, weights=box_area(lo, hi), minlength=len(corners))
    assert np.all(areas[split] < box_area(t_lo, t_hi)[split])


def test_split_triangles_are_sampled_by_area_once_each(tmp_path):
    mesh = read_mesh(sliver_sphere(tmp_path / "slivers.obj"))
    library = MeshLibrary([mesh])
    faces = len(mesh.faces)
    assert library.triangle_total > 2 * faces
    # Stratified u1: each triangle gets its area's share of the n strata, within one.
    n = 1 << 20
    u1 = ((np.arange(n) + 0.5) / n).astype(np.float32)
    u = device_arrays(Float, u1, np.full(n, 0.25, np.float32))
    _, position, _ = library.sample_area(UInt32(0), UInt32(library.triangle_total), *u)
    face = np.asarray(library.original_index)[np.asarray(position)]
    v = float32_exact(mesh.vertices)[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    expected = n * area / area.sum()
    assert np.abs(np.bincount(face, minlength=faces) - expected).max() <= 1.0 + 1e-5 * n


def _cost_alone(lo: np.ndarray, hi: np.ndarray) -> float:
    """Surface cost of the tree built over boxes (lo, hi) alone, with its root box."""
    tree = build_bvh(lo, hi, 4)
    packed = np.stack([tree.child_lo[:, 0], tree.child_hi[:, 0], tree.child_lo[:, 1], tree.child_hi[:, 1]], 1)
    root_items = tree.root_ref & 15
    return (surface_cost(packed, tree.child_ref)
            + box_area(lo.min(axis=0), hi.max(axis=0)) * (root_items if root_items else 1))


def test_each_mesh_keeps_the_tree_of_lower_surface_cost(tmp_path):
    # A low-poly tree (a third of its triangles slanted enough to split) and a sphere of slivers.
    meshes = [read_mesh(MESH_DIR / "tree.ply"), read_mesh(sliver_sphere(tmp_path / "slivers.obj"))]
    corners = [float32_exact(m.vertices)[m.faces] for m in meshes]
    forest, roots, triangles = mesh_forest(corners, 4)
    split = []
    for v, leaf_triangles in zip(corners, triangles):
        triangle, lo, hi = triangle_references(v)
        assert len(triangle) > len(v)
        split.append(_cost_alone(lo, hi) < _cost_alone(v.min(axis=1), v.max(axis=1)))
        expected = np.sort(triangle) if split[-1] else np.arange(len(v))
        np.testing.assert_array_equal(np.sort(leaf_triangles), expected)
    assert split == [False, True]
    assert len(roots) == 2 and len(forest.order) == sum(len(t) for t in triangles)


def test_a_large_mesh_is_decided_on_a_sample_and_walked_as_brute_force(tmp_path):
    rng = np.random.default_rng(8)
    # 80 low-poly trees in one mesh (whose references cost more) and a sphere of 33 000
    # slivers (whose references cost less), both above the sample's size.
    tree = read_mesh(MESH_DIR / "tree.ply")
    trees = float32_exact(np.concatenate([tree.vertices[tree.faces] @ rotation(rng).T + rng.uniform(-9, 9, 3)
                                          for _ in range(80)]))
    path = sliver_sphere(tmp_path / "slivers.obj", bands=16, segments=1100)
    mesh = read_mesh(path)
    slivers = float32_exact(mesh.vertices)[mesh.faces]
    assert min(len(trees), len(slivers)) > SAMPLE_WINDOWS * SAMPLE_WINDOW
    _, roots, triangles = mesh_forest([trees, slivers], 4)
    np.testing.assert_array_equal(np.sort(triangles[0]), np.arange(len(trees)))
    np.testing.assert_array_equal(np.sort(triangles[1]), np.sort(triangle_references(slivers)[0]))
    assert len(roots) == 2
    # The chosen tree's walk: rays from outside at points inside random triangles.
    scene = instancing.load_scene({"models": {"m": {"type": "obj", "filename": str(path)}},
                                   "instances": [{"model": "m"}]})
    assert scene.instances.libraries["mesh"].triangle_total == len(triangles[1])
    face = rng.integers(0, len(slivers), 2_000)
    target = np.einsum("fc,fcj->fj", rng.dirichlet(np.ones(3), 2_000), slivers[face])
    o = float32_exact(target * rng.uniform(1.5, 3.0, (2_000, 1)) + rng.normal(0.0, 0.3, (2_000, 3)))
    d = float32_exact(target - o)
    hits = scene.intersect(o, d)
    t, _, prim = reference.intersect_object("mesh", o, d, mesh=(float32_exact(mesh.vertices), mesh.faces))
    assert np.isfinite(t).all()
    np.testing.assert_array_equal(np.asarray(hits.prim), prim)
    np.testing.assert_allclose(np.asarray(hits.t), t, rtol=1e-6)
