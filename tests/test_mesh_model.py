"""The triangle-mesh model (instancing/models/mesh.py): watertight traversal test.

Rays aimed at the shared edges and vertices of a closed mesh are where a
per-triangle test (Moller-Trumbore in float32) lets rays slip between two
triangles: on the 20 000 rays of each case below, the previous float32
Moller-Trumbore test missed / passed through the first surface on 222 / 3 014
(identity instance), 81 / 1 158 (sheared, reflected) and 0 / 35 (the same
300 units away) on the icosphere. The watertight test must hit the first surface on every
one, also where the BVH holds a triangle as several split references (a sphere of slivers).
"""

from __future__ import annotations


import numpy as np
import pytest

import instancing
from instancing.validation.stress import MESH_FILE as STRESS_MESH
from instancing.validation import reference
from instancing.core.backend import Float
from instancing.io.mesh_file import read_mesh
from instancing.models.mesh import difference_of_products
from scene_helpers import float32_exact, sliver_sphere

#: A closed convex mesh (320 triangles): its first hit has a reference without edge tests.
ICOSPHERE = STRESS_MESH
#: The stress suite's "shear + reflection" linear part (det < 0).
SHEAR_REFLECTION = np.array([[-1.0, 0.9, 0.5], [0.0, 1.2, -0.8], [0.0, 0.0, 0.7]])


