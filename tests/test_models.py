"""Analytic models and their discontinuity curves (instancing/models/analytic.py and
instancing/models/curves.py), tested in object space against float64 NumPy closed forms
written out here: ray intersection, normals, area sampling, areas, world bounds,
silhouettes/rims/edges, and the edge topology of triangle meshes."""

import math
import warnings

import numpy as np
import pytest

import instancing  # noqa: F401  (selects the backend)
from instancing.core.backend import Array3f, Float, UInt32
from instancing.io.mesh_file import read_mesh
from instancing.models.analytic import ANALYTIC_MODELS
from instancing.models.curves import (CREASE_SCALE_FLOOR, QUADRIC_DIAGONALS, Curves, EdgeTopology,
                                      quadric_intersection)
from instancing.models.mesh import vertex_normals
from scene_helpers import MESH_FILE, float32_exact, random_affine

KINDS = ["sphere", "cube", "rectangle", "disk", "cylinder"]
#: float32 unit roundoff.
EPS32 = 2.0 ** -24
#: Rays whose float64 answer lies closer than this (object-space units, or the
#: dimensionless quantities named in each reference) to a decision boundary (grazing a
#: quadric, crossing a rim or an edge, starting on the surface, ending at t_max) may
#: legitimately be classified either way in float32; they are left out of the
#: exact-agreement checks, and must be rare.
MARGIN = 1e-4


def _vectors(x: np.ndarray) -> Array3f:
    return Array3f(*[Float(np.ascontiguousarray(x[:, k], np.float32)) for k in range(3)])


def _rows(v: Array3f) -> np.ndarray:
    return np.asarray(v, np.float64).T


# -- float64 closed forms --------------------------------------------------------------------

def _nearest(candidates, t_max):
    """Nearest of the candidate parameters (t, valid) in (0, t_max), inf if none."""
    best = np.full(len(t_max), np.inf)
    for t, ok in reversed(candidates):
        best = np.where(ok & (t > 0) & (t < t_max), t, best)
    return best


def _reference_sphere(o, d, t_max):
    a = np.sum(d * d, 1)
    b = np.sum(o * d, 1)
    closest2 = np.sum(o * o, 1) - b * b / a  # squared distance of the line from the centre
    disc = np.maximum(1.0 - closest2, 0.0) * a
    roots = [(-b - np.sqrt(disc)) / a, (-b + np.sqrt(disc)) / a]
    hit = closest2 <= 1.0
    t = _nearest([(r, hit) for r in roots], t_max)
    length = np.sqrt(a)
    margin = np.minimum.reduce([np.abs(1.0 - closest2)] + [np.abs(r) * length for r in roots]
                               + [np.abs(r - t_max) * length for r in roots])
    return t, margin


def _reference_cylinder(o, d, t_max):
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    closest2 = o[:, 0] ** 2 + o[:, 1] ** 2 - b * b / a
    disc = np.maximum(1.0 - closest2, 0.0) * a
    roots = [(-b - np.sqrt(disc)) / a, (-b + np.sqrt(disc)) / a]
    z = [o[:, 2] + r * d[:, 2] for r in roots]
    hit = closest2 <= 1.0
    t = _nearest([(r, hit & (zk >= 0) & (zk <= 1)) for r, zk in zip(roots, z)], t_max)
    length = np.linalg.norm(d, axis=1)
    margin = np.minimum.reduce([np.abs(1.0 - closest2), a / length ** 2]
                               + [np.abs(r) * length for r in roots]
                               + [np.abs(r - t_max) * length for r in roots]
                               + [np.abs(zk) for zk in z] + [np.abs(zk - 1) for zk in z])
    return t, np.where(hit | (np.abs(1.0 - closest2) > MARGIN), margin, 0.0)


def _reference_planar(inside_margin):
    def reference(o, d, t_max):
        t = -o[:, 2] / d[:, 2]
        x, y = o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1]
        inside = inside_margin(x, y)
        length = np.linalg.norm(d, axis=1)
        margin = np.minimum.reduce([np.abs(inside), np.abs(t) * length, np.abs(t - t_max) * length,
                                    np.abs(d[:, 2]) / length])
        return _nearest([(t, inside >= 0)], t_max), margin
    return reference


def _reference_cube(o, d, t_max):
    t_lo, t_hi = (-1.0 - o) / d, (1.0 - o) / d
    t_enter = np.minimum(t_lo, t_hi).max(1)
    t_exit = np.maximum(t_lo, t_hi).min(1)
    hit = t_enter <= t_exit
    length = np.linalg.norm(d, axis=1)
    margin = np.minimum.reduce([np.abs(t_exit - t_enter) * length, np.abs(t_enter) * length,
                                np.abs(t_exit) * length, np.abs(t_enter - t_max) * length,
                                np.abs(t_exit - t_max) * length])
    return _nearest([(t_enter, hit), (t_exit, hit)], t_max), margin


REFERENCE = {
    "sphere": _reference_sphere,
    "cylinder": _reference_cylinder,
    "rectangle": _reference_planar(lambda x, y: np.minimum(1 - np.abs(x), 1 - np.abs(y))),
    "disk": _reference_planar(lambda x, y: 1 - np.hypot(x, y)),
    "cube": _reference_cube,
}


def _surface_distance(kind: str, p: np.ndarray) -> np.ndarray:
    """Signed float64 distance-like implicit function: > 0 outside, 0 on the surface
    (for flat shapes: the height above the plane)."""
    if kind == "sphere":
        return np.linalg.norm(p, axis=1) - 1.0
    if kind == "cylinder":
        return np.hypot(p[:, 0], p[:, 1]) - 1.0
    if kind == "cube":
        return np.abs(p).max(1) - 1.0
    return p[:, 2]


def _in_extent(kind: str, p: np.ndarray) -> np.ndarray:
    """The surface's extent besides the implicit equation (height, rim, sides)."""
    tol = 8 * EPS32
    if kind == "cylinder":
        return (p[:, 2] >= -tol) & (p[:, 2] <= 1 + tol)
    if kind == "rectangle":
        return (np.abs(p[:, :2]) <= 1 + tol).all(1)
    if kind == "disk":
        return np.hypot(p[:, 0], p[:, 1]) <= 1 + tol
    return np.ones(len(p), bool)


