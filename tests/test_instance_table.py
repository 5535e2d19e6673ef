"""The instance table (instancing/scene/instance_table.py) of a loaded scene: the stored
float32 matrices read back against NumPy float32 rounding and float64 inverses, the remap
bound, partial and full transform updates, row save/restore and per-kind lane masks."""

import numpy as np
import pytest

import instancing
from instancing.core import transform as tf
from instancing.core.backend import Array3f, Float, UInt32, dr
from scene_helpers import MESH_FILE, random_affine

#: float32 unit roundoff.
EPS32 = 2.0 ** -24
KINDS = ["sphere", "cube", "rectangle", "disk", "cylinder", "mesh"]
N = 14


def _scene(seed: int = 0, kinds=None):
    """N instances of mixed kinds, each placed by a random affine 4x4 ``matrix`` op."""
    rng = np.random.default_rng(seed)
    kinds = kinds or [KINDS[i % len(KINDS)] for i in range(N)]
    matrices = np.stack([random_affine(rng, 4.0, reflect=i % 3 == 2) for i in range(len(kinds))])
    scene = instancing.load_scene({
        "models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
        "instances": [{"model": "torus" if k == "mesh" else k, "to_world": [{"matrix": m.tolist()}]}
                      for k, m in zip(kinds, matrices)],
    })
    return rng, scene, kinds, matrices


def _f32(x):
    return np.asarray(x, np.float32).astype(np.float64)


def _inverse_tolerance(a32: np.ndarray, b32: np.ndarray) -> np.ndarray:
    """Elementwise bound of (stored A^-1, -A^-1 b) against the float64 inverse: the linear
    part is the float64 inverse rounded once (half a unit of roundoff, relative); the
    translation -A^-1 b is formed in float64 from the rounded A^-1 and b, so it moves by
    at most |A^-1| |b| times a few units of roundoff."""
    inv = np.linalg.inv(a32)
    tol = np.zeros(a32.shape[:-2] + (4, 4))
    tol[..., :3, :3] = EPS32 * np.abs(inv)
    tol[..., :3, 3] = 4 * EPS32 * np.einsum("...ij,...j->...i", np.abs(inv), np.abs(b32))
    return tol


def test_to_world_reads_back_the_float32_rounding_of_the_input():
    _, scene, _, matrices = _scene()
    table = scene.instances
    assert table.count == N
    np.testing.assert_array_equal(table.to_world, _f32(matrices))
    assert table.to_world.dtype == np.float64


def test_from_world_is_the_rounded_float64_inverse():
    """The linear part is the float64 inverse of the user's matrix rounded once to float32
    (never the inverse of the rounded matrix); the translation is -A^-1 b from the stored
    values, within a few units of roundoff of the float64 inverse's."""
    _, scene, _, matrices = _scene()
    inverse64 = np.linalg.inv(matrices)
    from_world = scene.instances.from_world
    np.testing.assert_array_equal(from_world[:, :3, :3], _f32(inverse64[:, :3, :3]))
    np.testing.assert_array_equal(from_world[:, 3], np.tile([0, 0, 0, 1.0], (N, 1)))
    tol = _inverse_tolerance(matrices[:, :3, :3], _f32(matrices[:, :3, 3]))
    assert (np.abs(from_world - inverse64) <= tol + 1e-300).all()
    # And it inverts the stored forward matrix up to float32 rounding, scaled by the
    # condition (|A^-1| |A|).
    product = from_world @ scene.instances.to_world
    cond = np.abs(from_world[:, :3, :3]) @ np.abs(scene.instances.to_world[:, :3, :3])
    assert (np.abs(product[:, :3, :3] - np.eye(3)) <= 2 * EPS32 * cond).all()


@pytest.mark.parametrize("index", [3, slice(2, 9, 3), np.array([5, 0, 5, 13]), np.array([[1, 2], [12, 7]])])
def test_to_world_of_and_from_world_of_equal_the_rows_of_the_full_arrays(index):
    _, scene, _, _ = _scene()
    table = scene.instances
    np.testing.assert_array_equal(table.to_world_of(index), table.to_world[index])
    np.testing.assert_array_equal(table.from_world_of(index), table.from_world[index])


