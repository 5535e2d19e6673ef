"""Tests of the float64 reference intersector (instancing/reference.py) itself.

These check the reference against closed forms, exact (Decimal) arithmetic,
internal consistency (mesh vs. analytic cube, affine invariance, the
inverse-transpose normal rule) and, when available, Mitsuba 3 (scalar_rgb,
float32) with loose tolerances.
"""

import math
import warnings
from decimal import Decimal, getcontext

import numpy as np
import pytest

from instancing.validation import reference as ref

ANALYTIC = ("sphere", "cube", "rectangle", "disk", "cylinder")


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def unit_cube_mesh():
    """[-1,1]^3 as 12 outward-wound triangles (two per face)."""
    v = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0)
                  for z in (-1.0, 1.0)])
    idx = {tuple(p): i for i, p in enumerate(v)}
    faces = []
    for axis in range(3):
        for s in (-1.0, 1.0):
            a, b = [k for k in range(3) if k != axis]
            quad = []
            for ua, ub in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = [0.0, 0.0, 0.0]
                p[axis], p[a], p[b] = s, ua, ub
                quad.append(idx[tuple(p)])
            tri = [(quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])]
            for f in tri:
                # Orient so that cross(v1 - v0, v2 - v0) points outward.
                nrm = np.cross(v[f[1]] - v[f[0]], v[f[2]] - v[f[0]])
                faces.append(f if nrm[axis] * s > 0 else (f[0], f[2], f[1]))
    return v, np.array(faces, dtype=np.int64)


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def affine(lin, trans):
    m = np.eye(4)
    m[:3, :3] = lin
    m[:3, 3] = trans
    return m


def random_affine(rng):
    """Rotation x shear x non-uniform scale + translation."""
    shear = np.eye(3)
    shear[0, 1], shear[0, 2], shear[1, 2] = rng.uniform(-0.6, 0.6, size=3)
    scale = np.diag(rng.uniform(0.3, 3.0, size=3))
    return affine(random_rotation(rng) @ shear @ scale, rng.uniform(-5, 5, 3))