def _samples(kind: str, seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u1, u2 = (Float(rng.random(n, dtype=np.float32)) for _ in range(2))
    return _rows(ANALYTIC_MODELS[kind].sample_area(u1, u2))


# -- intersect --------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_intersect_matches_the_float64_closed_form(kind):
    """Random object-space rays (some starting inside the bounds, half aimed near the
    shape, directions of random length: t is in units of d), half with a finite t_max: the nearest hit in (0, t_max)
    agrees with the float64 closed form on every ray not within MARGIN of a decision."""
    rng = np.random.default_rng(KINDS.index(kind))
    n = 20_000
    o = rng.uniform(-3, 3, (n, 3))
    # Half aimed at points near the shape, half in random directions.
    d = np.where(rng.random((n, 1)) < 0.5, rng.uniform(-1.2, 1.2, (n, 3)) - o, rng.normal(size=(n, 3)))
    o = float32_exact(o)
    d = float32_exact(d / np.linalg.norm(d, axis=1, keepdims=True) * 10.0 ** rng.uniform(-1, 1, (n, 1)))
    t_max = float32_exact(np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0, 6, n)))
    t = np.asarray(ANALYTIC_MODELS[kind].intersect(_vectors(o), _vectors(d), Float(t_max.astype(np.float32))),
                   np.float64)
    t_ref, margin = REFERENCE[kind](o, d, t_max)
    robust = margin > MARGIN
    assert robust.mean() > 0.99
    assert 0.05 < np.isfinite(t_ref[robust]).mean() < 0.95  # both hits and misses are tested
    np.testing.assert_array_equal(np.isfinite(t[robust]), np.isfinite(t_ref[robust]))
    both = robust & np.isfinite(t_ref)
    # Careful float32 quadratics (Haines et al.) and slab/plane tests: the hit point is off
    # by a few float32 ulps of the coordinates involved (|o| + t |d| <= ~70 here), so the
    # distance error is a small multiple of EPS32 times that scale (measured: up to 10 for
    # the quadrics, whose roots near grazing amplify roundoff; 2 for the flat shapes/slabs).
    length = np.linalg.norm(d[both], axis=1)
    scale = np.linalg.norm(o[both], axis=1) + t_ref[both] * length
    error = np.abs(t[both] - t_ref[both]) * length / scale
    assert error.max() < 32 * EPS32, error.max() / EPS32


# -- normal -----------------------------------------------------------------------------------

def _gradient(kind: str, p: np.ndarray) -> np.ndarray:
    """Outward normal direction from the gradient of the implicit function, float64."""
    if kind == "sphere":
        return p
    if kind == "cylinder":
        return np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], 1)
    if kind == "cube":
        axis = np.argmax(np.abs(p), 1)
        g = np.zeros_like(p)
        g[np.arange(len(p)), axis] = np.sign(p[np.arange(len(p)), axis])
        return g
    return np.tile([0.0, 0.0, 1.0], (len(p), 1))


@pytest.mark.parametrize("kind", KINDS)
def test_normal_is_perpendicular_to_the_surface_and_outward(kind):
    """At surface points, normal() is parallel to the implicit function's gradient (hence
    perpendicular to every tangent) with the same orientation; for closed shapes a small
    step along it leaves the shape and a step against it enters."""
    p = _samples(kind, 20 + KINDS.index(kind), 4000)
    # (Flat shapes return one constant normal: broadcast it to the points.)
    n = np.broadcast_to(_rows(ANALYTIC_MODELS[kind].normal(_vectors(p), UInt32(0))), p.shape)
    n_hat = n / np.linalg.norm(n, axis=1, keepdims=True)
    g = _gradient(kind, p)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    # float32 samples on the surface: directions agree to a few float32 roundings.
    np.testing.assert_allclose(n_hat, g, atol=16 * EPS32)
    if kind in ("sphere", "cube", "cylinder"):
        h = 1e-3
        f_out = _surface_distance(kind, p + h * n_hat)
        f_in = _surface_distance(kind, p - h * n_hat)
        interior = np.ones(len(p), bool)
        if kind == "cube":  # away from edges, where the inward step meets another face
            interior = np.sort(np.abs(p), 1)[:, 1] < 1 - 2 * h
        assert (f_out > 0).all()
        assert (f_in[interior] < 0).all()


# -- area sampling ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_sample_area_points_lie_on_the_surface(kind):
    p = _samples(kind, 30 + KINDS.index(kind), 20_000)
    # float32 sqrt/sincos products: a few units of roundoff from the exact surface.
    np.testing.assert_allclose(_surface_distance(kind, p), 0.0, atol=8 * EPS32)
    assert _in_extent(kind, p).all()


def _area_coordinates(kind: str, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, list, list]:
    """Two coordinates in which the uniform-by-area distribution is uniform on a box
    (Archimedes for the sphere, r^2 for the disk, the face coordinates for the cube
    faces unrolled in a row), with that box."""
    phi = np.arctan2(p[:, 1], p[:, 0])
    if kind == "sphere":
        return p[:, 2], phi, [-1, 1], [-np.pi, np.pi]
    if kind == "cylinder":
        return p[:, 2], phi, [0, 1], [-np.pi, np.pi]
    if kind == "rectangle":
        return p[:, 0], p[:, 1], [-1, 1], [-1, 1]
    if kind == "disk":
        return p[:, 0] ** 2 + p[:, 1] ** 2, phi, [0, 1], [-np.pi, np.pi]
    # Cube: face index (axis, sign) in [0, 6), plus the face's first free coordinate
    # in [0, 1); the second free coordinate is checked by the same histogram transposed.
    axis = np.argmax(np.abs(p), 1)
    sign = p[np.arange(len(p)), axis] > 0
    face = 2 * axis + sign
    free = np.where(axis[:, None] == 0, p[:, [1, 2]], np.where(axis[:, None] == 1, p[:, [0, 2]], p[:, [0, 1]]))
    return face + 0.5 * (free[:, 0] + 1), free[:, 1], [0, 6], [-1, 1]