def test_forward_and_inverse_gather_the_stored_rows_per_lane():
    """Kernels' per-lane rows: (A row i, b_i) and (A^-1 row i, b_i), b the forward
    translation in both."""
    _, scene, _, _ = _scene()
    table = scene.instances
    lanes = np.array([0, 7, 13, 7, 2], np.uint32)
    fwd = np.stack([np.asarray(r, np.float64).T for r in table.forward(UInt32(lanes))], 1)
    inv = np.stack([np.asarray(r, np.float64).T for r in table.inverse(UInt32(lanes))], 1)
    to_world, from_world = table.to_world[lanes], table.from_world[lanes]
    np.testing.assert_array_equal(fwd, to_world[:, :3, :])
    np.testing.assert_array_equal(inv[..., :3], from_world[:, :3, :3])
    np.testing.assert_array_equal(inv[..., 3], to_world[:, :3, 3])


def test_remap_error_bounds_the_return_of_world_points_to_object_space():
    """remap_error is positive, and a float32 world point taken back to object space by the
    kernels' map (A^-1 (w - b) in float32, transform.object_ray) lands within
    remap * max|p| of its exact float64 preimage p under the stored forward matrix."""
    rng, scene, _, _ = _scene(1)
    table = scene.instances
    remap = np.asarray(table.remap_error, np.float64)
    assert remap.shape == (N,) and (remap > 0).all()
    k = 4096
    inst = rng.integers(0, N, k).astype(np.uint32)
    to_world = table.to_world[inst]
    p_obj = rng.uniform(-1.5, 1.5, (k, 3))
    w = _f32(np.einsum("kij,kj->ki", to_world[:, :3, :3], p_obj) + to_world[:, :3, 3])
    exact = np.einsum("kij,kj->ki", np.linalg.inv(to_world[:, :3, :3]), w - to_world[:, :3, 3])
    rows = table.inverse(UInt32(inst))
    zero = Float(np.zeros(k, np.float32))
    back, _ = tf.object_ray(rows, Array3f(*[Float(w[:, c].astype(np.float32)) for c in range(3)]),
                            Array3f(zero, zero, zero))
    back = np.asarray(back, np.float64).T
    deviation = np.abs(back - exact).max(1)
    assert (deviation <= remap[inst] * np.abs(exact).max(1)).all()
    assert deviation.max() > 0  # the map really rounds (measured: up to 0.29 of the bound)


def _lanes(matrices: np.ndarray) -> tf.Transform:
    return tf.from_matrix(tf.matrices_to_lanes(matrices))


def _stored(table):
    """Bitwise snapshot of everything the table stores per instance."""
    inverse, linear = table._host_rows()
    return inverse.copy(), linear.copy(), np.asarray(table.remap_error).copy()


@pytest.mark.parametrize("as_uint32", [False, True])
def test_set_transforms_with_changed_writes_only_those_rows(as_uint32):
    rng, scene, _, _ = _scene(2)
    table = scene.instances
    before = _stored(table)
    changed = np.array([11, 2, 6])
    new = np.stack([random_affine(rng, 4.0) for _ in changed])
    table.set_transforms(_lanes(new), UInt32(changed.astype(np.uint32)) if as_uint32 else changed)
    after = _stored(table)
    others = np.setdiff1d(np.arange(N), changed)
    for b, a in zip(before, after):
        np.testing.assert_array_equal(a[others], b[others])  # bit for bit
    # The changed rows: the lanes' float32 matrices, and their float32 inverses
    # (dr.rcp of the Matrix4f lanes: within float32 rounding times the condition).
    np.testing.assert_array_equal(table.to_world_of(changed), _f32(new))
    inv = table.from_world_of(changed)
    tol = 16 * EPS32 * np.einsum("kij,kjl->kil", np.abs(np.linalg.inv(_f32(new))), np.abs(_f32(new)))
    np.testing.assert_array_less(np.abs(inv @ _f32(new) - np.eye(4))[:, :3, :3], tol[:, :3, :3] + 1e-12)
    # Remap bounds recomputed for those instances (the others stayed, checked above).
    remap = np.asarray(table.remap_error)
    assert (remap[changed] != before[2][changed]).all() and (remap[changed] > 0).all()