def random_dirs(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def rays_towards_box(rng, n, extent=1.3, dist=6.0):
    """Rays from a sphere of radius `dist` aimed into [-extent, extent]^3,
    with directions of random (non-unit) length."""
    o = dist * random_dirs(rng, n)
    target = rng.uniform(-extent, extent, size=(n, 3))
    d = (target - o) * rng.uniform(0.2, 3.0, size=(n, 1))
    return o, d


def angle_deg(a, b):
    c = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def one(kind, o, d, mesh=None):
    t, n, prim = ref.intersect_object(kind, np.array([o], float), np.array([d], float), mesh)
    return t[0], n[0], prim[0]


# ---------------------------------------------------------------------------
# Closed forms
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("axis", range(3))
@pytest.mark.parametrize("sign", (-1.0, 1.0))
def test_sphere_axis_rays(axis, sign):
    rng = np.random.default_rng(10 + axis)
    for dist, scale in zip(rng.uniform(1.5, 50.0, 5), rng.uniform(0.1, 10.0, 5)):
        e = np.zeros(3)
        e[axis] = sign
        # From outside, towards the centre: t = (dist - 1) / |d|.
        t, n, prim = one("sphere", dist * e, -scale * e)
        assert t == pytest.approx((dist - 1.0) / scale, rel=1e-15)
        np.testing.assert_allclose(n, e, atol=1e-15)
        assert prim == 0
        # From the centre: t = 1 / |d|, normal along d (exit hit, outward).
        t, n, _ = one("sphere", np.zeros(3), scale * e)
        assert t == pytest.approx(1.0 / scale, rel=1e-15)
        np.testing.assert_allclose(n, e, atol=1e-15)
        # Pointing away from the sphere: miss.
        t, n, prim = one("sphere", dist * e, scale * e)
        assert t == np.inf and np.all(np.isnan(n)) and prim == -1


def test_sphere_tangent_rays():
    for h in (0.5, 0.9, 1 - 1e-6, 1 - 1e-10, 1 - 2**-40):
        # Offset h from the axis: half chord sqrt(1 - h^2) = sqrt((1-h)(1+h)).
        # Near tangency 1 - h^2 is formed from a rounded h^2, so allow a few
        # ulps of the origin's scale (still ~1e-15 relative).
        t, n, _ = one("sphere", (h, 0.0, -5.0), (0.0, 0.0, 1.0))
        half = math.sqrt((1 - h) * (1 + h))
        assert t == pytest.approx(5.0 - half, rel=4e-15)
        assert np.linalg.norm(n) == pytest.approx(1.0, rel=1e-15)
    # Just outside the silhouette: miss; exactly on it: (double) hit.
    assert one("sphere", (1 + 1e-12, 0.0, -5.0), (0.0, 0.0, 1.0))[0] == np.inf
    t, n, _ = one("sphere", (1.0, 0.0, -5.0), (0.0, 0.0, 1.0))
    assert t == 5.0
    np.testing.assert_allclose(n, (1.0, 0.0, 0.0), atol=1e-15)


def _decimal_sphere_t(o, d, dims=3):
    """Nearest positive root of |o + t d|^2 = 1 in 60-digit arithmetic."""
    getcontext().prec = 60
    O = [Decimal(float(x)) for x in o[:dims]]
    D = [Decimal(float(x)) for x in d[:dims]]
    a = sum(x * x for x in D)
    b = sum(x * y for x, y in zip(O, D))
    c = sum(x * x for x in O) - 1
    disc = b * b - a * c
    if a == 0 or disc < 0:
        return []
    s = disc.sqrt()
    return sorted([(-b - s) / a, (-b + s) / a])


def test_sphere_and_cylinder_match_exact_arithmetic():
    """Far-away origins stress the cancellation in the naive quadratic."""
    rng = np.random.default_rng(1)
    n = 300
    dist = 10.0 ** rng.uniform(0.5, 5.0, n)
    o = dist[:, None] * random_dirs(rng, n)
    target = rng.uniform(-0.9, 0.9, size=(n, 3))
    d = (target - o) * 10.0 ** rng.uniform(-3, 3, (n, 1))
    # Some rays from inside too.
    o[:50] = rng.uniform(-0.5, 0.5, (50, 3))
    o[:50, 2] += 0.5
    for kind, dims in (("sphere", 3), ("cylinder", 2)):
        t, _, _ = ref.intersect_object(kind, o, d)
        checked = 0
        for i in range(n):
            roots = _decimal_sphere_t(o[i], d[i], dims)
            if kind == "cylinder":
                roots = [r for r in roots
                         if 0 <= Decimal(float(o[i, 2])) + r * Decimal(float(d[i, 2])) <= 1]
            roots = [r for r in roots if r > 0]
            if not roots:
                assert t[i] == np.inf
                continue
            exact = float(roots[0])
            # A few ulps of t, or of the origin's magnitude for hits very
            # close to the origin (|o|^2 - 1 is rounded once in float64).
            scale = abs(exact) + np.linalg.norm(o[i]) / np.linalg.norm(d[i])
            assert abs(t[i] - exact) <= 4e-16 * scale, (kind, i, t[i], exact)
            checked += 1
        assert checked > 100


def test_cylinder_closed_forms():
    # From inside, horizontally: exit at x = sqrt(1 - y^2), outward normal.
    t, n, _ = one("cylinder", (0.2, 0.1, 0.5), (2.0, 0.0, 0.0))
    x = math.sqrt(1 - 0.01)
    assert t == pytest.approx((x - 0.2) / 2.0, rel=1e-15)
    np.testing.assert_allclose(n, (x, 0.1, 0.0), atol=1e-15)
    # From outside: entering hit on the near side, normal facing the ray.
    t, n, _ = one("cylinder", (-3.0, 0.0, 0.5), (1.0, 0.0, 0.0))
    assert t == 2.0
    np.testing.assert_allclose(n, (-1.0, 0.0, 0.0), atol=0)
    # Near hit below z = 0, far hit inside the z range: hit the inner wall,
    # normal still outward (x, y, 0) -- not flipped toward the ray.
    t, n, _ = one("cylinder", (-3.0, 0.0, -0.25), (1.0, 0.0, 0.1))
    assert t == pytest.approx(4.0, rel=1e-15)
    np.testing.assert_allclose(n, (1.0, 0.0, 0.0), atol=1e-15)
    # Both candidate hits outside the z range: miss (no caps).
    assert one("cylinder", (-3.0, 0.0, 1.5), (1.0, 0.0, 0.0))[0] == np.inf
    # Along the axis (inside or outside): miss.
    assert one("cylinder", (0.3, 0.0, -1.0), (0.0, 0.0, 1.0))[0] == np.inf
    assert one("cylinder", (3.0, 0.0, -1.0), (0.0, 0.0, 1.0))[0] == np.inf
    # z-range bounds are inclusive.
    assert one("cylinder", (-3.0, 0.0, 0.0), (1.0, 0.0, 0.0))[0] == 2.0
    assert one("cylinder", (-3.0, 0.0, 1.0), (1.0, 0.0, 0.0))[0] == 2.0
    assert one("cylinder", (-3.0, 0.0, 1.0 + 1e-15), (1.0, 0.0, 0.0))[0] == np.inf


@pytest.mark.parametrize("kind", ("rectangle", "disk"))
def test_planar_shapes(kind):
    ez = np.array([0.0, 0.0, 1.0])
    # From above and from below: same t, normal +z in both cases.
    for oz, dz in ((2.0, -0.5), (-2.0, 0.5), (-2.0, 4.0)):
        t, n, prim = one(kind, (0.3, -0.4, oz), (0.0, 0.0, dz))
        assert t == abs(oz / dz) and prim == 0
        np.testing.assert_array_equal(n, ez)
    # Oblique ray.
    t, n, _ = one(kind, (0.0, 0.0, 1.0), (0.25, 0.25, -1.0))
    assert t == 1.0
    # Edges are inclusive; a hair outside misses.
    edge = (1.0, 0.0)
    assert one(kind, (*edge, 1.0), (0.0, 0.0, -1.0))[0] == 1.0
    assert one(kind, (0.0, -1.0, 1.0), (0.0, 0.0, -1.0))[0] == 1.0
    assert one(kind, (1.0 + 1e-15, 0.0, 1.0), (0.0, 0.0, -1.0))[0] == np.inf
    if kind == "rectangle":
        assert one(kind, (1.0, -1.0, 1.0), (0.0, 0.0, -1.0))[0] == 1.0
        assert one(kind, (0.99, 0.99, 1.0), (0.0, 0.0, -1.0))[0] == 1.0
    else:
        assert one(kind, (0.8, 0.8, 1.0), (0.0, 0.0, -1.0))[0] == np.inf
        assert one(kind, (0.7, 0.7, 1.0), (0.0, 0.0, -1.0))[0] == 1.0
    # Parallel rays miss, including rays lying in the plane.
    assert one(kind, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))[0] == np.inf
    assert one(kind, (-3.0, 0.0, 0.0), (1.0, 0.0, 0.0))[0] == np.inf
    # Starting on the plane: t = 0 is not a hit.
    assert one(kind, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))[0] == np.inf
    # Plane behind the origin: miss.
    assert one(kind, (0.0, 0.0, 1.0), (0.0, 0.0, 1.0))[0] == np.inf