def affine(linear, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = translation
    return m


def rays_at_edges_and_vertices(rng, vertices, faces, m, count):
    """float32 world rays from outside aimed at points of the mesh's edges (a tenth at
    vertices): target ``v_a + s (v_b - v_a)`` in object space rounded to float32, origin
    0.5..4 away within 60 degrees of the outward radial direction, so that the target
    is on the front of the convex mesh and the first hit is at t ~ 1."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    k = rng.integers(0, len(edges), count)
    s = rng.uniform(0.0, 1.0, count)
    s[: count // 10] = 0.0
    a, b = vertices[edges[k, 0]], vertices[edges[k, 1]]
    target = float32_exact(a + s[:, None] * (b - a))
    radial = target / np.linalg.norm(target, axis=1, keepdims=True)
    w = rng.normal(size=(count, 3))
    w = radial + 1.5 * w / np.linalg.norm(w, axis=1, keepdims=True)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    w = np.where((np.sum(w * radial, axis=1) > 0.5)[:, None], w, radial)
    origin = target + rng.uniform(0.5, 4.0, (count, 1)) * w
    # To world space with the stored (float32) transform; rays rounded to float32.
    lin, tr = m[:3, :3], m[:3, 3]
    o = float32_exact(origin @ lin.T + tr)
    d = float32_exact(float32_exact(target @ lin.T + tr) - o)
    return o, d


def convex_first_hit(vertices, faces, m, o, d) -> np.ndarray:
    """First hit on a closed convex mesh in float64 with no edge tests: Cyrus-Beck
    clipping of the object-space ray against every face plane (entering t), inf on a miss.

    The float64 Moller-Trumbore reference (:mod:`instancing.validation.reference`) is itself not
    watertight: on rays through exact float32 vertices it slips through a few times
    in ten thousand (checked below), so it cannot judge these rays alone.
    """
    inv = np.linalg.inv(m)
    o = o @ inv[:3, :3].T + inv[:3, 3]
    d = d @ inv[:3, :3].T
    p0 = vertices[faces[:, 0]]
    n = np.cross(vertices[faces[:, 1]] - p0, vertices[faces[:, 2]] - p0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    offset = np.sum(n * p0, axis=1)
    t_in, t_out = np.empty(len(o)), np.empty(len(o))
    # Rays a thousand at a time, so that the (ray, face) tables stay within cache.
    with np.errstate(divide="ignore", invalid="ignore"):
        for s in range(0, len(o), 1024):
            rows = slice(s, s + 1024)
            dn = d[rows] @ n.T
            t = (offset - o[rows] @ n.T) / dn
            t_in[rows] = np.max(np.where(dn < 0, t, -np.inf), axis=1)
            t_out[rows] = np.min(np.where(dn > 0, t, np.inf), axis=1)
    return np.where((t_in <= t_out * (1 + 1e-9)) & (t_in > 0), t_in, np.inf)


@pytest.mark.parametrize("mesh_name", ["icosphere", "sphere of slivers"])
@pytest.mark.parametrize("name, m", [
    ("identity", affine(np.eye(3), [0.0, 0.0, 0.0])),
    ("shear + reflection", affine(SHEAR_REFLECTION, [2.0, -1.0, 3.0])),
    ("far shear + reflection", affine(SHEAR_REFLECTION, [200.0, -100.0, 300.0]))])
def test_rays_through_shared_edges_and_vertices_hit_the_first_surface(name, m, mesh_name, tmp_path):
    rng = np.random.default_rng(7)
    path = ICOSPHERE if mesh_name == "icosphere" else sliver_sphere(tmp_path / "slivers.obj")
    mesh = read_mesh(path)
    vertices = float32_exact(mesh.vertices)
    m32 = float32_exact(m)
    o, d = rays_at_edges_and_vertices(rng, vertices, mesh.faces, m32, 20_000)
    scene = instancing.load_scene({"models": {"ico": {"type": "obj", "filename": str(path)}},
                                   "instances": [{"model": "ico", "to_world": m.tolist()}]})
    if mesh_name != "icosphere":
        # Its slivers are split into several references each (three per triangle, on average).
        assert scene.instances.libraries["mesh"].triangle_total > 2 * len(mesh.faces)
    t = np.asarray(scene.intersect(o, d).t, np.float64)
    expected = convex_first_hit(vertices, mesh.faces, m32, o, d)
    assert np.all(np.isfinite(expected)) and np.all(np.abs(expected - 1.0) < 2e-4)
    # The convex reference is the Moller-Trumbore float64 reference wherever that one holds
    # (on every fourth ray: a check of the references).
    mt64 = reference.intersect_instances([{"kind": "mesh", "to_world": m32,
                                           "mesh": (vertices, mesh.faces)}], o[::4], d[::4])["t"]
    assert np.mean(np.abs(mt64 - expected[::4]) <= 1e-9 * expected[::4]) > 0.995
    # No miss, and the first surface: t within 1e-5 relative (a leak lands on the far side,
    # 25 % to 390 % further along these rays).
    misses = int(np.sum(~np.isfinite(t)))
    wrong = int(np.sum(np.isfinite(t) & (np.abs(t - expected) > 1e-5 * expected)))
    assert (misses, wrong) == (0, 0), (name, misses, wrong)


def test_difference_of_products_has_the_exact_sign():
    rng = np.random.default_rng(3)
    n = 200_000
    a, b, c = (rng.uniform(-2.0, 2.0, n).astype(np.float32) for _ in range(3))
    # d chosen so that c d is within a few ulp of a b: cancellation to 0 and near it.
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (a.astype(np.float64) * b / c).astype(np.float32)
    d = np.where(np.isfinite(d), d, np.float32(1.0))
    d[: n // 2] = np.nextafter(d[: n // 2], np.float32(np.inf))
    # Products of float32 numbers are exact in float64, and so is the sign of their difference.
    exact = a.astype(np.float64) * b - c.astype(np.float64) * d
    ours = difference_of_products(*(Float(x) for x in (a, b, c, d)))
    ours = np.asarray(ours, np.float64)
    assert np.array_equal(np.sign(ours), np.sign(exact))
    assert np.all(np.abs(ours - exact) <= 2 * 2.0 ** -24 * np.abs(exact))
    # The plain float32 formula rounds such differences to 0 (its sign is never wrong when
    # the compiler keeps it unfused, but a 0 there would need the float64 fallback).
    naive = a * b - c * d
    assert np.any((naive == 0) & (exact != 0))


def test_mesh_areas_without_numpy_warnings_and_refused_naming_the_model(tmp_path):
    """Triangle areas (area sampling) are computed in float64: a mesh of coordinates 1e10
    loads without NumPy overflow warnings and samples areas in proportion; a mesh whose
    total area float32 cannot hold is refused naming the model and its file, without a
    warning from its BVH's float32 costs either."""
    import warnings
    from instancing.core.errors import SceneError
    from instancing.models.mesh import MeshLibrary, MeshData
    rng = np.random.default_rng(21)
    vertices = rng.uniform(-1, 1, (6, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 0]])

    def triangle_areas(v):
        p = float32_exact(v)[faces]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        library = MeshLibrary([MeshData(vertices * 1e10, faces)])
        expected = triangle_areas(vertices * 1e10)
        np.testing.assert_allclose(library.object_areas[0], expected.sum(), rtol=1e-12)
        cdf = np.asarray(library.area_cdf, np.float64)
        np.testing.assert_allclose(np.sort(np.diff(cdf, prepend=0.0)), np.sort(expected / expected.sum()),
                                   atol=1e-6)
        # 20 copies of a triangle of area 2.4e37 (spanning 7e18): 4.9e38 in all.
        copies = np.array([[0.0, 0, 0], [7e18, 0, 0], [0, 7e18, 0]])
        for scale, v, f, words in ((1e-25, vertices, faces, "vanish in float32"),
                                   (1e25, vertices, faces, "overflow float32"),
                                   (1.0, copies, [[0, 1, 2]] * 20, "overflow float32")):
            path = tmp_path / f"scaled{scale:g}-{len(f)}.obj"
            path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v * scale)
                            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))
            with pytest.raises(SceneError) as info:
                instancing.load_scene({"models": {"scaled": {"type": "obj", "filename": str(path)}},
                                       "instances": [{"model": "scaled"}]})
            message = str(info.value)
            assert "model 'scaled'" in message and path.name in message and words in message, message