@pytest.mark.parametrize("kind", KINDS)
def test_sample_area_is_uniform_by_area(kind):
    """Histograms over area-preserving coordinates are flat: every one of 12 x 8 bins
    within 5 binomial standard errors of its expected count (fixed seed), so each
    sub-region gets its area fraction of the samples."""
    n = 1 << 17
    p = _samples(kind, 40 + KINDS.index(kind), n)
    a, b, a_range, b_range = _area_coordinates(kind, p)
    counts, _, _ = np.histogram2d(a, b, bins=[12, 8], range=[a_range, b_range])
    prob = 1.0 / counts.size
    assert counts.sum() == n
    assert np.abs(counts - n * prob).max() < 5 * math.sqrt(n * prob * (1 - prob)), counts


def test_object_area_matches_the_closed_forms():
    expected = {"sphere": 4 * np.pi, "cube": 6 * 4.0, "rectangle": 2.0 * 2.0, "disk": np.pi,
                "cylinder": 2 * np.pi * 1.0 * 1.0}  # open cylinder: side only
    for kind, area in expected.items():
        assert ANALYTIC_MODELS[kind].object_area == pytest.approx(area, rel=1e-12)


# -- world bounds -----------------------------------------------------------------------------

def _extreme_points(kind: str) -> np.ndarray:
    """Deterministic surface points dense where a linear function can peak: a lat-long
    grid on the sphere, rims for the cylinder and disk, corners for the box shapes."""
    if kind == "sphere":
        theta, phi = np.meshgrid(np.linspace(0, np.pi, 257), np.linspace(-np.pi, np.pi, 513))
        return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    phi = np.linspace(-np.pi, np.pi, 4097)
    rim = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1)
    if kind == "cylinder":
        return np.concatenate([rim, rim + [0, 0, 1.0]])
    if kind == "disk":
        return rim
    if kind == "rectangle":
        return np.array([[x, y, 0.0] for x in (-1, 1) for y in (-1, 1)])
    return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)


@pytest.mark.parametrize("kind", KINDS)
def test_world_bounds_contain_the_transformed_surface_and_touch_it(kind):
    """Bounds under random affine maps contain every transformed surface point (random
    samples and the extreme points), and the extreme points reach each face of the box:
    exact bounds for quadrics (ellipses/ellipsoids) and transformed boxes."""
    rng = np.random.default_rng(50 + KINDS.index(kind))
    matrices = np.stack([random_affine(rng, 5.0, reflect=i % 2 == 1) for i in range(8)])
    lo, hi = ANALYTIC_MODELS[kind].world_bounds(matrices)
    assert lo.shape == hi.shape == (8, 3)
    points = np.concatenate([_samples(kind, 60, 5000), _extreme_points(kind)])
    world = np.einsum("nij,kj->nki", matrices[:, :3, :3], points) + matrices[:, None, :3, 3]
    extent = hi - lo
    # float64 bounds; the float32 samples sit a few units of roundoff off the surface.
    slack = 1e-6 * extent[:, None, :]
    assert (world >= lo[:, None] - slack).all() and (world <= hi[:, None] + slack).all()
    extreme = world[:, 5000:]
    # The sphere grid's spacing pi/256 falls short by at most (pi/256)^2/2 ~ 8e-5 of a row
    # norm (half the extent); the rims' pi/2048 by much less; corners reach the box exactly.
    reach = 5e-5 * extent
    assert (extreme.min(1) - lo <= reach).all() and (hi - extreme.max(1) <= reach).all()