def test_cube_closed_forms():
    rng = np.random.default_rng(3)
    o = rng.uniform(-0.99, 0.99, (200, 3))
    for axis in range(3):
        for s in (-1.0, 1.0):
            e = np.zeros(3)
            e[axis] = s
            scale = rng.uniform(0.1, 10.0)
            # From inside: exit face along d, t = (1 - s o_axis) / |d|.
            t, n, prim = ref.intersect_object("cube", o, np.tile(scale * e, (200, 1)))
            np.testing.assert_allclose(t, (1 - s * o[:, axis]) / scale, rtol=1e-15)
            np.testing.assert_array_equal(n, np.tile(e, (200, 1)))
            assert np.all(prim == 0)
            # From outside: entering face opposes d.
            oo = o.copy()
            oo[:, axis] = -3.0 * s
            t, n, _ = ref.intersect_object("cube", oo, np.tile(scale * e, (200, 1)))
            np.testing.assert_allclose(t, 2.0 / scale, rtol=1e-15)
            np.testing.assert_array_equal(n, np.tile(-e, (200, 1)))
    # Random rays from inside: exit point on the boundary, normal = its face.
    d = rng.normal(size=(200, 3))
    t, n, _ = ref.intersect_object("cube", o, d)
    p = o + t[:, None] * d
    assert np.all(np.isfinite(t)) and np.all(t > 0)
    np.testing.assert_allclose(np.max(np.abs(p), axis=1), 1.0, rtol=1e-15)
    ax = np.argmax(np.abs(n), axis=1)
    np.testing.assert_allclose(np.abs(p[np.arange(200), ax]), 1.0, rtol=1e-15)
    assert np.all(np.sum(n * d, axis=1) > 0)
    # Edge/corner ties resolve deterministically to one of the touching faces.
    t, n, _ = one("cube", (-3.0, -3.0, 0.0), (1.0, 1.0, 0.0))
    assert t == 2.0 and (n[0] == -1.0 or n[1] == -1.0) and np.sum(np.abs(n)) == 1
    # Parallel to a slab and outside it: miss; inside it: hit.
    assert one("cube", (-3.0, 1.5, 0.0), (1.0, 0.0, 0.0))[0] == np.inf
    assert one("cube", (-3.0, 1.0, 0.0), (1.0, 0.0, 0.0))[0] == 2.0
    # Pointing away: miss.
    assert one("cube", (-3.0, 0.0, 0.0), (-1.0, 0.0, 0.0))[0] == np.inf