@pytest.mark.parametrize("name", ["torus.obj", "tree.ply", "icosphere"])
def test_vertex_normals_are_mitsubas(name):
    """Smooth normals of a mesh file without any: Mitsuba's own (angle-weighted), at every
    triangle corner, for meshes with quads split in two (torus), poles (tree) and a
    subdivided sphere."""
    from instancing.models.mesh import vertex_normals
    from test_mesh_file import MESHES, mitsuba_corner_normals
    path = STRESS_MESH if name == "icosphere" else MESHES / name
    mesh = read_mesh(path)
    ours = vertex_normals(mesh.vertices, mesh.faces)
    np.testing.assert_allclose(np.linalg.norm(ours, axis=2), 1.0, atol=1e-12)
    np.testing.assert_allclose(ours, mitsuba_corner_normals(path), rtol=0, atol=2e-6)


def _terminator_setup(seed: int):
    """The torus mesh with its computed smooth normals in a library, and a viewpoint."""
    from instancing.models.mesh import MeshLibrary, vertex_normals
    from test_mesh_file import MESHES
    mesh = read_mesh(MESHES / "torus.obj")
    mesh = mesh.with_normals(vertex_normals(mesh.vertices, mesh.faces))
    rng = np.random.default_rng(seed)
    viewpoint = rng.normal(size=3)
    return mesh, MeshLibrary([mesh]), 4.0 * viewpoint / np.linalg.norm(viewpoint)


def _g(mesh, face, x, c, w=1.0):
    """float64 g(x) = sn(x) . (c - w x) on triangle ``face`` (per row)."""
    v, n = mesh.vertices[mesh.faces[face]], mesh.normals[face]
    e1, e2, d = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], x - v[:, 0]
    a11, a12, a22 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    b1, b2 = np.einsum("ij,ij->i", d, e1), np.einsum("ij,ij->i", d, e2)
    det = a11 * a22 - a12 * a12
    u, v_bary = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
    sn = n[:, 0] + u[:, None] * (n[:, 1] - n[:, 0]) + v_bary[:, None] * (n[:, 2] - n[:, 0])
    return np.einsum("ij,ij->i", sn, c - w * x), u, v_bary


