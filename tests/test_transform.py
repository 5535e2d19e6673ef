"""Tests of :mod:`instancing.core.transform` against independent references.

References are float64 NumPy matrices built here from the lecture's formulas
(T, S, R_x, R_y, R_z, reflections) and Rodrigues' formula, Mitsuba 3's
``ScalarTransform4f``, closed forms and central finite differences.

Tolerances:
* float64 results: 1e-12 (absolute on O(1) entries, or relative to the
  matrix norms involved), i.e. a few thousand ulps of slack over a handful of
  rounded operations;
* float32 per-lane results and Mitsuba (float32) matrices: ~1e-6 relative
  (float32 epsilon is 6e-8; trigonometric functions and a few products add
  an order of magnitude).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import instancing  # noqa: F401  (selects the backend before Dr.Jit/Mitsuba start)
from instancing.core import transform as tf
from instancing.core.backend import Array3f, Array4f, Float, dr
from instancing.core.errors import TransformError

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)

mi.set_variant("scalar_rgb")

F64 = 1e-12   # float64 tolerance (see module docstring)
F32 = 2e-6    # float32 relative tolerance (see module docstring)


# --- independent float64 references --------------------------------------------------------

def np_translate(v):
    m = np.eye(4)
    m[:3, 3] = v
    return m


def np_scale(s):
    return np.diag([*np.broadcast_to(np.asarray(s, float), (3,)), 1.0])


def np_rotate(axis, degrees):
    """Rodrigues: R = I + sin(q) K + (1 - cos(q)) K^2 with K the cross-product matrix of the unit axis."""
    k = np.asarray(axis, float)
    k = k / np.linalg.norm(k)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    q = math.radians(degrees)
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(q) * kx + (1 - math.cos(q)) * kx @ kx
    return m


def lecture_rx(degrees):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def lecture_ry(degrees):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def lecture_rz(degrees):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


LECTURE_REFLECT = {"x": np.diag([-1.0, 1, 1, 1]), "y": np.diag([1.0, -1, 1, 1]),
                   "z": np.diag([1.0, 1, -1, 1])}


def mat(t):
    """A scalar transform's (matrix, inverse) as float64 NumPy arrays."""
    return np.array(t.matrix, dtype=np.float64), np.array(t.inverse_matrix, dtype=np.float64)


def mi_mat(t):
    return np.array(t.matrix, dtype=np.float64)


def assert_inverse_pair(t, tol=F64):
    """matrix @ inverse == I and inverse @ matrix == I, relative to the norms' product."""
    m, inv = mat(t)
    bound = tol * np.linalg.norm(m) * np.linalg.norm(inv)
    assert np.abs(m @ inv - np.eye(4)).max() <= bound
    assert np.abs(inv @ m - np.eye(4)).max() <= bound


def random_axis(rng):
    while True:
        a = rng.normal(size=3)
        if np.linalg.norm(a) > 0.1:
            return a


def hpoint(p):
    return np.append(np.asarray(p, float), 1.0)


# --- builders against the lecture, Rodrigues and Mitsuba ------------------------------------

def test_translate_matches_lecture_matrix():
    rng = np.random.default_rng(1)
    for _ in range(10):
        v = rng.uniform(-100, 100, 3)
        t = tf.translate(v.tolist())
        m, inv = mat(t)
        np.testing.assert_allclose(m, np_translate(v), rtol=0, atol=F64)
        np.testing.assert_allclose(inv, np_translate(-v), rtol=0, atol=F64)
        assert t.is_scalar


def test_scale_uniform_and_per_axis():
    rng = np.random.default_rng(2)
    for _ in range(10):
        s = rng.uniform(0.1, 10, 3) * rng.choice([-1, 1], 3)
        m, inv = mat(tf.scale(s.tolist()))
        np.testing.assert_allclose(m, np_scale(s), rtol=F64, atol=0)
        np.testing.assert_allclose(inv, np_scale(1 / s), rtol=F64, atol=0)
        u = float(s[0])
        m, inv = mat(tf.scale(u))
        np.testing.assert_allclose(m, np.diag([u, u, u, 1]), rtol=F64, atol=0)
        np.testing.assert_allclose(inv, np.diag([1 / u, 1 / u, 1 / u, 1]), rtol=F64, atol=0)


@pytest.mark.parametrize("builder, reference", [(tf.rotate_x, lecture_rx),
                                                (tf.rotate_y, lecture_ry),
                                                (tf.rotate_z, lecture_rz)])
def test_axis_rotations_match_lecture(builder, reference):
    for angle in (0.0, 17.0, 90.0, -45.0, 180.0, 333.3):
        m, inv = mat(builder(angle))
        np.testing.assert_allclose(m, reference(angle), rtol=0, atol=F64)
        # The inverse of a rotation is its transpose = rotation by -angle.
        np.testing.assert_allclose(inv, reference(-angle), rtol=0, atol=F64)