def test_mesh_single_triangle():
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2]])
    # Normal = normalize(cross(v1 - v0, v2 - v0)) = +z, from either side.
    for oz, dz in ((1.0, -1.0), (-1.0, 2.0)):
        t, n, prim = one("mesh", (0.2, 0.3, oz), (0.0, 0.0, dz), (v, f))
        assert t == abs(oz / dz) and prim == 0
        np.testing.assert_array_equal(n, (0.0, 0.0, 1.0))
    # Reversed winding flips the normal.
    _, n, _ = one("mesh", (0.2, 0.3, 1.0), (0.0, 0.0, -1.0), (v, f[:, ::-1]))
    np.testing.assert_array_equal(n, (0.0, 0.0, -1.0))
    # Inclusive barycentric bounds: vertices and edges hit, beyond misses.
    for x, y in ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.5, 0.5), (0.5, 0.0)):
        assert one("mesh", (x, y, 1.0), (0.0, 0.0, -1.0), (v, f))[0] == 1.0
    assert one("mesh", (0.5, 0.5 + 1e-15, 1.0), (0.0, 0.0, -1.0), (v, f))[0] == np.inf
    assert one("mesh", (-1e-300, 0.2, 1.0), (0.0, 0.0, -1.0), (v, f))[0] == np.inf
    # Parallel ray, ray starting on the triangle, degenerate triangle: miss.
    assert one("mesh", (0.2, 0.2, 0.0), (1.0, 0.0, 0.0), (v, f))[0] == np.inf
    assert one("mesh", (0.2, 0.2, 0.0), (0.0, 0.0, 1.0), (v, f))[0] == np.inf
    vd = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert one("mesh", (0.5, 0.0, 1.0), (0.0, 0.0, -1.0), (vd, f))[0] == np.inf


def test_mesh_prim_is_nearest_triangle_index():
    # Three stacked triangles at z = 0, 1, 2 listed out of order.
    base = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]])
    zs = (2.0, 0.0, 1.0)
    v = np.concatenate([base + (0.0, 0.0, z) for z in zs])
    f = np.arange(9).reshape(3, 3)
    t, _, prim = one("mesh", (0.1, 0.1, -1.0), (0.0, 0.0, 1.0), (v, f))
    assert t == 1.0 and prim == 1
    t, _, prim = one("mesh", (0.1, 0.1, 5.0), (0.0, 0.0, -1.0), (v, f))
    assert t == 3.0 and prim == 0
    t, _, prim = one("mesh", (0.1, 0.1, 0.5), (0.0, 0.0, 1.0), (v, f))
    assert t == 0.5 and prim == 2


# ---------------------------------------------------------------------------
# Internal consistency
# ---------------------------------------------------------------------------

def test_mesh_cube_agrees_with_analytic_cube(monkeypatch):
    rng = np.random.default_rng(4)
    mesh = unit_cube_mesh()
    o, d = rays_towards_box(rng, 2000, extent=1.2, dist=5.0)
    o[:300] = rng.uniform(-0.95, 0.95, (300, 3))          # inside rays
    t_c, n_c, _ = ref.intersect_object("cube", o, d)
    t_m, n_m, prim = ref.intersect_object("mesh", o, d, mesh)
    hit = np.isfinite(t_c)
    assert 900 < hit.sum() < 2000
    np.testing.assert_array_equal(hit, np.isfinite(t_m))
    np.testing.assert_allclose(t_m[hit], t_c[hit], rtol=1e-13)
    # Normals agree away from edges (where the face choice is a tie).
    p = o + np.where(hit, t_c, 0)[:, None] * d
    off_edge = hit & (np.sort(np.abs(p), axis=1)[:, 1] < 1 - 1e-9)
    np.testing.assert_allclose(n_m[off_edge], n_c[off_edge], atol=1e-15)
    # Each prim belongs to the face the normal says (2 triangles per face).
    v, f = mesh
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    np.testing.assert_allclose(face_n[prim[hit]], n_m[hit], atol=1e-15)
    assert np.all(prim[~hit] == -1)
    # Chunking over triangles does not change anything.
    monkeypatch.setattr(ref, "_MESH_BLOCK_ELEMS", 3 * len(o))
    t_b, n_b, prim_b = ref.intersect_object("mesh", o, d, mesh)
    np.testing.assert_array_equal(t_b, t_m)
    np.testing.assert_array_equal(prim_b, prim)
    np.testing.assert_array_equal(n_b[hit], n_m[hit])