@pytest.mark.parametrize("seed, w", [(1, 1.0), (2, 1.0), (3, 1.0), (1, 0.0), (2, 0.0)])
def test_terminator_arcs_lie_where_smooth_shading_turns_away(seed, w):
    """Each terminator arc found (torus, smooth normals) joins two edges of one triangle
    whose corners see the viewpoint on opposite sides; the kernel's points at random s lie
    in that triangle with g = sn . (c - x) = 0 (float64, relative to |sn| |c - x|), and
    every triangle whose corners' g change sign has an arc. With w = 0 the viewer is at
    infinity in direction c (an orthographic camera): g = sn . c."""
    from instancing.core.backend import Array3f, UInt32
    mesh, library, c = _terminator_setup(seed)
    if not w:
        c = c / np.linalg.norm(c)
    row, position, start, chord, normal = library.terminator_arcs(0, np.append(c, w)[None])
    face = np.asarray(library.original_index)[position]
    v, n = mesh.vertices[mesh.faces], mesh.normals
    g = np.einsum("fcj,fcj->fc", n, c - w * v)
    changing = np.flatnonzero((g > 0).any(axis=1) & ~(g > 0).all(axis=1))
    assert len(changing) > 10
    np.testing.assert_array_equal(np.sort(face), changing)
    assert (row == 0).all()
    s = np.random.default_rng(seed).random(len(face))
    x, tangent, inside = library.terminator_point(
        UInt32(position.astype(np.uint32)), Array3f(*start.T.astype(np.float32)),
        Array3f(*chord.T.astype(np.float32)), Array3f(*normal.T.astype(np.float32)),
        Float(s.astype(np.float32)), Array3f(*np.tile(c, (len(face), 1)).T.astype(np.float32)), w)
    x = np.asarray(x, np.float64).T
    assert np.asarray(inside).mean() > 0.95
    value, u, v_bary = _g(mesh, face, x, c, w)
    scale = np.linalg.norm(c - w * x, axis=1)
    assert np.abs(value / scale).max() < 1e-4
    assert (u > -1e-4).all() and (v_bary > -1e-4).all() and (u + v_bary < 1 + 1e-4).all()
    # The tangent runs along the arc: g does not change along it.
    tangent = np.asarray(tangent, np.float64).T
    ahead = _g(mesh, face, x + 1e-4 * tangent, c, w)[0] / scale
    assert np.abs(ahead).max() < 1e-5


def test_terminator_points_slide_with_the_viewpoint():
    """The arc point's derivative with respect to the viewpoint (AD, forward mode) is the
    central difference of the points computed from moved viewpoints, along the line
    s = const (float32: step 1e-3, agreement 2 % of the largest motion)."""
    from instancing.core.backend import Array3f, UInt32, dr
    mesh, library, c = _terminator_setup(4)
    row, position, start, chord, normal = library.terminator_arcs(0, c[None])
    k = len(position)
    s = Float(np.full(k, 0.5, np.float32))
    args = (UInt32(position.astype(np.uint32)), Array3f(*start.T.astype(np.float32)),
            Array3f(*chord.T.astype(np.float32)), Array3f(*normal.T.astype(np.float32)), s)
    direction = np.array([0.3, -0.5, 0.8])

    def point(c_value, attach=False):
        cv = Array3f(*np.tile(c_value, (k, 1)).T.astype(np.float32))
        if attach:
            dr.enable_grad(cv)
            dr.set_grad(cv, Array3f(*np.tile(direction, (k, 1)).T.astype(np.float32)))
        x, _, inside = library.terminator_point(*args, cv)
        if attach:
            dr.forward_to(x)
            return np.asarray(dr.grad(x), np.float64).T, np.asarray(inside)
        return np.asarray(x, np.float64).T

    derivative, inside = point(c, attach=True)
    step = 1e-3
    central = (point(c + step * direction) - point(c - step * direction)) / (2 * step)
    scale = np.abs(central[inside]).max()
    assert scale > 0
    assert np.abs(derivative[inside] - central[inside]).max() < 0.02 * scale