def test_sphere_world_bounds_touch_at_the_closed_form_tangent_points():
    """The ellipsoid's extreme along axis i is at the object point A_i / |A_i| (row i of
    the linear part, normalised): there the box face is reached exactly."""
    rng = np.random.default_rng(70)
    matrices = np.stack([random_affine(rng, 5.0) for _ in range(16)])
    lo, hi = ANALYTIC_MODELS["sphere"].world_bounds(matrices)
    for i in range(3):
        row = matrices[:, i, :3]
        p = row / np.linalg.norm(row, axis=1, keepdims=True)
        top = np.einsum("nj,nj->n", row, p) + matrices[:, i, 3]
        bottom = np.einsum("nj,nj->n", row, -p) + matrices[:, i, 3]
        np.testing.assert_allclose(top, hi[:, i], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(bottom, lo[:, i], rtol=1e-13, atol=1e-13)


# -- discontinuity curves ---------------------------------------------------------------------

def _homogeneous(viewpoints: np.ndarray, w: float = 1.0) -> np.ndarray:
    """(M, 4) homogeneous viewpoints: points (w = 1) or directions to a viewer at
    infinity (w = 0)."""
    return np.concatenate([viewpoints, np.full((len(viewpoints), 1), w)], axis=1)


def _curves(kind: str, viewpoints: np.ndarray, w: float = 1.0, **kwargs) -> Curves:
    return Curves(*ANALYTIC_MODELS[kind].discontinuity_curves(_homogeneous(viewpoints, w), **kwargs))


def _viewpoints(seed: int, n: int = 64) -> np.ndarray:
    """Viewpoints at distances 0.2 .. 8 from the origin in random directions."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True) * rng.uniform(0.2, 8.0, (n, 1))


S = np.linspace(0.0, 1.0, 33)[:-1]


def test_sphere_silhouette_is_the_circle_of_tangency_seen_from_outside():
    cam = _viewpoints(80)
    curves = _curves("sphere", cam)
    outside = np.linalg.norm(cam, axis=1) > 1
    assert 0 < outside.sum() < len(cam)
    # One circle per viewpoint outside, none from inside.
    np.testing.assert_array_equal(np.sort(curves.instance), np.flatnonzero(outside))
    assert curves.circle.all()
    x = curves.points(S)
    view = cam[curves.instance][:, None]
    # On the unit sphere, and the ray from the viewpoint is tangent: n . (x - cam) = 0.
    np.testing.assert_allclose(np.linalg.norm(x, axis=2), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(x * (x - view), axis=2), 0.0, atol=1e-12)


def test_cylinder_curves_are_tangent_lines_and_rims():
    cam = _viewpoints(81)
    curves = _curves("cylinder", cam)
    outside = np.hypot(cam[:, 0], cam[:, 1]) > 1
    assert 0 < outside.sum() < len(cam)
    rows, counts = np.unique(curves.instance, return_counts=True)
    np.testing.assert_array_equal(rows, np.arange(len(cam)))
    # Two rims from everywhere; two tangent lines from outside the infinite cylinder.
    np.testing.assert_array_equal(counts, np.where(outside, 4, 2))
    x = curves.points(S)
    rims, lines = curves.circle, ~curves.circle
    assert rims.sum() == 2 * len(cam) and lines.sum() == 2 * outside.sum()
    # Rims: radius 1 at z = 0 and z = 1, one of each per viewpoint.
    np.testing.assert_allclose(np.hypot(x[rims, :, 0], x[rims, :, 1]), 1.0, atol=1e-12)
    heights = x[rims, 0, 2]
    assert set(np.round(heights, 12)) == {0.0, 1.0}
    assert np.all(np.ptp(x[rims, :, 2], axis=1) == 0)
    # Lines: on the side from z = 0 to z = 1, tangent to the view ray: n . (x - cam) = 0.
    side = x[lines]
    np.testing.assert_allclose(np.hypot(side[..., 0], side[..., 1]), 1.0, atol=1e-12)
    np.testing.assert_allclose(side[:, 0, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(curves.points(np.array([1.0]))[lines, 0, 2], 1.0, atol=1e-12)
    normal = side * [1.0, 1.0, 0.0]
    view = cam[curves.instance[lines]][:, None]
    np.testing.assert_allclose(np.sum(normal * (side - view), axis=2), 0.0, atol=1e-12)
    # The two lines of a viewpoint are distinct (the two sides of the silhouette).
    first = curves.c[lines]
    rows_l = curves.instance[lines]
    for r in np.flatnonzero(outside)[:10]:
        pair = first[rows_l == r]
        assert len(pair) == 2 and np.linalg.norm(pair[0] - pair[1]) > 1e-6


@pytest.mark.parametrize("w", [1.0, 0.0])
def test_cylinder_seen_along_its_axis_shows_only_its_rims_without_warnings(w):
    """From a point on the axis, or from infinity along it (a directional light down the
    axis), no tangent line exists: only the two rims, and no 0 / 0 on the way."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        curves = _curves("cylinder", np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -2.0]]), w)
    assert curves.circle.all() and len(curves.circle) == 4
    assert np.isfinite(curves.c).all() and np.isfinite(curves.u).all()


def test_silhouettes_seen_from_infinity_are_where_the_view_direction_is_tangent():
    """Homogeneous viewpoints with w = 0 (a viewer at infinity in direction c, as a
    directional light): the sphere shows the great circle x . c = 0, the cylinder the two
    lines where (x, y) . c_xy = 0 (plus its rims), both tangent to the direction c."""
    rng = np.random.default_rng(85)
    direction = rng.normal(size=(32, 3))
    sphere = _curves("sphere", direction, w=0.0)
    np.testing.assert_array_equal(sphere.instance, np.arange(32))
    x = sphere.points(S)
    np.testing.assert_allclose(np.linalg.norm(x, axis=2), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(x * direction[:, None], axis=2), 0.0, atol=1e-12)
    cylinder = _curves("cylinder", direction, w=0.0)
    lines = ~cylinder.circle
    np.testing.assert_array_equal(np.bincount(cylinder.instance[lines], minlength=32), np.full(32, 2))
    side = cylinder.points(S)[lines]
    normal = side * [1.0, 1.0, 0.0]
    np.testing.assert_allclose(np.hypot(side[..., 0], side[..., 1]), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(normal * direction[cylinder.instance[lines]][:, None], axis=2), 0.0,
                               atol=1e-12)


def test_rectangle_curves_are_its_four_sides_from_every_viewpoint():
    cam = _viewpoints(82, 16)
    curves = _curves("rectangle", cam)
    assert not curves.circle.any()
    corners = {(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)}
    for r in range(len(cam)):
        mine = curves.instance == r
        assert mine.sum() == 4
        start = curves.c[mine]
        end = start + curves.u[mine]
        sides = {frozenset([tuple(a[:2]), tuple(b[:2])]) for a, b in zip(start, end)}
        # The 4 sides: each joins two corners differing in one coordinate.
        assert sides == {frozenset([a, b]) for a in corners for b in corners
                         if sum(x != y for x, y in zip(a, b)) == 1}
        assert np.all(start[:, 2] == 0) and np.all(end[:, 2] == 0)


def test_disk_curve_is_its_rim_from_every_viewpoint():
    cam = _viewpoints(83, 16)
    curves = _curves("disk", cam)
    np.testing.assert_array_equal(curves.instance, np.arange(len(cam)))
    assert curves.circle.all()
    x = curves.points(S)
    np.testing.assert_allclose(np.hypot(x[..., 0], x[..., 1]), 1.0, atol=1e-12)
    np.testing.assert_allclose(x[..., 2], 0.0, atol=1e-12)
    # The whole rim: the parameter covers every angle.
    angles = np.sort(np.arctan2(x[0, :, 1], x[0, :, 0]))
    assert np.diff(angles).max() < 2 * np.pi / len(S) + 1e-9


def _cube_edges():
    """The 12 cube edges as ((i, s_i), (j, s_j)): the two faces (axis, sign) they join."""
    return [((i, si), (j, sj)) for i in range(3) for j in range(i + 1, 3)
            for si in (-1, 1) for sj in (-1, 1)]


def _cube_edge_set(curves: Curves, row: int) -> set:
    """The curves of one viewpoint as cube edges ((i, s_i), (j, s_j)); each must be a true
    edge: a segment between corners that differ in exactly one coordinate."""
    got = set()
    for c, u in zip(curves.c[curves.instance == row], curves.u[curves.instance == row]):
        a, b = c, c + u
        same = np.flatnonzero(a == b)
        assert len(same) == 2 and set(np.abs(a)) == {1.0} and set(np.abs(b)) == {1.0}, (a, b)
        got.add(((int(same[0]), int(a[same[0]])), (int(same[1]), int(a[same[1]]))))
    return got


def test_cube_edges_are_those_with_a_face_turned_to_the_viewpoint():
    """The cube's curves are its 12 true edges only (never the diagonals of its
    triangulated faces, which are coplanar), and of those exactly the ones with at least
    one face turned to the viewpoint (face (axis i, sign s) faces cam when s cam_i > 1):
    every silhouette edge (one face towards, one away) is there, and no edge between two
    faces turned away (the creases between two visible faces are kept: flat shading
    jumps there, see instancing/rendering/boundary_term.py). From inside: none."""
    rng = np.random.default_rng(84)
    cam = np.concatenate([rng.uniform(-4, 4, (60, 3)), rng.uniform(-0.9, 0.9, (4, 3))])
    curves = _curves("cube", cam)
    assert not curves.circle.any()
    silhouettes = 0
    for r in range(len(cam)):
        got = _cube_edge_set(curves, r)
        facing = lambda face: face[1] * cam[r, face[0]] > 1  # noqa: E731
        expected = {e for e in _cube_edges() if facing(e[0]) or facing(e[1])}
        assert got == expected, (cam[r], got ^ expected)
        silhouettes += sum(facing(e[0]) != facing(e[1]) for e in expected)
    assert silhouettes > 100
    inside = np.abs(cam).max(1) < 1
    assert inside.sum() == 4 and not np.isin(np.flatnonzero(inside), curves.instance).any()


def test_cube_silhouette_edges_without_creases():
    """creases=False (what shadows need): exactly the edges between a face turned to the
    viewpoint and one turned away, from points and from infinity."""
    rng = np.random.default_rng(87)
    cam = np.concatenate([rng.uniform(-4, 4, (40, 3)), rng.uniform(-0.9, 0.9, (2, 3))])
    for w, threshold in ((1.0, 1.0), (0.0, 0.0)):
        curves = _curves("cube", cam, w=w, creases=False)
        silhouettes = 0
        for r in range(len(cam)):
            facing = lambda face: face[1] * cam[r, face[0]] > threshold  # noqa: E731
            expected = {e for e in _cube_edges() if facing(e[0]) != facing(e[1])}
            assert _cube_edge_set(curves, r) == expected, (w, cam[r])
            silhouettes += len(expected)
        assert silhouettes > 150


def test_cube_edges_seen_from_infinity():
    """From a viewer at infinity in direction c (w = 0), face (i, s) is turned to it when
    s c_i > 0."""
    direction = np.random.default_rng(86).normal(size=(16, 3))
    curves = _curves("cube", direction, w=0.0)
    for r in range(len(direction)):
        facing = lambda face: face[1] * direction[r, face[0]] > 0  # noqa: E731
        assert _cube_edge_set(curves, r) == {e for e in _cube_edges() if facing(e[0]) or facing(e[1])}


def _cube_mesh():
    """A closed cube of 12 outward triangles (its own triangulation, not the model's)."""
    v = np.array([[x, y, z] for z in (-1.0, 1.0) for y in (-1.0, 1.0) for x in (-1.0, 1.0)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return v, faces


def test_edge_topology_of_a_closed_mesh_gives_every_edge_two_faces():
    for vertices, faces in (_cube_mesh(), tuple(read_mesh(MESH_FILE))[:2]):
        edges = EdgeTopology.of_mesh(np.asarray(vertices, np.float64), np.asarray(faces))
        n_vertices = len(np.unique(faces))
        # Closed manifold mesh: 3F = 2E, and every edge has a second face, not the first.
        assert 2 * len(edges.start) == 3 * len(faces)
        assert (edges.face1 >= 0).all() and (edges.face0 != edges.face1).all()
        # Both faces really contain the edge's two endpoints.
        verts = np.asarray(vertices, np.float64)
        for face in (edges.face0, edges.face1):
            corners = verts[faces[face]]
            for end in (edges.start, edges.start + edges.direction):
                # (start + direction rounds the far end by at most an ulp)
                assert (np.abs(corners - end[:, None]).max(2).min(1) < 1e-12).all()
        # Unit face normals, cross(e1, e2) oriented.
        np.testing.assert_allclose(np.linalg.norm(edges.face_normal, axis=1), 1.0, atol=1e-12)
        if len(faces) == 12:
            # Cube: Euler characteristic 2 (V - E + F), outward normals.
            assert n_vertices - len(edges.start) + len(faces) == 2
            centres = verts[faces].mean(1)
            assert (np.sum(edges.face_normal * centres, 1) > 0).all()


def test_edge_topology_of_an_open_mesh_keeps_its_boundary_from_every_viewpoint():
    """A square of two triangles: 4 boundary edges (one face) and a coplanar diagonal. The
    boundary is a discontinuity from every side; the flat diagonal never is."""
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    edges = EdgeTopology.of_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))
    assert (edges.face1 == -1).sum() == 4 and (edges.face1 >= 0).sum() == 1
    cam = np.array([[0.5, 0.5, 2.0], [0.5, 0.5, -2.0], [3.0, 0.2, 0.0]])
    for creases in (True, False):
        rows, circle, c, u, _ = edges.discontinuity_curves(_homogeneous(cam), creases=creases)
        np.testing.assert_array_equal(np.bincount(rows, minlength=3), [4, 4, 4])
        assert not circle.any()
        # None of them is the diagonal (0,0,0)-(1,1,0).
        assert not np.any(np.all(np.abs(u[:, :2]) == 1.0, axis=1))


def _folded_pair(angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles sharing the edge (0,0,0)-(0,1,0), the second turned about it by
    ``angle`` (radians) from the first's plane z = 0 (their normals ``angle`` apart)."""
    v = np.array([[0.0, 0, 0], [0, 1, 0], [1, 0, 0], [-math.cos(angle), 0, math.sin(angle)]])
    return v, np.array([[0, 2, 1], [0, 1, 3]])


def _on_the_fold(c: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Which segments (c, u) lie on the fold of :func:`_folded_pair`, the y axis from 0 to 1."""
    return ((np.abs(c[:, [0, 2]]).max(1) < 1e-12) & (np.abs(u[:, [0, 2]]).max(1) < 1e-12)
            & (np.abs(u[:, 1]) == 1))


@pytest.mark.parametrize("degrees", [0.0, 3.0, 30.0, 60.0, 90.0, 150.0])
def test_a_creases_jump_scale_is_how_far_its_normals_turn(degrees):
    """|n0 - n1| = 2 sin(angle / 2) of the two faces' unit normals, between the floor and 1;
    the four boundary edges (one face each) 1. Seen from where both faces face the viewer,
    the crease carries that scale; from where only one face does, it is a silhouette: 1."""
    v, faces = _folded_pair(math.radians(degrees))
    edges = EdgeTopology.of_mesh(v, faces)
    shared = edges.face1 >= 0
    assert shared.sum() == 1
    expected = min(max(2.0 * math.sin(math.radians(degrees) / 2.0), CREASE_SCALE_FLOOR), 1.0)
    assert edges.jump_scale[shared][0] == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(edges.jump_scale[~shared], 1.0)
    if degrees == 0.0:
        return  # (coplanar: no crease to see)
    n0, n1 = edges.face_normal[edges.face0[shared][0]], edges.face_normal[edges.face1[shared][0]]
    fold = np.array([0.0, 0.5, 0.0])
    # Along the normals' bisector both faces face the viewer; along n1 - n0 only one does.
    for towards, scale in ((n0 + n1, expected), (n1 - n0, 1.0)):
        viewpoint = _homogeneous((fold + 3.0 * towards / np.linalg.norm(towards))[None])
        (_, _, c, u, _), scales = edges.scaled_discontinuity_curves(viewpoint)
        on_fold = _on_the_fold(c, u)
        assert on_fold.sum() == 1 and scales[on_fold][0] == pytest.approx(scale, rel=1e-12)
        np.testing.assert_array_equal(scales[~on_fold], 1.0)


def test_a_smooth_creases_jump_scale_takes_the_corner_normals_turn():
    """Coplanar faces whose corner normals at one end of the shared edge differ by 60
    degrees: the scale is their difference, 2 sin 30 = 1 (at the floor without them)."""
    v, faces = _folded_pair(0.0)
    tilted = [math.sin(math.radians(60.0)), 0.0, math.cos(math.radians(60.0))]
    normals = np.tile([0.0, 0.0, 1.0], (2, 3, 1))
    normals[1, list(faces[1]).index(1)] = tilted  # the second face's normal at (0, 1, 0)
    shared = EdgeTopology.of_mesh(v, faces).face1 >= 0
    assert EdgeTopology.of_mesh(v, faces).jump_scale[shared][0] == CREASE_SCALE_FLOOR
    assert EdgeTopology.of_mesh(v, faces, normals).jump_scale[shared][0] == pytest.approx(1.0)


# -- surface points and their error bounds ----------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_surface_points_lie_within_their_error_bound_of_the_surface(kind):
    """surface_point() of hits and sample_area() points lie on the surface up to
    point_error(), the bound across the surface: their float64 distance from it along the
    normal is at most dot(|n|, error) (0 for the flat shapes' z and the cube's face
    coordinate, which are exact)."""
    model = ANALYTIC_MODELS[kind]
    rng = np.random.default_rng(90 + KINDS.index(kind))
    n = 20_000
    o = rng.uniform(-3, 3, (n, 3))
    d = float32_exact(rng.uniform(-0.9, 0.9, (n, 3)) * [1, 1, 0.5] + [0, 0, 0.5] - o)
    o = float32_exact(o)
    t = model.intersect(_vectors(o), _vectors(d), Float(np.inf))
    hit = np.isfinite(np.asarray(t))
    assert hit.mean() > 0.2
    p_hits = _rows(model.surface_point(_vectors(o), _vectors(d), t))[hit]
    for p in (p_hits, _samples(kind, 91, n)):
        normal = np.broadcast_to(_rows(model.normal(_vectors(p), UInt32(0))), p.shape)
        normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        error = np.broadcast_to(_rows(model.point_error(_vectors(p))), p.shape)
        bound = np.sum(np.abs(normal) * error, axis=1)
        distance = np.abs(_surface_distance(kind, p))
        assert (distance <= bound).all(), (distance - bound).max()
        if kind in ("rectangle", "disk", "cube"):
            assert (distance == 0).all()


@pytest.mark.parametrize("kind", list(ANALYTIC_MODELS))
def test_plane_sections_lie_on_the_plane_and_the_surface(kind):
    """Contact curves: every point of a model's sections with random planes lies on the plane
    and on the model's surface (float64, 1e-12), the cylinder's where its height is in
    [0, 1] (its sections are clipped there when sampled), and a plane that cuts the model
    gives at least one curve (checked with the sphere, which every |offset| < 1 cuts)."""
    from instancing.models.curves import NORMAL_CYLINDER, NORMAL_SPHERE
    rng = np.random.default_rng(11)
    normal = rng.normal(size=(64, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.uniform(-0.95, 0.95, 64)
    rows, circle, c, u, v, code, stored = ANALYTIC_MODELS[kind].plane_sections(normal, offset)
    assert len(rows) > 0
    s = np.linspace(0.0, 1.0, 13)
    points = Curves(rows, circle, c, u, v).points(s)  # (K, S, 3)
    on_plane = np.einsum("ksj,kj->ks", points, normal[rows]) - offset[rows, None]
    np.testing.assert_allclose(on_plane, 0.0, atol=1e-12)
    flat = points.reshape(-1, 3)
    keep = _in_extent(kind, flat) if kind == "cylinder" else np.ones(len(flat), bool)
    np.testing.assert_allclose(_surface_distance(kind, flat)[keep], 0.0, atol=1e-12)
    if kind != "cylinder":
        assert _in_extent(kind, flat).all()
    if kind == "sphere":
        assert sorted(set(rows.tolist())) == list(range(64)) and (code == NORMAL_SPHERE).all()
    if kind == "cylinder":
        assert (code == NORMAL_CYLINDER).all()


def test_mesh_plane_sections_are_segments_on_the_plane_and_their_triangles():
    import instancing as ins
    scene = ins.load_scene({"models": {"m": {"type": "obj", "filename": str(MESH_FILE)}},
                            "instances": [{"model": "m"}]})
    rng = np.random.default_rng(12)
    normal = rng.normal(size=(4, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.uniform(-0.3, 0.3, 4)
    rows, circle, c, u, v, code, stored = scene.instances.meshes.plane_sections(0, normal, offset)
    assert len(rows) > 0 and not circle.any()
    for end in (c, c + u):
        np.testing.assert_allclose(np.einsum("kj,kj->k", end, normal[rows]), offset[rows], atol=1e-12)
    mesh = read_mesh(MESH_FILE)
    # Each segment lies in the plane of a triangle whose normal is the stored one.
    triangles = mesh.vertices[mesh.faces]
    plane = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    plane /= np.linalg.norm(plane, axis=1, keepdims=True)
    for k in rng.choice(len(rows), 20, replace=False):
        match = np.flatnonzero((np.abs(plane @ stored[k]) > 1 - 1e-12)
                               & (np.abs(np.einsum("fj,j->f", plane, c[k]) -
                                         np.einsum("fj,fj->f", plane, triangles[:, 0])) < 1e-12))
        assert len(match) >= 1, k


# -- per-lane silhouette sampling (the secondary boundary term's curves) ---------------------

def _sampled_curves(sample, viewpoint: np.ndarray, grid: np.ndarray):
    """Device samples of the curves seen from one object-space viewpoint over the u grid:
    (points (N, 3), d point / du (N, 3), valid (N,)) as float64 NumPy."""
    view = _vectors(np.tile(viewpoint, (len(grid), 1)))
    point, tangent, valid = sample(view, Float(grid.astype(np.float32)))
    return _rows(point), _rows(tangent), np.asarray(valid, bool) & np.ones(len(grid), bool)


def _distance_to_curves(points: np.ndarray, curves: Curves) -> np.ndarray:
    """Distance of each point to the nearest of the host curves (densely sampled)."""
    dense = curves.points(np.linspace(0.0, 1.0, 2001)).reshape(-1, 3)
    return np.array([np.linalg.norm(dense - p, axis=1).min() for p in points])


def _host_length(curves: Curves) -> float:
    s = np.linspace(0.0, 1.0, 4001)
    return float(np.linalg.norm(np.diff(curves.points(s), axis=1), axis=2).sum())


def _check_sampled_against_host(sample, host_curves, viewpoint, creases, pieces=12):
    """Valid samples lie on the host's curves from that viewpoint, the measure they carry
    (the integral of |d point / du| over valid u) is the host curves' total length, and
    d point / du is the derivative of the sampled point. ``pieces``: a multiple of the
    number of pieces the sampler splits u into (the grid gives each 512 points)."""
    grid = (np.arange(512 * pieces) + 0.5) / (512 * pieces)
    curves = host_curves(viewpoint, creases)
    points, tangent, valid = _sampled_curves(sample, viewpoint, grid)
    if not len(curves):
        assert not valid.any()
        return
    assert valid.any()
    on_curves = points[valid][np.linspace(0, valid.sum() - 1, 64).astype(int)]
    assert _distance_to_curves(on_curves, curves).max() < 2e-3
    measure = np.linalg.norm(tangent[valid], axis=1).sum() / len(grid)
    assert measure == pytest.approx(_host_length(curves), rel=2e-3)
    # d point / du against differences, where the forward and backward differences agree
    # (not across the end of a piece).
    step = 0.01 / pieces
    view = _vectors(np.tile(viewpoint, (len(grid), 1)))
    up, down = (_rows(sample(view, Float((grid + h).astype(np.float32)))[0]) for h in (step, -step))
    forward, backward = (up - points) / step, (points - down) / step
    scale = np.linalg.norm(tangent, axis=1, keepdims=True)
    smooth = (np.linalg.norm(forward - backward, axis=1, keepdims=True) < 0.05 * scale)[:, 0]
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(((forward + backward) / 2)[smooth], tangent[smooth], rtol=0,
                               atol=0.02 * scale.max())


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("creases", [False, True])
def test_sampled_silhouettes_are_the_models_curves_seen_from_a_point(kind, creases):
    """Each model's Dr.Jit sampler of the curves seen from a point (sample_silhouette)
    against the float64 curves of discontinuity_curves, from viewpoints outside and inside."""
    model = ANALYTIC_MODELS[kind]

    def host(viewpoint, creases):
        return _curves(kind, viewpoint[None], creases=creases)

    for viewpoint in _viewpoints(91, 6):
        _check_sampled_against_host(lambda v, u: model.sample_silhouette(v, u, creases), host,
                                    viewpoint, creases)


def _hard_normals(mesh, seed: int):
    """Smooth corner normals of ``mesh`` with a fifth of its corners tilted (hard edges
    there, as an OBJ with several vn per position has)."""
    normals = vertex_normals(mesh.vertices, mesh.faces)
    tilted = np.random.default_rng(seed).random(normals.shape[:2]) < 0.2
    normals[tilted] += 0.3 * np.random.default_rng(seed + 1).normal(size=(tilted.sum(), 3))
    return normals, tilted


def test_edge_topology_shading_jumps():
    """Reflected light can jump at every crease, flat or smooth (the geometric normal
    decides self-occlusion), and with tilted corner normals also at the coplanar edges
    that end at a tilted corner."""
    mesh = read_mesh(MESH_FILE)
    flat = EdgeTopology.of_mesh(mesh.vertices, mesh.faces)
    _, crease = flat._creases()
    np.testing.assert_array_equal(flat.shading_jump, crease)
    assert crease.any() and not crease.all()  # coplanar neighbours within its faces
    smooth = EdgeTopology.of_mesh(mesh.vertices, mesh.faces, vertex_normals(mesh.vertices, mesh.faces))
    np.testing.assert_array_equal(smooth.shading_jump, crease)
    normals, tilted = _hard_normals(mesh, 7)
    hard = EdgeTopology.of_mesh(mesh.vertices, mesh.faces, normals)
    # An edge (a, b) jumps where a corner at a or b of either of its faces is tilted.
    expected = crease.copy()
    for k, (start, direction, f0, f1) in enumerate(zip(hard.start, hard.direction, hard.face0, hard.face1)):
        for f in (f0, f1):
            for c in range(3):
                at = mesh.vertices[mesh.faces[f, c]]
                if tilted[f, c] and (np.allclose(at, start) or np.allclose(at, start + direction)):
                    expected[k] = True
    np.testing.assert_array_equal(hard.shading_jump, expected)
    assert (expected & ~crease).any() and not expected.all()


@pytest.mark.parametrize("creases, shading", [
    (creases, shading) if (creases, shading) in ((True, "flat"), (False, "smooth"), (True, "hard"))
    else pytest.param(creases, shading, marks=pytest.mark.slow)
    for creases in (False, True) for shading in ("flat", "smooth", "hard")])
def test_sampled_mesh_edges_are_the_meshs_curves_seen_from_a_point(creases, shading):
    """The mesh edge sampler (SilhouetteEdges: EDGE_DRAWS draws, one counting edge kept)
    against EdgeTopology's curves: the points lie on the silhouette and boundary edges (with
    creases: also the edges where reflected light can jump: every crease, and when hard the
    coplanar edges at tilted corner normals), along them, and the measure they carry is
    unbiased for the curves' total length (within 5 standard errors of its mean over
    random u, seeded)."""
    from instancing.models.mesh import EDGE_DRAWS, MeshLibrary
    mesh = read_mesh(MESH_FILE)
    if shading != "flat":
        mesh = mesh.with_normals(vertex_normals(mesh.vertices, mesh.faces) if shading == "smooth"
                                 else _hard_normals(mesh, 8)[0])
    library = MeshLibrary([mesh])
    edges = library.silhouette_edges([0])
    topology = library.edges(0)
    first, count = UInt32(int(edges.first[0])), UInt32(int(edges.count[0]))
    rng = np.random.default_rng(93)
    extent = np.abs(np.asarray(mesh.vertices)).max()
    for viewpoint in _viewpoints(92, 4) * extent:
        curves = Curves(*topology.discontinuity_curves(_homogeneous(viewpoint[None]), creases=creases))
        n = 1 << 16
        u, u_choice = rng.random(n), rng.random(n)
        point, tangent, valid = edges.sample(first, count, _vectors(np.tile(viewpoint, (n, 1))),
                                             Float(u.astype(np.float32)),
                                             Float(u_choice.astype(np.float32)), creases)
        point, tangent, valid = _rows(point), _rows(tangent), np.asarray(valid, bool)
        # The draws find a counting edge at least as often as independent draws would (on
        # this mesh's fixed edge order; the other shadings add edges that never count
        # without creases, and the drawing itself does not change with them).
        share = len(curves) / int(edges.count[0])
        if shading == "flat":
            assert valid.mean() > 1 - (1 - share) ** EDGE_DRAWS - 0.02
        on_curves = point[valid][np.linspace(0, valid.sum() - 1, 64).astype(int)]
        # Exact distance to the nearest host segment c + u t, t in [0, 1].
        rel = on_curves[:, None] - curves.c[None]
        t = np.clip(np.sum(rel * curves.u[None], axis=2) / np.sum(curves.u * curves.u, axis=1), 0, 1)
        gap = np.linalg.norm(rel - t[..., None] * curves.u[None], axis=2).min(axis=1)
        assert gap.max() < 1e-6 * extent
        # Each sample lies on one host segment and its tangent runs along it.
        host_directions = curves.u / np.linalg.norm(curves.u, axis=1, keepdims=True)
        unit = tangent[valid][:64] / np.linalg.norm(tangent[valid][:64], axis=1, keepdims=True)
        assert (np.abs(unit @ host_directions.T).max(axis=1) > 1 - 1e-5).all()
        weights = np.where(valid, np.linalg.norm(tangent, axis=1), 0.0)
        error = 5 * weights.std() / np.sqrt(n)
        assert abs(weights.mean() - _host_length(curves)) < error


def _loops(start: np.ndarray, step: np.ndarray) -> np.ndarray:
    """How many segments meet at each segment end (ends shared exactly, as the tracing
    computes each vertex once)."""
    ends = np.concatenate([start, start + step])
    _, counts = np.unique(np.round(ends, 12), axis=0, return_counts=True)
    return counts


@pytest.mark.parametrize("radius, distance", [(1.0, 1.2), (0.15, 1.0), (2.5, 3.2)])
def test_two_spheres_meet_along_their_circle(radius, distance):
    """The unit sphere and a sphere of ``radius`` at ``distance`` meet in the circle of
    radius sqrt(1 - x^2) in the plane x = (1 + distance^2 - radius^2) / (2 distance): the
    traced segments' ends lie on both spheres and on that plane, join into one closed loop,
    and their total length falls short of the circle's by the chords' sagitta only."""
    centre = np.array([distance, 0.0, 0.0])
    start, step = quadric_intersection("sphere", "sphere", np.eye(3) / radius, -centre / radius)
    ends = np.concatenate([start, start + step])
    plane = (1.0 + distance ** 2 - radius ** 2) / (2.0 * distance)
    np.testing.assert_allclose(np.linalg.norm(ends, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(ends - centre, axis=1), radius, atol=1e-12)
    np.testing.assert_allclose(ends[:, 0], plane, atol=1e-12)
    assert np.all(_loops(start, step) == 2)  # every end shared by exactly two segments
    circumference = 2.0 * np.pi * math.sqrt(1.0 - plane ** 2)
    length = np.linalg.norm(step, axis=1).sum()
    longest = np.linalg.norm(step, axis=1).max() / math.sqrt(1.0 - plane ** 2)  # angle, radians
    assert circumference * (1.0 - longest ** 2 / 24.0) <= length <= circumference


def test_quadric_intersections_lie_on_both_surfaces_under_affine_maps():
    """Ellipsoids and elliptic cylinders (random affine maps between the models' object
    spaces): every traced end lies on a's surface and on b's quadric in float64, and
    surfaces that do not meet give no segment."""
    rng = np.random.default_rng(5)
    kinds = list(QUADRIC_DIAGONALS)
    found = 0
    for trial in range(24):
        kind_a, kind_b = kinds[trial % 2], kinds[(trial // 2) % 2]
        linear = np.linalg.inv(np.diag(rng.uniform(0.4, 1.2, 3)) @ np.linalg.qr(rng.normal(size=(3, 3)))[0])
        offset = -linear @ rng.uniform(-0.8, 0.8, 3)
        start, step = quadric_intersection(kind_a, kind_b, linear, offset)
        if not len(start):
            continue
        found += 1
        ends = np.concatenate([start, start + step])
        d_a, d_b = np.array(QUADRIC_DIAGONALS[kind_a]), np.array(QUADRIC_DIAGONALS[kind_b])
        y = ends @ linear.T + offset
        np.testing.assert_allclose((ends * ends) @ d_a, 1.0, atol=1e-12)
        np.testing.assert_allclose((y * y) @ d_b, 1.0, atol=1e-9)
        assert np.all(_loops(start, step) <= 2)  # open only at the edge of a tube's grid
    assert found >= 12
    far = quadric_intersection("sphere", "sphere", np.eye(3), -np.array([3.0, 0.0, 0.0]))
    inside = quadric_intersection("sphere", "sphere", np.eye(3) * 4.0, np.zeros(3))
    assert len(far[0]) == len(inside[0]) == 0