def test_mesh_matches_exact_arithmetic():
    rng = np.random.default_rng(5)
    v = rng.uniform(-1, 1, (60, 3))
    f = rng.integers(0, 60, (20, 3))
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    o, d = rays_towards_box(rng, 400, extent=0.8, dist=3.0)
    t, n, prim = ref.intersect_object("mesh", o, d, (v, f))
    hit = np.isfinite(t)
    assert hit.sum() > 50
    getcontext().prec = 60
    for i in np.flatnonzero(hit):
        v0, v1, v2 = (v[j] for j in f[prim[i]])
        D = lambda a: [Decimal(float(x)) for x in a]   # noqa: E731
        e1 = [b - a for a, b in zip(D(v0), D(v1))]
        e2 = [b - a for a, b in zip(D(v0), D(v2))]
        nn = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
              e1[0] * e2[1] - e1[1] * e2[0]]
        num = sum(a * (b - c) for a, b, c in zip(nn, D(v0), D(o[i])))
        den = sum(a * b for a, b in zip(nn, D(d[i])))
        exact = float(num / den)
        # Well-conditioned hits are accurate to a few ulps.
        cosang = abs(float(den)) / (np.linalg.norm(d[i]) * float(sum(x * x for x in nn).sqrt()))
        if cosang > 0.05:
            assert abs(t[i] - exact) <= 1e-14 * abs(exact)


@pytest.mark.parametrize("kind", ANALYTIC + ("mesh",))
def test_direction_scale_divides_t(kind):
    rng = np.random.default_rng(6)
    mesh = unit_cube_mesh() if kind == "mesh" else None
    o, d = rays_towards_box(rng, 300)
    t1, n1, _ = ref.intersect_object(kind, o, d, mesh)
    for s in (0.125, 3.0, 1e-3, 1e4):   # powers of two are exact; others ~ulp
        ts, ns, _ = ref.intersect_object(kind, o, s * d, mesh)
        np.testing.assert_array_equal(np.isfinite(ts), np.isfinite(t1))
        hit = np.isfinite(t1)
        np.testing.assert_allclose(ts[hit] * s, t1[hit], rtol=1e-14)
        np.testing.assert_allclose(ns[hit], n1[hit], atol=1e-12)