def test_rotate_z_90_maps_x_to_y():
    # Counter-clockwise looking down the negative z axis (lecture, "3D Rotation").
    p = np.array(tf.rotate_z(90).apply_point([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(p, [0, 1, 0], atol=F64)
    v = np.array(tf.rotate_x(90).apply_vector([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(v, [0, 0, 1], atol=F64)
    v = np.array(tf.rotate_y(90).apply_vector([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(v, [1, 0, 0], atol=F64)


def test_rotate_arbitrary_axis_matches_rodrigues():
    rng = np.random.default_rng(3)
    for _ in range(20):
        # Unnormalized axes of any length: the builder normalizes internally.
        axis = random_axis(rng) * rng.uniform(0.01, 100)
        angle = rng.uniform(-360, 360)
        m, inv = mat(tf.rotate(axis.tolist(), angle))
        ref = np_rotate(axis, angle)
        np.testing.assert_allclose(m, ref, rtol=0, atol=F64)
        np.testing.assert_allclose(inv, ref.T, rtol=0, atol=F64)
        assert abs(np.linalg.det(m) - 1) < F64

def test_rotate_reduces_huge_angles_modulo_360_exactly():
    # 1e12 + 30 is an integer below 2^53 (exact in float64) and 1e12 = 2777777777 * 360 + 280,
    # so the angle is 310 degrees; sin and cos of the unreduced angle gave a singular matrix.
    rng = np.random.default_rng(7)
    for _ in range(5):
        axis = random_axis(rng).tolist()
        for huge, remainder in ((1e12 + 30, 310.0), (-(1e12 + 30), -310.0),
                                (np.float64(1e300), math.fmod(1e300, 360))):
            m, inv = mat(tf.rotate(axis, huge))
            np.testing.assert_array_equal(m, mat(tf.rotate(axis, remainder))[0])
            np.testing.assert_allclose(m @ inv, np.eye(4), rtol=0, atol=F64)
    # Per lane (float32 angles, exact powers of two): the same matrices, and the derivative
    # with respect to the angle is the one at the remainder (the reduction's derivative is 1).
    huge = np.float32([2.0 ** 40, -2.0 ** 100, 3.0e38]).astype(np.float64)
    remainders = [math.fmod(a, 360) for a in huge]
    p = [1.5, -0.5, 2.0]
    axis = random_axis(rng).tolist()
    grads = []
    for angles in (huge, remainders):
        x = Float(angles)
        dr.enable_grad(x)
        t = tf.rotate(axis, x)
        q = t.apply_point(Array3f(*p))
        dr.forward(x)
        grads.append(np.array(dr.grad(q)))
        np.testing.assert_allclose(t.to_numpy()[0], np.array([np_rotate(axis, r) for r in remainders]),
                                   rtol=0, atol=5 * F32)
    np.testing.assert_allclose(grads[0], grads[1], rtol=0, atol=F32)
    assert np.abs(grads[0]).max() > 1e-3



@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_reflect_matches_lecture(axis):
    m, inv = mat(tf.reflect(axis))
    np.testing.assert_array_equal(m, LECTURE_REFLECT[axis])
    np.testing.assert_array_equal(inv, LECTURE_REFLECT[axis])


def test_reflect_rejects_bad_axis():
    with pytest.raises(TransformError, match="'w'"):
        tf.reflect("w")


def test_identity():
    m, inv = mat(tf.identity())
    np.testing.assert_array_equal(m, np.eye(4))
    np.testing.assert_array_equal(inv, np.eye(4))


def test_look_at_frame_properties():
    rng = np.random.default_rng(4)
    for _ in range(10):
        o, target = rng.uniform(-10, 10, 3), rng.uniform(-10, 10, 3)
        up = random_axis(rng)
        m, inv = mat(tf.look_at(o.tolist(), target.tolist(), up.tolist()))
        fwd = (target - o) / np.linalg.norm(target - o)
        r = m[:3, :3]
        # An orthonormal, right-handed frame placed at the origin ...
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=F64)
        assert abs(np.linalg.det(r) - 1) < F64
        np.testing.assert_allclose(m @ hpoint([0, 0, 0]), hpoint(o), atol=F64 * 10)
        # ... whose +z looks at the target, whose +y leans towards up, and whose x is
        # perpendicular to up (Mitsuba's camera convention).
        np.testing.assert_allclose(r[:, 2], fwd, atol=F64)
        assert r[:, 1] @ up > 0
        assert abs(r[:, 0] @ up) < F64 * np.linalg.norm(up)
        np.testing.assert_allclose(m @ inv, np.eye(4), atol=F64 * 100)  # |o| <= 17


def test_builders_agree_with_mitsuba():
    # Mitsuba's scalar_rgb transforms are float32: compare relative to the entry size.
    rng = np.random.default_rng(5)
    for _ in range(10):
        v = rng.uniform(-100, 100, 3)
        np.testing.assert_allclose(mat(tf.translate(v.tolist()))[0],
                                   mi_mat(mi.ScalarTransform4f().translate(v.tolist())),
                                   rtol=F32, atol=F32 * 100)
        s = rng.uniform(0.1, 10, 3)
        np.testing.assert_allclose(mat(tf.scale(s.tolist()))[0],
                                   mi_mat(mi.ScalarTransform4f().scale(s.tolist())),
                                   rtol=F32, atol=0)
        axis = random_axis(rng)
        angle = rng.uniform(-180, 180)
        # Mitsuba does not normalize the axis (rotate([2, 0, 0], a) scales by 4): give it a unit one.
        unit = (axis / np.linalg.norm(axis)).tolist()
        np.testing.assert_allclose(mat(tf.rotate(axis.tolist(), angle))[0],
                                   mi_mat(mi.ScalarTransform4f().rotate(unit, angle)),
                                   rtol=0, atol=F32)
        o, target, up = rng.uniform(-10, 10, 3), rng.uniform(-10, 10, 3), random_axis(rng)
        np.testing.assert_allclose(
            mat(tf.look_at(o.tolist(), target.tolist(), up.tolist()))[0],
            mi_mat(mi.ScalarTransform4f().look_at(origin=o.tolist(), target=target.tolist(),
                                                  up=up.tolist())),
            rtol=0, atol=F32 * 10)  # translation column up to 10


def test_from_matrix_roundtrip_and_inverse():
    rng = np.random.default_rng(6)
    for _ in range(10):
        m = np.eye(4)
        m[:3, :4] = rng.uniform(-3, 3, (3, 4))
        t = tf.from_matrix(m)
        got, inv = mat(t)
        np.testing.assert_array_equal(got, m)
        np.testing.assert_allclose(inv, np.linalg.inv(m), rtol=0,
                                   atol=F64 * np.linalg.cond(m) * np.abs(np.linalg.inv(m)).max())
        np.testing.assert_array_equal(inv[3], [0, 0, 0, 1])
        # Nested lists work as well as arrays.
        np.testing.assert_array_equal(mat(tf.from_matrix(m.tolist()))[0], m)


# --- inverses and composition --------------------------------------------------------------

def test_every_builder_inverse_is_true_inverse_and_inverse_swaps():
    rng = np.random.default_rng(7)
    shear = np.eye(4)
    shear[0, 1], shear[1, 2], shear[:3, 3] = 0.7, -1.3, [1, 2, 3]
    transforms = [tf.identity(), tf.translate([1.5, -2, 30]), tf.scale([0.1, 4, -7]), tf.scale(3.0),
                  tf.rotate_x(33), tf.rotate_y(-71), tf.rotate_z(123),
                  tf.rotate(random_axis(rng).tolist(), 41), tf.reflect("x"), tf.reflect("y"),
                  tf.reflect("z"), tf.look_at([1, 2, 3], [-4, 0, 2], [0, 1, 0]),
                  tf.from_matrix(shear)]
    for t in transforms:
        assert_inverse_pair(t)
        m, inv = mat(t)
        m2, inv2 = mat(t.inverse())
        np.testing.assert_array_equal(m2, inv)
        np.testing.assert_array_equal(inv2, m)
        np.testing.assert_array_equal(mat(t.inverse().inverse())[0], m)


def test_composition_applies_right_operand_first():
    a, b = tf.translate([1.0, 2.0, 3.0]), tf.rotate_z(90)
    p = [1.0, 0.0, 0.0]
    # B first (rotate +x to +y), then A: (1, 3, 3); the other order would give (2, 2, 3) -> (-2, 2, 3).
    np.testing.assert_allclose(np.array((a @ b).apply_point(p)), [1, 3, 3], atol=F64)
    np.testing.assert_allclose(np.array((b @ a).apply_point(p)), [-2, 2, 3], atol=F64)

    rng = np.random.default_rng(8)
    for _ in range(10):
        a = tf.rotate(random_axis(rng).tolist(), rng.uniform(-180, 180)) @ tf.translate(
            rng.uniform(-5, 5, 3).tolist())
        b = tf.scale(rng.uniform(0.2, 5, 3).tolist()) @ tf.rotate_x(rng.uniform(-180, 180))
        ab = a @ b
        for _ in range(3):
            q = rng.uniform(-5, 5, 3)
            direct = np.array(ab.apply_point(q.tolist()))
            nested = np.array(a.apply_point(b.apply_point(q.tolist())))
            ref = (mat(a)[0] @ mat(b)[0] @ hpoint(q))[:3]
            np.testing.assert_allclose(direct, nested, atol=F64 * 100)
            np.testing.assert_allclose(direct, ref, atol=F64 * 100)  # entries up to ~50
        # The inverse of a composition: inv(B) @ inv(A), and the true inverse of the product.
        m_ab, inv_ab = mat(ab)
        np.testing.assert_allclose(m_ab, mat(a)[0] @ mat(b)[0], atol=F64 * 10)
        np.testing.assert_allclose(inv_ab, mat(b)[1] @ mat(a)[1], atol=F64 * 10)
        np.testing.assert_allclose(inv_ab, np.linalg.inv(mat(a)[0] @ mat(b)[0]),
                                   atol=F64 * 10 * np.linalg.cond(m_ab))


def random_chain_ops(rng, n=100):
    """n random (builder name, args) pairs: rotations, translations, scales, reflections."""
    ops = []
    for _ in range(n):
        kind = rng.choice(["rotate", "translate", "scale", "reflect"], p=[0.35, 0.3, 0.25, 0.1])
        if kind == "rotate":
            ops.append(("rotate", (random_axis(rng), rng.uniform(-180, 180))))
        elif kind == "translate":
            ops.append(("translate", (rng.uniform(-100, 100, 3),)))
        elif kind == "scale":
            ops.append(("scale", (rng.uniform(0.1, 10, 3),)))
        else:
            ops.append(("reflect", (str(rng.choice(["x", "y", "z"])),)))
    return ops


def build_op(kind, args):
    if kind == "rotate":
        return tf.rotate(args[0].tolist(), float(args[1]))
    if kind == "translate":
        return tf.translate(args[0].tolist())
    if kind == "scale":
        return tf.scale(args[0].tolist())
    return tf.reflect(args[0])


def reference_op(kind, args):
    if kind == "rotate":
        return np_rotate(*args)
    if kind == "translate":
        return np_translate(args[0])
    if kind == "scale":
        return np_scale(args[0])
    return LECTURE_REFLECT[args[0]]


@pytest.mark.parametrize("seed", [10, 11, 12])
def test_chain_of_100_random_transforms_float64(seed):
    rng = np.random.default_rng(seed)
    ops = random_chain_ops(rng)
    t = tf.identity()
    ref, ref_inv = np.eye(4), np.eye(4)
    for kind, args in ops:
        t = t @ build_op(kind, args)
        ref = ref @ reference_op(kind, args)
        ref_inv = np.linalg.inv(reference_op(kind, args)) @ ref_inv
    m, inv = mat(t)
    norm = np.linalg.norm(m) * np.linalg.norm(inv)
    # 100 compositions, each rounding a 4x4 product: the error of M @ M^-1 is bounded by a
    # small multiple of 100 * 2.2e-16 * |M| |M^-1| (measured: ~1e-17 of the norms, which reach
    # 1e21 with 25 random scales); 1e-12 leaves ample slack yet catches a wrong order of the
    # inverse's factors (an O(1) relative error).
    err = np.abs((t @ t.inverse()).to_numpy()[0] - np.eye(4)).max()
    assert err <= 1e-12 * norm
    assert np.abs(m @ inv - np.eye(4)).max() <= 1e-12 * norm
    # The composed matrices agree with the independent NumPy products.
    assert np.abs(m - ref).max() <= 1e-12 * np.abs(ref).max() * len(ops)
    assert np.abs(inv - ref_inv).max() <= 1e-12 * np.abs(ref_inv).max() * len(ops)


@pytest.mark.parametrize("seed", [20, 21])
def test_chain_of_100_random_transforms_float32_lanes(seed):
    rng = np.random.default_rng(seed)
    ops = random_chain_ops(rng)
    t64 = tf.identity()
    t32 = tf.identity().to_lanes()
    for kind, args in ops:
        op = build_op(kind, args)
        t64 = t64 @ op
        t32 = t32 @ op.to_lanes()  # each factor rounded to float32, composed in float32
    assert not t32.is_scalar
    m32, inv32 = (a[0] for a in t32.to_numpy())
    m64, inv64 = mat(t64)
    norm = np.linalg.norm(m64) * np.linalg.norm(inv64)
    # float32: 100 rounded products, eps 6e-8 -> relative errors up to ~1e-5 of the norms.
    prod = (t32 @ t32.inverse()).to_numpy()[0][0]
    assert np.abs(prod - np.eye(4)).max() <= 1e-5 * norm
    assert np.abs(m32 - m64).max() <= 1e-5 * np.abs(m64).max()
    assert np.abs(inv32 - inv64).max() <= 1e-5 * np.abs(inv64).max()


# --- applying transforms ---------------------------------------------------------------------

def test_apply_point_and_vector():
    rng = np.random.default_rng(30)
    for _ in range(10):
        m = np.eye(4)
        m[:3, :4] = rng.uniform(-3, 3, (3, 4))
        t = tf.from_matrix(m)
        p = rng.uniform(-5, 5, 3)
        np.testing.assert_allclose(np.array(t.apply_point(p.tolist())), (m @ hpoint(p))[:3],
                                   atol=F64 * 100)
        # Vectors (w = 0) ignore the translation.
        np.testing.assert_allclose(np.array(t.apply_vector(p.tolist())), m[:3, :3] @ p,
                                   atol=F64 * 100)
    v = np.array(tf.translate([5.0, 6.0, 7.0]).apply_vector([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(v, [1, 2, 3])


def sphere_frame(rng, n):
    """n unit-sphere points with two tangent vectors at each."""
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    helper = np.where(np.abs(p[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(p, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(p, t1)
    return p, t1, t2


def normal_test_transforms():
    shear = np.eye(4)
    shear[0, 1], shear[0, 2], shear[1, 2] = 1.5, -0.8, 2.0
    shear[:3, 3] = [3, -1, 2]
    return {
        "nonuniform": tf.translate([1.0, 2.0, 3.0]) @ tf.rotate([1, 2, 3], 40) @ tf.scale([0.2, 3, 7]),
        "shear": tf.from_matrix(shear),
        "reflect_x": tf.reflect("x") @ tf.scale([1, 2, 0.5]),
        "reflect_yz": tf.translate([0, 0, 5.0]) @ tf.reflect("y") @ tf.reflect("z") @ tf.scale([4, 1, 1]),
        "negative_scale": tf.rotate_z(30) @ tf.scale([-2, 1, 3]),
    }


@pytest.mark.parametrize("name", list(normal_test_transforms()))
def test_apply_normal_perpendicular_and_outward(name):
    t = normal_test_transforms()[name]
    rng = np.random.default_rng(31)
    centre = np.array(t.apply_point([0.0, 0.0, 0.0]))
    pts, t1s, t2s = sphere_frame(rng, 40)
    for p, t1, t2 in zip(pts, t1s, t2s):
        n = np.array(t.apply_normal(p.tolist()))  # the sphere's outward normal is p
        assert abs(np.linalg.norm(n) - 1) < F64
        for tangent in (t1, t2):
            tw = np.array(t.apply_vector(tangent.tolist()))
            assert abs(n @ tw) <= F64 * 10 * np.linalg.norm(tw)
        assert n @ (np.array(t.apply_point(p.tolist())) - centre) > 0
    # Applying the matrix itself to the normal (the lecture's wrong way) is not perpendicular
    # for the non-reflection cases with non-uniform scale or shear: the test can fail.
    if name in ("nonuniform", "shear"):
        m = mat(t)[0][:3, :3]
        p, t1 = pts[0], t1s[0]
        wrong = m @ p
        assert abs(wrong @ (m @ t1)) > 1e-3 * np.linalg.norm(wrong) * np.linalg.norm(m @ t1)


def test_apply_normal_per_lane_matches_scalar():
    rng = np.random.default_rng(32)
    t = normal_test_transforms()["shear"]
    pts, _, _ = sphere_frame(rng, 64)
    lanes = np.array(t.to_lanes().apply_normal(Array3f(*[Float(c) for c in pts.T.astype(np.float32)])))
    ref = np.array([np.array(t.apply_normal(p.tolist())) for p in pts]).T
    np.testing.assert_allclose(lanes, ref, atol=10 * F32)


def test_apply_homogeneous():
    t = tf.translate([10.0, 20.0, 30.0]) @ tf.scale([1.0, 2.0, 3.0])
    # w != 1 is divided out: (2, 4, 6, 2) is the point (1, 2, 3).
    a = np.array(t.apply_homogeneous([2.0, 4.0, 6.0, 2.0]))
    b = np.array(t.apply_homogeneous([1.0, 2.0, 3.0, 1.0]))
    np.testing.assert_allclose(a, [11, 24, 39, 1], atol=F64)
    np.testing.assert_allclose(a, b, atol=F64)
    np.testing.assert_allclose(np.array(t.apply_homogeneous([-1.0, -2.0, -3.0, -1.0])), b, atol=F64)
    # w = 0 is a direction: translation ignored, w stays 0.
    d = np.array(t.apply_homogeneous([1.0, 2.0, 3.0, 0.0]))
    np.testing.assert_allclose(d, [1, 4, 9, 0], atol=F64)

    # Per lane, with a mix of w values: every returned w is 0 or 1.
    v = Array4f(Float([2, 1, 1, 3]), Float([4, 2, 2, 3]), Float([6, 3, 3, 3]), Float([2, 1, 0, -0.5]))
    out = np.array(t.to_lanes().apply_homogeneous(v))
    # Lane 3: (3, 3, 3) / -0.5 = (-6, -6, -6) -> scaled (-6, -12, -18) -> moved (4, 8, 12).
    expected = np.array([[11, 24, 39, 1], [11, 24, 39, 1], [1, 4, 9, 0], [4, 8, 12, 1]], float).T
    np.testing.assert_allclose(out, expected, rtol=F32, atol=F32)
    assert set(np.unique(out[3])) <= {0.0, 1.0}


# --- per-lane transforms and automatic differentiation ---------------------------------------

def lanes(t):
    """(N, 4, 4) matrix and inverse of a per-lane transform."""
    assert not t.is_scalar
    return t.to_numpy()


def test_per_lane_builders_agree_with_scalar():
    rng = np.random.default_rng(40)
    n = 7
    v = rng.uniform(-10, 10, (n, 3))
    s = rng.uniform(0.1, 10, (n, 3)) * rng.choice([-1, 1], (n, 3))
    axes = np.array([random_axis(rng) * rng.uniform(0.5, 5) for _ in range(n)])
    angles = rng.uniform(-360, 360, n)
    o, tgt, up = rng.uniform(-10, 10, (n, 3)), rng.uniform(-10, 10, (n, 3)), rng.normal(size=(n, 3))

    def a3(x):
        return Array3f(*[Float(c) for c in x.T.astype(np.float32)])

    def fl(x):
        return Float(x.astype(np.float32))

    cases = [
        (tf.translate(a3(v)), [tf.translate(x.tolist()) for x in v]),
        (tf.scale(a3(s)), [tf.scale(x.tolist()) for x in s]),
        (tf.scale(fl(s[:, 0])), [tf.scale(float(x)) for x in s[:, 0]]),
        (tf.rotate(a3(axes), fl(angles)), [tf.rotate(x.tolist(), float(a)) for x, a in zip(axes, angles)]),
        (tf.rotate([0.0, 1.0, 1.0], fl(angles)), [tf.rotate([0, 1, 1], float(a)) for a in angles]),
        (tf.rotate_x(fl(angles)), [tf.rotate_x(float(a)) for a in angles]),
        (tf.rotate_y(fl(angles)), [tf.rotate_y(float(a)) for a in angles]),
        (tf.rotate_z(fl(angles)), [tf.rotate_z(float(a)) for a in angles]),
        (tf.look_at(a3(o), a3(tgt), a3(up)),
         [tf.look_at(*(x.tolist() for x in xs)) for xs in zip(o, tgt, up)]),
    ]
    for per_lane, scalars in cases:
        m, inv = lanes(per_lane)
        assert m.shape == (n, 4, 4)
        for i, ts in enumerate(scalars):
            ms, invs = mat(ts)
            # float32 inputs and arithmetic: relative to the largest entry (angles up to 360
            # degrees lose a little more in the degree -> radian conversion).
            np.testing.assert_allclose(m[i], ms, rtol=0, atol=5 * F32 * max(1, np.abs(ms).max()))
            np.testing.assert_allclose(inv[i], invs, rtol=0, atol=5 * F32 * max(1, np.abs(invs).max()))


def test_per_lane_from_matrix_and_mixed_composition():
    rng = np.random.default_rng(41)
    n = 5
    ms = np.tile(np.eye(4), (n, 1, 1))
    ms[:, :3, :] = rng.uniform(-2, 2, (n, 3, 4))
    ms[:, :3, :3] += 3 * np.eye(3)  # well conditioned
    t = tf.from_matrix(tf.matrices_to_lanes(ms))
    m, inv = lanes(t)
    np.testing.assert_allclose(m, ms, atol=F32 * 2)
    np.testing.assert_allclose(inv, np.linalg.inv(ms), atol=20 * F32)
    # scalar @ per-lane promotes the scalar factor to lanes.
    s = tf.translate([1.0, 2.0, 3.0])
    m2, inv2 = lanes(s @ t)
    np.testing.assert_allclose(m2, mat(s)[0] @ ms, atol=20 * F32)
    np.testing.assert_allclose(inv2, np.linalg.inv(ms) @ mat(s)[1], atol=50 * F32)


def _point_grad_fd(build, x0, p, h):
    """Central difference in float64 of build(x).apply_point(p) at x0 with step h."""
    plus = np.array(build(x0 + h).apply_point(p))
    minus = np.array(build(x0 - h).apply_point(p))
    return (plus - minus) / (2 * h)


def _forward_grad(build, x0, p):
    x = Float(x0)
    dr.enable_grad(x)
    out = build(x).apply_point(Array3f(*p))
    dr.forward(x)
    return np.array(dr.grad(out))[:, 0]


def test_forward_ad_translation_component_vs_fd():
    p = [0.3, -1.2, 2.0]

    def build(tx):
        return tf.translate([1.0, -2.0, 0.5]) @ tf.rotate([1, 1, 0], 35) @ tf.translate([tx, 0.7, -0.4]) \
            @ tf.scale([2.0, 0.5, 1.5])

    # FD step 1e-4 units; the map is affine in tx, so FD is exact up to float64 rounding
    # (1e-16 / 1e-4); AD in float32 is good to ~1e-6 relative.
    ad = _forward_grad(build, 0.25, p)
    fd = _point_grad_fd(build, 0.25, p, 1e-4)
    np.testing.assert_allclose(ad, fd, rtol=1e-5, atol=1e-6)
    assert np.linalg.norm(fd) > 0.5  # the derivative is the rotated x axis: not trivial


@pytest.mark.parametrize("axis", [[0, 0, 1], [1, -2, 0.5]])
def test_forward_ad_rotation_angle_vs_fd(axis):
    p = [1.5, -0.5, 2.0]

    def build(angle):
        return tf.translate([3.0, 0.0, -1.0]) @ tf.rotate(axis, angle) @ tf.scale([1.0, 2.0, 0.5])

    # Angle in degrees, FD step 1e-4 deg: truncation error ~ h^2 (pi/180)^3 |p| / 6 ~ 1e-14,
    # rounding ~ 1e-16 * |p| / 1e-4 ~ 1e-12; AD in float32 (|grad| ~ 0.05): 1e-5 relative.
    for angle in (-130.0, 0.0, 37.0, 200.0):
        ad = _forward_grad(build, angle, p)
        fd = _point_grad_fd(build, angle, p, 1e-4)
        np.testing.assert_allclose(ad, fd, rtol=1e-5, atol=1e-7)
    assert np.linalg.norm(fd) > 1e-2


def test_forward_ad_through_inverse_vs_fd():
    p = [1.0, 2.0, -0.5]

    def build(theta):
        return tf.rotate_z(theta).inverse()

    # d/dtheta of R_z(theta)^-1 p, i.e. through the stored transpose; step 1e-4 deg as above.
    for theta in (0.0, 25.0, -100.0):
        ad = _forward_grad(build, theta, p)
        fd = _point_grad_fd(build, theta, p, 1e-4)
        np.testing.assert_allclose(ad, fd, rtol=1e-5, atol=1e-7)
        # Closed form: d/dq R_z(-q) p = (pi/180) (sin q x + cos q y, -cos q x + sin q y, 0)... check x.
        q = math.radians(theta)
        np.testing.assert_allclose(fd[0], math.pi / 180 * (-math.sin(q) * p[0] + math.cos(q) * p[1]),
                                   rtol=1e-8, atol=1e-12)


def test_forward_ad_per_lane_translation_through_inverse():
    # Per-lane translation: d/dt of translate(t)^-1 p = -e_x in every lane.
    tx = Float([0.0, 1.0, -3.0])
    dr.enable_grad(tx)
    t = tf.translate(Array3f(tx, 0.0, 0.0)) @ tf.rotate_y(30)
    q = t.inverse().apply_point(Array3f(1.0, 2.0, 3.0))
    dr.forward(tx)
    g = np.array(dr.grad(q))
    # Inverse: R_y(-30) (p - t); derivative -R_y(-30) e_x (closed form).
    ref = -lecture_ry(-30)[:3, 0]
    np.testing.assert_allclose(g, np.tile(ref[:, None], (1, 3)), atol=F32)


# --- validation ------------------------------------------------------------------------------

def _bad(fix):
    """A valid affine matrix broken by ``fix``."""
    a = np.eye(4)
    a[:3, :] = [[1, 2, 0, 1], [0, 1, 3, 2], [4, 0, 1, 3]]
    fix(a)
    return a


def _zero_row(a):
    a[1, :3] = 0


def _rank2(a):
    a[2, :3] = a[0, :3] + 2 * a[1, :3]


def _nan(a):
    a[0, 2] = np.nan


def _inf(a):
    a[2, 1] = np.inf


def _neg_inf(a):
    a[1, 3] = -np.inf


def _projective(a):
    a[3] = [0, 0, 1, 1]


def _scaled_w(a):
    a[3, 3] = 2.0


@pytest.mark.parametrize("fix, words", [(_zero_row, "singular"), (_rank2, "singular"),
                                        (_nan, "non-finite"), (_inf, "non-finite"),
                                        (_neg_inf, "non-finite"), (_projective, "affine"),
                                        (_scaled_w, "affine")])
def test_from_matrix_rejects_bad_matrices(fix, words):
    with pytest.raises(TransformError, match=words) as err:
        tf.from_matrix(_bad(fix), name="inst7")
    assert "inst7" in str(err.value)


@pytest.mark.parametrize("m", [np.eye(3), np.eye(4)[:3], np.zeros(16), np.eye(4)[None],
                               [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "eye", [["a"] * 4] * 4,
                               [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]])
def test_from_matrix_rejects_wrong_shapes(m):
    with pytest.raises(TransformError) as err:
        tf.from_matrix(m, name="inst7")
    assert "inst7" in str(err.value)


def test_from_matrix_accepts_nearly_degenerate_and_reflection():
    # One axis scaled by 1e-6, then rotated and moved: valid, and inverted accurately.
    m = np_translate([1, 2, 3]) @ np_rotate([1, 2, 3], 30) @ np_scale([1, 1e-6, 1])
    t = tf.from_matrix(m, name="thin")
    got, inv = mat(t)
    # Condition number ~1e6, so the product is exact to ~1e6 * 1e-16.
    np.testing.assert_allclose(got @ inv, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(inv, np.linalg.inv(m), rtol=1e-9, atol=1e-9)
    r = np.diag([-1.0, 1, 1, 1])
    r[:3, 3] = [4, 5, 6]
    got, inv = mat(tf.from_matrix(r))
    np.testing.assert_allclose(inv @ r, np.eye(4), atol=F64)
    assert np.linalg.det(got) < 0


@pytest.mark.parametrize("call", [
    lambda: tf.translate([math.nan, 0, 0]),
    lambda: tf.translate([0, math.inf, 0]),
    lambda: tf.scale(math.nan),
    lambda: tf.scale([1, -math.inf, 1]),
    lambda: tf.rotate([math.nan, 0, 1], 10),
    lambda: tf.rotate([0, 0, 1], math.nan),
    lambda: tf.rotate_z(math.inf),
    lambda: tf.look_at([0, 0, math.nan], [1, 1, 1], [0, 0, 1]),
    lambda: tf.look_at([0, 0, 0], [1, 1, 1], [0, math.inf, 1]),
], ids=["translate-nan", "translate-inf", "scale-nan", "scale-inf", "axis-nan", "angle-nan",
        "angle-inf", "look_at-origin-nan", "look_at-up-inf"])
def test_builders_reject_non_finite(call):
    with pytest.raises(TransformError, match="non-finite"):
        call()


@pytest.mark.parametrize("axis", ["w", "", [], ["x"], {"x": 1}, None, 0])
def test_reflect_rejects_anything_but_an_axis_name(axis):
    # (A list or dict axis once raised TypeError: unhashable, found by fuzzing.)
    with pytest.raises(TransformError, match="reflect: axis must be"):
        tf.reflect(axis)


def test_check_affine_matrix_refuses_what_float32_cannot_hold():
    """Past float32's range (a batch names the matrix); its edges still pass."""
    batch = np.tile(np.eye(4), (3, 1, 1))
    batch[2, 1, 1] = 1e-39
    with pytest.raises(TransformError, match=r"#2 does not fit in float32: its inverse's entries"):
        tf.check_affine_matrix(batch)
    with pytest.raises(TransformError, match="its entries reach 1e"):
        tf.check_affine_matrix(np.diag([1e39, 1e39, 1e39, 1.0]))
    tf.check_affine_matrix(np.diag([1e-38, 1e38, 1.0, 1.0]))


@pytest.mark.parametrize("build, words", [
    (lambda: tf.translate("abc"), "translate: expected numbers, got 'abc'"),
    (lambda: tf.translate(None), "translate: expected a number or 3 numbers, got None"),
    (lambda: tf.rotate([0, 0, 1], "30"), "rotate: expected numbers, got '30'"),
    (lambda: tf.rotate([0, 0, 1], True), "rotate: expected numbers, got True"),
    (lambda: tf.scale(1e-320), "its inverse is not finite"),
    (lambda: tf.translate([0, 0, 0]).apply_point([1, 2]), "a point or vector of 3 numbers, got [1, 2]")])
def test_builders_name_arguments_that_are_no_numbers(build, words):
    """(Raw TypeErrors, a string taken for its letters, and a scale whose inverse is
    infinite before.)"""
    with pytest.raises(TransformError) as err:
        build()
    assert words in str(err.value)


def test_builders_reject_singular_arguments():
    with pytest.raises(TransformError, match="factor 0"):
        tf.scale(0.0)
    with pytest.raises(TransformError, match="factor 0"):
        tf.scale([1.0, 0.0, 2.0])
    with pytest.raises(TransformError, match="zero-length axis"):
        tf.rotate([0.0, 0.0, 0.0], 45)
    with pytest.raises(TransformError, match="coincide"):
        tf.look_at([1, 2, 3], [1, 2, 3], [0, 1, 0])
    for up in ([0, 0, 2], [0, 0, -1], [0, 0, 0]):
        with pytest.raises(TransformError, match="parallel"):
            tf.look_at([1, 1, 0], [1, 1, 5], up)
    with pytest.raises(TransformError, match="3 components"):
        tf.translate([1, 2])


@pytest.mark.parametrize("size", [1e-200, 1e-160, 1e160, 1e300])
def test_rotate_axis_of_any_finite_length_is_the_unit_axis(size):
    """An axis whose squared length over- or underflows float64 turns as the unit axis
    (it once gave the identity, or raised as zero-length)."""
    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    unit = axis / np.linalg.norm(axis)
    expected = tf.rotate(unit.tolist(), 37.0).to_numpy()[0]
    np.testing.assert_allclose(tf.rotate((axis * size).tolist(), 37.0).to_numpy()[0], expected,
                               atol=1e-15)


def test_check_affine_matrix_batch_names_index():
    rng = np.random.default_rng(50)
    batch = np.tile(np.eye(4), (6, 1, 1))
    batch[:, :3, 3] = rng.uniform(-5, 5, (6, 3))
    tf.check_affine_matrix(batch, "forest")  # valid: no exception
    for k, fix, words in [(4, _zero_row, "singular"), (2, _nan, "non-finite"),
                          (5, _projective, "affine"), (0, _rank2, "singular")]:
        bad = batch.copy()
        m = bad[k]
        fix(m)
        with pytest.raises(TransformError, match=words) as err:
            tf.check_affine_matrix(bad, "forest")
        assert f"forest #{k}" in str(err.value)


def test_checked_affine_inverse_is_the_inverse_and_refuses_what_the_check_refuses():
    """The inverse of checked matrices equals affine_inverse's (the float64 NumPy reference
    of the linear part's inverse); a batch with a bad matrix raises the check's error."""
    rng = np.random.default_rng(51)
    batch = np.tile(np.eye(4), (6, 1, 1))
    batch[:, :3, :4] = rng.uniform(-2, 2, (6, 3, 4))
    batch[:, :3, :3] += 3 * np.eye(3)
    inverse = tf.checked_affine_inverse(batch, "forest")
    np.testing.assert_array_equal(inverse, tf.affine_inverse(batch))
    np.testing.assert_allclose(inverse @ batch, np.tile(np.eye(4), (6, 1, 1)), atol=1e-13)
    np.testing.assert_array_equal(tf.checked_affine_inverse(batch[2]), tf.affine_inverse(batch[2]))
    for k, fix, words in [(4, _zero_row, "singular"), (2, _nan, "non-finite"),
                          (5, _projective, "affine")]:
        bad = batch.copy()
        fix(bad[k])
        with pytest.raises(TransformError, match=words) as err:
            tf.checked_affine_inverse(bad, "forest")
        assert f"forest #{k}" in str(err.value)


def test_per_lane_from_matrix_names_bad_lane():
    batch = np.tile(np.eye(4), (4, 1, 1))
    batch[3, 2, :3] = 0
    with pytest.raises(TransformError, match="#3"):
        tf.from_matrix(tf.matrices_to_lanes(batch), name="lanes")


def test_transform_is_immutable():
    t = tf.translate([1.0, 2.0, 3.0])
    with pytest.raises(AttributeError):
        t.matrix = tf.identity().matrix


# --- quaternion rotations and decomposition (the optimisation parameters) -------------------

def np_quaternion_matrix(q):
    """Rotation matrix of the unit quaternion q / |q| (x, y, z, w), from its axis and angle."""
    q = np.asarray(q, np.float64) / np.linalg.norm(q)
    angle = 2 * math.atan2(np.linalg.norm(q[:3]), q[3])
    axis = q[:3] / max(np.linalg.norm(q[:3]), 1e-300)
    return np_rotate(axis, math.degrees(angle)) if angle else np.eye(4)


def test_rotate_quaternion_matches_axis_angle_and_normalizes():
    rng = np.random.default_rng(7)
    for q in rng.normal(size=(20, 4)):
        t = tf.rotate_quaternion(q * 3.0)  # not unit: the builder normalizes
        fwd, inv = t.to_numpy()
        np.testing.assert_allclose(fwd, np_quaternion_matrix(q), atol=F64)
        np.testing.assert_allclose(inv @ fwd, np.eye(4), atol=F64)
        lanes = tf.rotate_quaternion(Array4f(*q.tolist()))
        np.testing.assert_allclose(lanes.to_numpy()[0][0], fwd, atol=F32)


def test_rotate_quaternion_rejects_bad_input():
    with pytest.raises(TransformError, match="zero quaternion"):
        tf.rotate_quaternion([0, 0, 0, 0])
    with pytest.raises(TransformError, match="4 components"):
        tf.rotate_quaternion([1, 0, 0])
    with pytest.raises(TransformError, match="non-finite"):
        tf.rotate_quaternion([0, 0, float("nan"), 1])


def test_quaternion_from_rotation_inverts_the_builder():
    rng = np.random.default_rng(8)
    q = rng.normal(size=(200, 4))
    q[:50, :3] *= 1e-9  # near the identity
    q[50:100, 3] = 0.0  # half turns (w = 0): the trace is -1
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = np.stack([np_quaternion_matrix(x)[:3, :3] for x in q])
    back = tf.quaternion_from_rotation(r)
    # q and -q are the same rotation: compare up to sign.
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", back, q)), 1.0, atol=1e-12)


def test_decompose_recomposes_any_affine_matrix():
    """translate(t) @ rotate_quaternion(q) @ scale(s) @ H == M for random affine maps, incl.
    reflections (det < 0 -> negative z scale) and shear (H unit upper triangular)."""
    rng = np.random.default_rng(9)
    m = np.zeros((300, 4, 4))
    m[:, 3, 3] = 1.0
    m[:, :3, :3] = rng.normal(size=(300, 3, 3))
    m[:, :3, 3] = rng.normal(size=(300, 3)) * 10
    t, q, s, shear = tf.decompose(m)
    for i in range(len(m)):
        h = np.eye(4)
        h[:3, :3] = shear[i]
        composed = np_translate(t[i]) @ np_quaternion_matrix(q[i]) @ np.diag([*s[i], 1.0]) @ h
        np.testing.assert_allclose(composed, m[i], atol=1e-11 * np.abs(m[i]).max())
    np.testing.assert_allclose(np.tril(shear, -1), 0.0)
    np.testing.assert_allclose(np.diagonal(shear, axis1=1, axis2=2), 1.0)
    assert (s[:, :2] > 0).all()
    assert (np.sign(s[:, 2]) == np.sign(np.linalg.det(m[:, :3, :3]))).all()


def test_decompose_of_a_rotate_scale_chain_has_no_shear():
    chain = tf.translate([1, 2, 3]) @ tf.rotate([1, 1, 0], 40) @ tf.scale([2, 0.5, 3]) @ tf.reflect("z")
    t, q, s, shear = tf.decompose(chain.to_numpy()[0])
    np.testing.assert_allclose(t, [1, 2, 3], atol=F64)
    np.testing.assert_allclose(s, [2, 0.5, -3], atol=1e-12)
    np.testing.assert_allclose(shear, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np_quaternion_matrix(q), np_rotate([1, 1, 0], 40), atol=1e-12)


def test_quaternion_product_is_the_rotation_of_the_matrix_product():
    """R(a b) = R(a) R(b) for random quaternions, in NumPy and in Dr.Jit."""
    from instancing.core.backend import Array4f
    from instancing.core.transform import quaternion_product, quaternion_rows
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(2, 4))
    rows = lambda q: np.array(quaternion_rows(*q), np.float64)  # noqa: E731
    np.testing.assert_allclose(rows(quaternion_product(a, b)), rows(a) @ rows(b), atol=1e-12)
    jit = Array4f(*quaternion_product(Array4f(*map(float, a)), Array4f(*map(float, b))))
    np.testing.assert_allclose(np.array(jit).ravel(), quaternion_product(a, b), rtol=1e-5)


def _collapsing(sensitivity: float, rng) -> np.ndarray:
    """A random rotation times a linear part whose third row leans onto the first by the
    angle that gives its determinant ``sensitivity`` to rounding (within 1 %)."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lean = 2.0 / sensitivity
    for _ in range(4):
        linear = np.eye(3)
        linear[2] = [np.sqrt(1 - lean ** 2), 0.0, lean]
        linear = linear @ q
        lean *= tf.determinant_sensitivity(linear[None])[0] / sensitivity
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = rng.uniform(-3, 3, 3)
    return m


def test_float32_threshold_keeps_accepted_determinants_within_one_percent():
    """Just inside the threshold every matrix rounded to float32 keeps its determinant
    within 1 %; a hundred times beyond it rounding moves some by more than 5 %: the threshold
    is where float32 storage stops representing the matrix."""
    rng = np.random.default_rng(71)

    def det_change(m):
        return abs(np.linalg.det(m.astype(np.float32).astype(np.float64)[:3, :3])
                   / np.linalg.det(m[:3, :3]) - 1)

    inside = [_collapsing(0.98 * tf.MAX_DETERMINANT_SENSITIVITY, rng) for _ in range(2000)]
    for m in inside:
        tf.check_affine_matrix(m, "inside")
    assert max(det_change(m) for m in inside) < 0.01
    beyond = [_collapsing(100 * tf.MAX_DETERMINANT_SENSITIVITY, rng) for _ in range(2000)]
    assert max(det_change(m) for m in beyond) > 0.05
    with pytest.raises(TransformError, match="ill-conditioned"):
        tf.check_affine_matrix(beyond[0], "beyond")
    # Scaling rows and columns leaves the measure alone.
    scaled = np.diag([1e-4, 1.0, 1e3]) @ inside[0][:3, :3] @ np.diag([1e5, 1.0, 1e-2])
    np.testing.assert_allclose(tf.determinant_sensitivity(scaled[None]),
                               tf.determinant_sensitivity(inside[0][None, :3, :3]), rtol=1e-6)


def test_ill_conditioned_matrix_is_named_with_its_condition_number_never_singular():
    m = _collapsing(1e9, np.random.default_rng(72))
    with pytest.raises(TransformError) as err:
        tf.from_matrix(m, name="leaning")
    text = str(err.value)
    assert "leaning" in text and "ill-conditioned" in text and "singular" not in text
    cond = float(text.split("condition number ")[1].split(")")[0])
    np.testing.assert_allclose(cond, np.linalg.cond(m[:3, :3]), rtol=1e-2)
    batch = np.tile(np.eye(4), (5, 1, 1))
    batch[3] = m
    with pytest.raises(TransformError, match=r"#3 is ill-conditioned"):
        tf.check_affine_matrix(batch, "forest")


def test_condition_number_1e11_accepted_when_float32_holds_it_refused_when_not():
    """A rotated 1e-6 : 1 : 1e5 scale (condition number 1e11, as in pbrt's transformed-shape
    tests) survives float32 rounding and is accepted; the same scale turned first too mixes
    the thin axis into entries of size 1e5, where float32 loses it, and is refused."""
    needle = np_translate([1, -2, 3]) @ np_rotate([1, 2, 3], 40) @ np_scale([1e-6, 1.0, 1e5])
    assert np.linalg.cond(needle[:3, :3]) > 1e10
    got, inv = mat(tf.from_matrix(needle, name="needle"))
    expected = np.linalg.inv(needle)
    np.testing.assert_allclose(inv, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    mixed = needle @ np_rotate([-2, 1, 1], 25)
    rounded = mixed.astype(np.float32).astype(np.float64)
    assert abs(np.linalg.det(rounded[:3, :3]) / np.linalg.det(mixed[:3, :3]) - 1) > 1.0
    with pytest.raises(TransformError, match=r"mixed is ill-conditioned \(condition number 1e\+11"):
        tf.from_matrix(mixed, name="mixed")


def test_similarities_stored_in_float32_are_recognised_and_stretches_are_not():
    """is_similarity: rotations about random axes times uniform scales (and mirrors), rounded
    to float32 as scenes store them, are similarities; a stretch of 1e-4 or a shear is not."""
    rng = np.random.default_rng(2)
    for _ in range(50):
        axis, angle, size = rng.normal(size=3), rng.uniform(0, 360), rng.uniform(1e-3, 1e3)
        m = (tf.rotate(axis, angle) @ tf.scale(size)).to_numpy()[0]
        m[:3, 0] *= rng.choice([-1.0, 1.0])
        assert tf.is_similarity(m.astype(np.float32))
        stretched = m @ np.diag([1.0, 1.0 + 1e-4, 1.0, 1.0])
        assert not tf.is_similarity(stretched)
        sheared = m.copy()
        sheared[:3, 2] += 1e-4 * size * sheared[:3, 0] / np.linalg.norm(sheared[:3, 0])
        assert not tf.is_similarity(sheared)