def test_set_transforms_without_changed_packs_every_row():
    rng, scene, _, _ = _scene(3)
    table = scene.instances
    new = np.stack([random_affine(rng, 2.0) for _ in range(N)])
    table.set_transforms(_lanes(new))
    np.testing.assert_array_equal(table.to_world, _f32(new))
    # One lane for all: broadcast.
    one = tf.translate([1.0, -2.0, 0.5]).to_lanes()
    table.set_transforms(one)
    expected = np.eye(4)
    expected[:3, 3] = [1.0, -2.0, 0.5]
    np.testing.assert_array_equal(table.to_world, np.broadcast_to(expected, (N, 4, 4)))
    np.testing.assert_array_equal(table.from_world, np.broadcast_to(np.linalg.inv(expected), (N, 4, 4)))


def test_derivatives_only_keeps_the_values_and_attaches_the_lanes_derivatives():
    rng, scene, _, _ = _scene(4)
    table = scene.instances
    before = _stored(table)
    changed = np.array([1, 8])
    param = tf.matrices_to_lanes(np.stack([random_affine(rng, 2.0) for _ in changed]))
    dr.enable_grad(param)
    table.set_transforms(tf.from_matrix(param), changed, derivatives_only=True)
    for b, a in zip(before, _stored(table)):
        np.testing.assert_array_equal(a, b)
    assert dr.grad_enabled(table.forward_linear)
    # Each changed lane's A entries appear once in the forward rows: d(sum)/dA = 1, and the
    # translation (stored in the inverse rows' w) is not part of forward_linear.
    dr.backward(dr.sum(table.forward_linear))
    grad = np.asarray(dr.grad(param), np.float64)  # (4, 4, K)
    np.testing.assert_array_equal(grad[:3, :3], np.ones((3, 3, len(changed))))
    np.testing.assert_array_equal(grad[:3, 3], np.zeros((3, len(changed))))
    table.detach()
    assert not dr.grad_enabled(table.forward_linear)


def test_rows_and_restore_rows_round_trip():
    rng, scene, _, _ = _scene(5)
    table = scene.instances
    to_world, from_world = table.to_world, table.from_world
    saved = table.rows()
    table.set_transforms(_lanes(np.stack([random_affine(rng, 2.0) for _ in range(3)])), np.array([0, 4, 9]))
    assert not np.array_equal(table.to_world, to_world)
    table.restore_rows(saved)
    np.testing.assert_array_equal(table.to_world, to_world)
    np.testing.assert_array_equal(table.from_world, from_world)


def test_kind_mask_marks_the_lanes_of_each_kind():
    _, scene, kinds, _ = _scene(6)
    table = scene.instances
    # Kinds in code order (analytic models, then meshes), only those present.
    assert table.kind_names == ["sphere", "cube", "rectangle", "disk", "cylinder", "mesh"]
    lanes = np.array([13, 0, 5, 5, 7, 2, 1, 12, 3, 4], np.uint32)
    for code, name in enumerate(table.kind_names):
        mask = np.asarray(table.kind_mask(UInt32(lanes), code))
        np.testing.assert_array_equal(mask, np.array([kinds[i] == name for i in lanes]))
    codes, _ = table.host_codes
    np.testing.assert_array_equal(codes, [table.kind_names.index(k) for k in kinds])


def test_kind_mask_is_true_for_a_single_kind():
    _, scene, _, _ = _scene(7, kinds=["disk"] * 3)
    assert scene.instances.kind_names == ["disk"]
    assert scene.instances.kind_mask(UInt32([0, 1, 2]), 0) is True