def test_terminator_tangents_measure_the_arc_length():
    """|d x / ds| integrated over s (the boundary term's measure) is each arc's length:
    a fine polyline through the kernel's points (65 per arc) against the trapezoid rule
    on the tangents' norms, within 0.1 %."""
    from instancing.core.backend import Array3f, UInt32
    mesh, library, c = _terminator_setup(5)
    row, position, start, chord, normal = library.terminator_arcs(0, c[None])
    s = np.linspace(0.0, 1.0, 65)
    k = len(position)
    rep = lambda a: np.repeat(a, len(s), axis=0)  # noqa: E731
    x, tangent, inside = library.terminator_point(
        UInt32(rep(position).astype(np.uint32)), Array3f(*rep(start).T.astype(np.float32)),
        Array3f(*rep(chord).T.astype(np.float32)), Array3f(*rep(normal).T.astype(np.float32)),
        Float(np.tile(s, k).astype(np.float32)),
        Array3f(*np.tile(c, (k * len(s), 1)).T.astype(np.float32)))
    x = np.asarray(x, np.float64).T.reshape(k, len(s), 3)
    speed = np.linalg.norm(np.asarray(tangent, np.float64).T, axis=1).reshape(k, len(s))
    whole = np.asarray(inside).reshape(k, len(s)).all(axis=1)
    assert whole.mean() > 0.9
    polyline = np.linalg.norm(np.diff(x, axis=1), axis=2).sum(axis=1)
    integral = ((speed[:, 1:] + speed[:, :-1]) / 2 * np.diff(s)).sum(axis=1)
    np.testing.assert_allclose(integral[whole], polyline[whole], rtol=1e-3)


def test_a_flat_mesh_has_a_plane_and_a_curved_one_none():
    """MeshLibrary.plane: the tiles (32 coplanar triangles at z = 0, some wound either way)
    lie in z = 0; a sheared and moved copy in its own plane, against the plane through three
    of its vertices in float64; the torus, and the tiles with one vertex lifted by 1e-3 of
    their extent, in none."""
    from instancing.models.mesh import MeshData, MeshLibrary
    from instancing.validation.gradient_check import DATA
    from test_mesh_file import MESHES
    tiles = read_mesh(DATA / "tiles.obj")
    normal, offset = MeshLibrary([tiles]).plane(0)
    np.testing.assert_allclose(np.abs(normal), [0.0, 0.0, 1.0], atol=1e-12)
    assert abs(offset) < 1e-12
    matrix = np.array([[1.0, 0.3, 0.2], [0.1, 0.9, -0.4], [0.5, 0.0, 1.1]])
    moved = tiles.vertices.astype(np.float64) @ matrix.T + [0.4, -2.0, 7.0]
    a, b, c = moved[tiles.faces[0]]
    expected = np.cross(b - a, c - a)
    expected /= np.linalg.norm(expected)
    normal, offset = MeshLibrary([MeshData(moved, tiles.faces)]).plane(0)
    sign = np.sign(normal @ expected)
    np.testing.assert_allclose(normal * sign, expected, atol=1e-9)
    assert abs(offset * sign - expected @ a) < 1e-9
    lifted = tiles.vertices.astype(np.float64).copy()
    lifted[0, 2] += 2e-3
    assert MeshLibrary([MeshData(lifted, tiles.faces)]).plane(0) is None
    assert MeshLibrary([read_mesh(MESHES / "torus.obj")]).plane(0) is None