@pytest.mark.parametrize("kind", ANALYTIC + ("mesh",))
def test_affine_invariance(kind):
    """Intersecting an instance with to_world M == intersecting the canonical
    shape with the inverse-transformed ray (same t, p mapped by M)."""
    rng = np.random.default_rng(7)
    mesh = unit_cube_mesh() if kind == "mesh" else None
    for _ in range(4):
        m = random_affine(rng)
        o_w, d_w = rays_towards_box(rng, 400, dist=30.0)
        o_w = o_w + m[:3, 3]
        inv = np.linalg.inv(m)
        o_obj = (inv @ np.c_[o_w, np.ones(len(o_w))].T).T[:, :3]
        d_obj = (inv @ np.c_[d_w, np.zeros(len(d_w))].T).T[:, :3]
        t_obj, n_obj, prim_obj = ref.intersect_object(kind, o_obj, d_obj, mesh)
        res = ref.intersect_instances([{"kind": kind, "to_world": m, "mesh": mesh}], o_w, d_w)
        hit = np.isfinite(t_obj)
        np.testing.assert_array_equal(np.isfinite(res["t"]), hit)
        np.testing.assert_allclose(res["t"][hit], t_obj[hit], rtol=1e-12)
        np.testing.assert_array_equal(res["instance"], np.where(hit, 0, -1))
        np.testing.assert_array_equal(res["prim"], prim_obj)
        p_obj = o_obj + np.where(hit, t_obj, 0)[:, None] * d_obj
        p_w = (m[:3, :3] @ p_obj.T).T + m[:3, 3]
        np.testing.assert_allclose(res["p"][hit], p_w[hit], rtol=1e-10, atol=1e-10)
        assert np.all(np.isnan(res["p"][~hit])) and np.all(np.isnan(res["n"][~hit]))
        np.testing.assert_allclose(np.linalg.norm(res["n"][hit], axis=1), 1.0, rtol=1e-14)
        # The object-space ray from transform_rays is what we computed above.
        o2, d2, _ = ref.transform_rays(m, o_w, d_w)
        np.testing.assert_allclose(o2, o_obj, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(d2, d_obj, rtol=1e-12, atol=1e-12)


def test_inverse_transpose_normal_is_orthogonal_to_surface():
    """Sphere under non-uniform scale + shear: nearby surface points lie in
    the tangent plane of the world normal to first order."""
    rng = np.random.default_rng(8)
    lin = random_rotation(rng) @ np.array([[1.0, 0.7, -0.4], [0.0, 2.5, 0.9],
                                           [0.0, 0.0, 0.4]])
    m = affine(lin, (1.0, -2.0, 0.5))
    inst = [{"kind": "sphere", "to_world": m, "mesh": None}]
    o, d = rays_towards_box(rng, 300, extent=0.9, dist=20.0)
    o = (lin @ (o / 4).T).T + m[:3, 3]
    d = (lin @ d.T).T
    res = ref.intersect_instances(inst, o, d)
    hit = np.isfinite(res["t"])
    assert hit.sum() > 200
    inv = np.linalg.inv(m)
    eps = 1e-5
    worst_it, worst_naive = 0.0, 0.0
    for i in np.flatnonzero(hit):
        q = inv[:3, :3] @ res["p"][i] + inv[:3, 3]                # object hit
        q /= np.linalg.norm(q)
        t1 = np.cross(q, random_dirs(rng, 1)[0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(q, t1)
        naive = lin @ q
        naive /= np.linalg.norm(naive)
        for tan in (t1, t2, (t1 + t2) / math.sqrt(2)):
            q2 = q + eps * tan
            q2 /= np.linalg.norm(q2)                               # on the sphere
            delta = lin @ (q2 - q)                                 # world chord
            cos = abs(delta @ res["n"][i]) / np.linalg.norm(delta)
            worst_it = max(worst_it, cos)
            worst_naive = max(worst_naive, abs(delta @ naive) / np.linalg.norm(delta))
    assert worst_it < 100 * eps        # O(eps): chord is tangent to first order
    assert worst_naive > 0.1           # forward-transformed normal is wrong


def test_nearest_instance_wins_and_ties_are_deterministic():
    s = affine(np.eye(3), (0.0, 0.0, 0.0))
    far = affine(np.eye(3) * 0.5, (0.0, 0.0, 5.0))
    cube_mesh = unit_cube_mesh()
    insts = [
        {"kind": "sphere", "to_world": far, "mesh": None},
        {"kind": "cube", "to_world": s, "mesh": None},
        {"kind": "mesh", "to_world": s, "mesh": cube_mesh},       # same t as cube
        {"kind": "disk", "to_world": affine(np.eye(3), (0.0, 0.0, -10.0)), "mesh": None},
    ]
    o = np.array([[0.0, 0.0, 10.0], [0.1, 0.2, -20.0], [5.0, 5.0, 5.0],
                  [0.1, 0.2, 0.0], [0.3, 0.1, -5.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0],
                  [0.0, 0.0, 1.0], [0.0, 0.0, -2.0]])
    res = ref.intersect_instances(insts, o, d)
    np.testing.assert_array_equal(res["instance"], [0, 3, -1, 1, 3])
    np.testing.assert_allclose(res["t"], [4.5, 10.0, np.inf, 1.0, 2.5])
    np.testing.assert_array_equal(res["prim"], [0, 0, -1, 0, 0])
    np.testing.assert_allclose(res["n"][[0, 1, 3, 4]],
                               [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1]])
    assert res["t"].dtype == np.float64 and res["instance"].dtype == np.int64
    assert res["prim"].dtype == np.int64 and res["p"].shape == (5, 3)


@pytest.mark.parametrize("kind", ANALYTIC + ("mesh",))
def test_degenerate_directions_no_warnings(kind):
    mesh = unit_cube_mesh() if kind == "mesh" else None
    o = np.array([[0.5, 0.5, 3.0], [0.5, 0.5, -3.0], [0.0, 0.0, 0.5], [3.0, 0.5, 0.5],
                  [0.2, 0.3, 0.4], [0.2, 0.3, 0.4], [1.0, 1.0, 1.0], [-3.0, 0.0, 0.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0], [0.0, 1e-100, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t, n, prim = ref.intersect_object(kind, o, d, mesh)
        res = ref.intersect_instances([{"kind": kind, "to_world": np.eye(4), "mesh": mesh}], o, d)
    # Zero direction: always a miss.
    assert t[4] == np.inf and prim[4] == -1 and res["instance"][4] == -1
    hit = np.isfinite(t)
    assert np.all(t[hit] > 0) and np.all(np.isfinite(n[hit]))
    assert np.all(np.isnan(n[~hit]))
    np.testing.assert_array_equal(res["t"], t)
    # Axis-aligned rays give the exact closed-form answers.
    expected = {"sphere": [3 - math.sqrt(0.5), 3 - math.sqrt(0.5), 0.5, 3 - math.sqrt(0.5)],
                "cube": [2.0, 2.0, 0.5, 2.0], "mesh": [2.0, 2.0, 0.5, 2.0],
                "rectangle": [3.0, 3.0, np.inf, np.inf], "disk": [3.0, 3.0, np.inf, np.inf],
                "cylinder": [np.inf, np.inf, np.inf, 3.0 - math.sqrt(0.75)]}[kind]
    np.testing.assert_allclose(t[:4], expected, rtol=1e-15)
    # Tiny-but-nonzero direction: t scales up accordingly for closed shapes.
    if kind in ("sphere", "cube", "mesh", "cylinder"):
        assert np.isfinite(t[5]) and t[5] > 1e99


def test_input_validation():
    with pytest.raises(ValueError):
        ref.intersect_object("torus", np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(ValueError):
        ref.intersect_object("mesh", np.zeros((1, 3)), np.ones((1, 3)))
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(ValueError):
        ref.intersect_instances([{"kind": "sphere", "to_world": bad, "mesh": None}],
                                np.zeros((1, 3)), np.ones((1, 3)))
    # Empty ray batches and empty scenes.
    t, n, prim = ref.intersect_object("sphere", np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == (0,) and n.shape == (0, 3) and prim.shape == (0,)
    res = ref.intersect_instances([], np.zeros((2, 3)), np.ones((2, 3)))
    assert np.all(res["t"] == np.inf) and np.all(res["instance"] == -1)


# ---------------------------------------------------------------------------
# Mitsuba 3 agreement (float32, scalar_rgb)
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    prev = mitsuba.variant()
    try:
        mitsuba.set_variant("scalar_rgb")
    except (AttributeError, ImportError):
        pytest.skip("mitsuba scalar_rgb variant unavailable")
    yield mitsuba
    if prev is not None and prev != "scalar_rgb":
        mitsuba.set_variant(prev)


def mitsuba_transforms(kind, rng):
    """Transforms Mitsuba accepts without warnings for each shape."""
    out = []
    for _ in range(3):
        rot = random_rotation(rng)
        trans = rng.uniform(-3, 3, 3)
        if kind == "sphere":            # uniform scale + rotation + translation
            lin = rot * rng.uniform(0.3, 3.0)
        elif kind == "cylinder":        # same radius in x and y, any length
            r, h = rng.uniform(0.3, 3.0, 2)
            lin = rot @ np.diag([r, r, h])
        else:                           # general affine (incl. shear)
            lin = random_affine(rng)[:3, :3]
        out.append(affine(lin, trans))
    return out


def mitsuba_hits(mi, kind, m, o, d):
    scene = mi.load_dict({"type": "scene",
                          "a": {"type": kind, "to_world": mi.ScalarTransform4f(m.tolist())}})
    t = np.full(len(o), np.inf)
    n = np.full((len(o), 3), np.nan)
    for i in range(len(o)):
        si = scene.ray_intersect(mi.Ray3f(o[i].tolist(), d[i].tolist()))
        if si.is_valid():
            t[i] = si.t
            n[i] = np.array(si.n)
    return t, n


def stable_under_jitter(inst, o, d, res, rel=1e-4):
    """Rays whose reference outcome (hit/miss, face, t) is insensitive to a
    small perturbation of the origin; the others are grazing/edge cases."""
    scale = np.linalg.norm(d, axis=1, keepdims=True) * np.maximum(res["t"], 1.0)[:, None]
    scale = np.where(np.isfinite(scale), scale, np.linalg.norm(o, axis=1, keepdims=True))
    ok = np.ones(len(o), bool)
    for k in range(3):
        for s in (-1.0, 1.0):
            e = np.zeros(3)
            e[k] = s * rel
            r = ref.intersect_instances(inst, o + e * scale, d)
            same_hit = np.isfinite(r["t"]) == np.isfinite(res["t"])
            with np.errstate(invalid="ignore"):
                close_t = ~np.isfinite(res["t"]) | (np.abs(r["t"] - res["t"]) < 1e-2 * res["t"])
                close_n = ~np.isfinite(res["t"]) | (np.sum(r["n"] * res["n"], axis=1) > 0.999)
            ok &= same_hit & close_t & close_n
    return ok


@pytest.mark.parametrize("kind", ANALYTIC)
def test_agrees_with_mitsuba(mi, kind):
    rng = np.random.default_rng(100 + ANALYTIC.index(kind))
    for m in mitsuba_transforms(kind, rng):
        n_rays = 200
        o_obj, d_obj = rays_towards_box(rng, n_rays, extent=1.3, dist=4.0)
        if kind in ("sphere", "cube", "cylinder"):           # some from inside
            o_obj[:40] = rng.uniform(-0.8, 0.8, (40, 3))
            if kind == "cylinder":
                o_obj[:40, 2] = rng.uniform(0.1, 0.9, 40)
        o = (m[:3, :3] @ o_obj.T).T + m[:3, 3]
        d = (m[:3, :3] @ d_obj.T).T
        inst = [{"kind": kind, "to_world": m, "mesh": None}]
        res = ref.intersect_instances(inst, o, d)
        t_mi, n_mi = mitsuba_hits(mi, kind, m, o, d)
        stable = stable_under_jitter(inst, o, d, res)
        assert stable.mean() > 0.9
        hit = np.isfinite(res["t"])
        assert (hit & stable).sum() > 40
        # Hit/miss agreement on every non-grazing ray.
        np.testing.assert_array_equal(np.isfinite(t_mi)[stable], hit[stable])
        both = stable & hit
        # t in units of d (Mitsuba does not normalise Ray3f.d).
        np.testing.assert_allclose(t_mi[both], res["t"][both], rtol=1e-4)
        # Same normal convention (no flipping toward the ray), within 0.1 deg.
        ang = angle_deg(n_mi[both], res["n"][both])
        assert np.all(ang < 0.1), (kind, ang.max())


def test_mitsuba_t_is_in_units_of_d(mi):
    scene = mi.load_dict({"type": "scene", "a": {"type": "sphere"}})
    si = scene.ray_intersect(mi.Ray3f([0.0, 0.0, -3.0], [0.0, 0.0, 4.0]))
    assert si.t == pytest.approx(0.5, rel=1e-6)
    assert one("sphere", (0.0, 0.0, -3.0), (0.0, 0.0, 4.0))[0] == 0.5


@pytest.mark.parametrize("kind,o,d", [
    ("sphere", (0.1, 0.2, 0.3), (0.0, 0.0, 1.0)),          # from inside
    ("cylinder", (0.1, 0.2, 0.5), (1.0, 0.0, 0.0)),        # from inside
    ("cube", (0.1, 0.2, 0.3), (0.0, 0.0, 1.0)),            # from inside
    ("rectangle", (0.1, 0.2, -1.0), (0.0, 0.0, 1.0)),      # from below
    ("disk", (0.1, 0.2, -1.0), (0.0, 0.0, 1.0)),           # from below
    ("rectangle", (0.1, 0.2, 1.0), (0.0, 0.0, -1.0)),      # from above
])
def test_mitsuba_normal_conventions(mi, kind, o, d):
    """si.n is the geometric normal, never flipped toward the ray."""
    scene = mi.load_dict({"type": "scene", "a": {"type": kind}})
    si = scene.ray_intersect(mi.Ray3f(list(o), list(d)))
    t, n, _ = one(kind, o, d)
    assert si.is_valid()
    assert si.t == pytest.approx(t, rel=1e-6)
    np.testing.assert_allclose(np.array(si.n), n, atol=1e-6)
