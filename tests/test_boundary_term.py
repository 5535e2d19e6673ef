"""Curve selection for the boundary term (instancing/rendering/boundary_term.py): selection
weights against closed-form film lengths, the padded sampler's distribution against its
probabilities, and sampled silhouette points of a sphere instance against the float64
tangency condition of camera rays."""

import dataclasses
import math
import warnings
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

import instancing
from instancing.core.backend import Array3f, Float, UInt32
from instancing.models.curves import Curves
from instancing.rendering import boundary_term as bt
from instancing.scene.camera import CameraBatch
from instancing.validation.gradient_check import contact_scene, gradient_image, mirror_floor_scene

SCENES = Path(__file__).resolve().parents[1] / "scenes"

#: float32 unit roundoff.
EPS32 = 2.0 ** -24
WIDTH, HEIGHT, FOV = 64, 48, 50.0
CAMERA = {"type": "perspective", "fov": FOV, "width": WIDTH, "height": HEIGHT,
          "to_world": [{"look_at": {"origin": [0, 0, -10], "target": [0, 0, 0], "up": [0, 1, 0]}}]}


def _camera():
    return instancing.parse_camera(CAMERA)


def _pixels_per_unit(depth: float) -> float:
    """Film pixels per world unit for a segment parallel to the film at this depth."""
    return 0.5 * WIDTH / (depth * math.tan(math.radians(FOV) / 2))


def _segments(starts, directions, instance=None) -> Curves:
    starts, directions = np.asarray(starts, np.float64), np.asarray(directions, np.float64)
    k = len(starts)
    return Curves(np.arange(k) if instance is None else np.asarray(instance), np.zeros(k, bool),
                  starts, directions, np.zeros((k, 3)))


def _identity(k: int) -> np.ndarray:
    return np.broadcast_to(np.eye(4), (k, 4, 4)).copy()


def test_selection_weights_are_film_lengths_of_the_curves():
    """Segments parallel to the film project linearly: a segment twice as long gets twice
    the weight, one twice as far half of it; a circle facing the camera gets its 8-chord
    polygon's film perimeter, 16 sin(pi/8) times its film radius."""
    camera = _camera()
    # Camera at z = -10 looking along +z: segments in planes z = 0 and z = 10.
    curves = _segments([[-1.0, 0.5, 0], [-2.0, -0.5, 0], [-2.0, 0.3, 10.0]],
                       [[1.0, 0, 0], [2.0, 0, 0], [2.0, 0, 0]])
    w = bt.selection_weights(curves, _identity(3), camera)
    assert (w > 0).all()
    ppu = _pixels_per_unit(10.0)
    # float32 projection of float64 points: a few units of roundoff of the film coordinates.
    np.testing.assert_allclose(w, [1.0 * ppu, 2.0 * ppu, 2.0 * _pixels_per_unit(20.0)], rtol=1e-5)
    circle = Curves(np.zeros(1, np.int64), np.ones(1, bool), np.zeros((1, 3)),
                    np.array([[0.7, 0, 0]]), np.array([[0, 0.7, 0]]))
    w_circle = bt.selection_weights(circle, _identity(1), camera)
    np.testing.assert_allclose(w_circle, 16 * math.sin(math.pi / 8) * 0.7 * ppu, rtol=1e-5)


def test_selection_weights_follow_the_instance_transform():
    """The same object-space segment under a transform that doubles it (scale 2 along x)
    gets twice the weight of the untransformed one."""
    camera = _camera()
    curves = _segments([[-0.5, 0, 0], [-0.5, 0, 0]], [[1.0, 0, 0], [1.0, 0, 0]])
    m = _identity(2)
    m[1, 0, 0] = 2.0
    w = bt.selection_weights(curves, m, camera)
    np.testing.assert_allclose(w[1] / w[0], 2.0, rtol=1e-5)


def test_curves_behind_the_camera_keep_a_floor_weight():
    camera = _camera()
    curves = _segments([[-1.0, 0, 0], [-1.0, 0, 5.0], [-1.0, 0, -20.0]], [[2.0, 0, 0]] * 3)
    w = bt.selection_weights(curves, _identity(3), camera)
    visible = w[:2]
    # The curve behind the camera has no film length: the floor, a fraction of the mean
    # (lengths are float32 sums: a few units of roundoff).
    np.testing.assert_allclose(w[2], bt.WEIGHT_FLOOR * visible.astype(np.float64).sum() / 3, rtol=4 * EPS32)
    assert (visible > 10 * w[2]).all()


@pytest.mark.parametrize("count, capacity", [(1, 64), (5, 64), (64, 64), (65, 256), (256, 256),
                                             (257, 1024)])
def test_build_pads_to_a_power_of_four_of_at_least_64(count, capacity):
    rng = np.random.default_rng(count)
    curves = _segments(rng.normal(size=(count, 3)), rng.normal(size=(count, 3)), np.arange(1, count + 1))
    sampler = bt.BoundarySampler.build(curves, rng.uniform(0.1, 1.0, count))
    assert sampler.count == capacity
    assert all(len(np.asarray(a)) == capacity for a in (sampler.instance, sampler.cdf, sampler.probability))


def test_sampler_never_picks_padding_and_picks_curves_by_their_probability():
    """Five curves (instances 1..5; padding has instance 0) with weights spanning 30x, in
    a capacity of 64: over 2^17 uniform u_pick values, and the extremes 0 and the largest
    float below 1, every picked index is a real curve's (< 5), reported with its
    probability weight / total, at a frequency within 5 binomial standard errors of that
    probability (fixed seed)."""
    rng = np.random.default_rng(10)
    weights = np.array([0.1, 3.0, 0.5, 1.2, 2.2])
    curves = _segments(rng.normal(size=(5, 3)), rng.normal(size=(5, 3)), np.arange(1, 6))
    sampler = bt.BoundarySampler.build(curves, weights)
    n = 1 << 17
    u = rng.random(n, dtype=np.float32)
    u[:2] = [0.0, np.nextafter(np.float32(1), np.float32(0))]
    curve, instance, _, _, probability, present = sampler.sample(Float(u), Float(np.full(n, 0.5, np.float32)))
    curve, instance = np.asarray(curve), np.asarray(instance)
    probability = np.asarray(probability, np.float64)
    assert curve.max() < 5  # never one of the padding entries
    assert np.asarray(present).all()
    np.testing.assert_array_equal(instance, curve + 1)
    assert curve[0] == 0 and curve[1] == 4
    expected = weights / weights.sum()
    # float32 storage of the probabilities.
    np.testing.assert_allclose(probability, expected[curve], rtol=2 * EPS32)
    freq = np.bincount(curve, minlength=5) / n
    se = np.sqrt(expected * (1 - expected) / n)
    assert (np.abs(freq - expected) < 5 * se).all(), (freq, expected)


def test_joined_sampler_picks_each_views_curves_by_that_views_probability():
    """Three views of a camera batch: 5 shadow curves (capacity 64), none, and 70 (capacity
    256) with their own weights, lights and offsets, joined into one table of 3 x 256 entries.
    Lanes of view v pick only view v's curves (instances 100 v + 1 ...), with view v's
    probabilities and each curve's own light and offset, at frequencies within 5 binomial
    standard errors; the view without curves is reported absent (fixed seed)."""
    rng = np.random.default_rng(12)
    counts = (5, 0, 70)
    weights = [rng.uniform(0.1, 3.0, k) for k in counts]
    lights = [rng.integers(0, 4, k) for k in counts]
    offsets = [rng.uniform(0.01, 0.1, k) for k in counts]
    samplers = [bt.BoundarySampler.build(
        _segments(rng.normal(size=(k, 3)), rng.normal(size=(k, 3)), 100 * v + 1 + np.arange(k)),
        weights[v], lights[v], offsets[v]) if k else None for v, k in enumerate(counts)]
    joined = bt.BoundarySampler.joined(samplers)
    assert joined.count == 256 and dr.width(joined.cdf) == 3 * 256
    n = 1 << 17
    view = np.repeat(np.arange(3, dtype=np.uint32), n)
    u = rng.random(3 * n, dtype=np.float32)
    curve, instance, point, _, probability, present = joined.sample(
        Float(u), Float(np.full(3 * n, 0.5, np.float32)), UInt32(view))
    curve, instance, present = np.asarray(curve), np.asarray(instance), np.asarray(present)
    probability = np.asarray(probability, np.float64)
    np.testing.assert_array_equal(present, view != 1)
    for v in (0, 2):
        mine = view == v
        local = curve[mine] - v * 256
        assert local.min() >= 0 and local.max() < counts[v]
        np.testing.assert_array_equal(instance[mine], 100 * v + 1 + local)
        expected = weights[v] / weights[v].sum()
        np.testing.assert_allclose(probability[mine], expected[local], rtol=2 * EPS32)
        np.testing.assert_array_equal(np.asarray(dr.gather(UInt32, joined.light, UInt32(curve[mine]))),
                                      lights[v][local])
        np.testing.assert_allclose(np.asarray(dr.gather(Float, joined.offset, UInt32(curve[mine]))),
                                   offsets[v][local], rtol=EPS32)
        freq = np.bincount(local, minlength=counts[v]) / n
        se = np.sqrt(expected * (1 - expected) / n)
        assert (np.abs(freq - expected) < 5 * se).all(), v
    assert bt.BoundarySampler.joined([None, None]) is None
    assert bt.BoundarySampler.joined(samplers[:1]) is samplers[0]


def test_sampled_points_and_tangents_follow_the_curve_parameterisation():
    """point = c + u a(s) + v b(s) and tangent = d point / ds, against float64 closed forms
    (segments: a = s; circles: cos 2 pi s, sin 2 pi s) and central differences."""
    rng = np.random.default_rng(11)
    c, u, v = rng.normal(size=(3, 2, 3))
    curves = Curves(np.array([1, 2]), np.array([False, True]), c, u, v)
    sampler = bt.BoundarySampler.build(curves, np.array([1.0, 1.0]))
    n = 4096
    s = rng.random(n, dtype=np.float32).astype(np.float64)
    pick = np.where(np.arange(n) % 2 == 0, 0.25, 0.75).astype(np.float32)
    curve, instance, point, tangent, _, _ = sampler.sample(Float(pick), Float(s.astype(np.float32)))
    k = np.asarray(curve)
    np.testing.assert_array_equal(np.asarray(instance), k + 1)
    point, tangent = np.asarray(point, np.float64).T, np.asarray(tangent, np.float64).T
    circle = curves.circle[k][:, None]

    def x(t):
        a = np.where(circle, np.cos(2 * np.pi * t)[:, None], t[:, None])
        b = np.where(circle, np.sin(2 * np.pi * t)[:, None], 0.0)
        return c[k] + u[k] * a + v[k] * b

    # float32 curve data and trigonometry: ~1e-6 of the curve's size (|c|, |u|, |v| < 4).
    np.testing.assert_allclose(point, x(s), atol=1e-5)
    h = 1e-5
    np.testing.assert_allclose(tangent, (x(s + h) - x(s - h)) / (2 * h), atol=1e-4)


def _sphere_scene(moving: bool):
    m = np.array([[1.4, 0.3, -0.2, 0.5], [0.1, 0.7, 0.25, -0.3], [-0.4, 0.2, 1.1, 1.0], [0, 0, 0, 1.0]])
    scene = instancing.load_scene({
        "instances": [{"model": "sphere", "to_world": [{"matrix": m.tolist()}]},
                      {"model": "cube", "to_world": [{"translate": [3, 0, 2]}, {"scale": 0.5}]}],
        "camera": CAMERA})
    if moving:
        scene.set_moving(np.array([0]))
    return scene


def test_boundary_sampler_is_none_without_moving_instances():
    scene = _sphere_scene(moving=False)
    assert len(scene.moving_instances) == 0
    assert bt.boundary_sampler(scene, scene.camera) is None
    assert bt.boundary_term(None, scene, CameraBatch((scene.camera,)), None, 3, 4, None, 1 << 10, None,
                            0.5) is None
    scene.set_moving(np.array([0]))
    assert bt.boundary_sampler(scene, scene.camera) is not None


def test_boundary_sampler_is_none_when_the_moving_instances_show_no_curve():
    """A camera inside a moving sphere sees no silhouette of it."""
    scene = _sphere_scene(moving=True)
    inside = dict(CAMERA, to_world=[{"look_at": {"origin": [0.5, -0.3, 1.0], "target": [0, 0, 5],
                                                 "up": [0, 1, 0]}}])
    assert bt.boundary_sampler(scene, instancing.parse_camera(inside)) is None


def test_shadow_curves_fall_along_the_rays_of_their_own_light():
    """With a point light at the camera (its shadows hide behind their casters: skipped)
    listed before one off the camera, every sampled shadow curve point p falls on the
    receiver z along the ray from the off-camera light: z - L parallel to p - L."""
    off_camera = np.array([2.0, 3.0, -6.0])
    scene = instancing.load_scene({
        "instances": [{"id": "ball", "model": "sphere", "to_world": [{"scale": 0.8}]},
                      {"id": "wall", "model": "rectangle",
                       "to_world": [{"translate": [0, 0, 3]}, {"scale": 6}]}],
        "lights": [{"type": "point", "position": [0, 0, -10], "intensity": 1},
                   {"type": "point", "position": off_camera.tolist(), "intensity": 1}],
        "camera": CAMERA})
    scene.set_moving(np.array([0]))
    sampler = bt.shadow_samplers(scene, [scene.camera])[0]
    lanes = 4096
    u = np.random.default_rng(5).random((2, lanes)).astype(np.float32)
    curve, instance, x_obj, tangent, _, _ = sampler.sample(Float(u[0]), Float(u[1]))
    rows = scene.instances.forward(instance)
    p = bt.world_point(rows, x_obj)
    z, _, found = bt.shadow_receivers(scene, scene.light_set(), bt.dr.gather(UInt32, sampler.light, curve),
                                      bt.dr.gather(Float, sampler.offset, curve), p,
                                      bt.world_vector(rows, tangent), bt.Bool(True))
    found = np.array(found)
    assert found.mean() > 0.9
    to_p, to_z = (np.array(a).T.astype(np.float64)[found] - off_camera for a in (p, z))
    sine = np.linalg.norm(np.cross(to_p, to_z), axis=1) / (np.linalg.norm(to_p, axis=1)
                                                           * np.linalg.norm(to_z, axis=1))
    assert sine.max() < 1e-5


def test_sampled_silhouette_points_project_to_camera_rays_tangent_to_the_ellipsoid():
    """Points sampled on a moving sphere instance's curve, mapped to world space and
    projected to the film: the camera ray through that film position passes through them
    and touches the ellipsoid (float64 discriminant ~ 0 in object space)."""
    scene = _sphere_scene(moving=True)
    camera = scene.camera
    sampler = bt.boundary_sampler(scene, camera)
    # One curve (the silhouette circle), padded: its cumulative weight is 1 at once.
    assert sampler.count == bt.MIN_CURVE_CAPACITY and np.asarray(sampler.cdf)[0] == 1
    rng = np.random.default_rng(12)
    n = 2048
    _, instance, x_obj, _, probability, _ = sampler.sample(Float(rng.random(n, dtype=np.float32)),
                                                        Float(rng.random(n, dtype=np.float32)))
    assert (np.asarray(instance) == 0).all() and (np.asarray(probability) == 1).all()
    x_obj = np.asarray(x_obj, np.float64).T
    m, m_inv = scene.to_world[0], np.linalg.inv(scene.to_world[0])
    world = x_obj @ m[:3, :3].T + m[:3, 3]
    fx, fy, front = camera.project(Array3f(*[Float(world[:, k].astype(np.float32)) for k in range(3)]))
    fx, fy = np.asarray(fx, np.float64), np.asarray(fy, np.float64)
    assert np.asarray(front).all()
    # The whole silhouette lies on the film here.
    assert (fx > 0).all() and (fx < WIDTH).all() and (fy > 0).all() and (fy < HEIGHT).all()
    o, d = camera.rays(Float((fx / WIDTH).astype(np.float32)), Float((fy / HEIGHT).astype(np.float32)))
    o, d = np.asarray(o, np.float64).T, np.asarray(d, np.float64).T
    # The ray passes through the world point (float32 film round trip: ~1e-6 relative).
    to_point = world - o
    miss = np.linalg.norm(np.cross(d, to_point), axis=1) / np.linalg.norm(to_point, axis=1)
    assert miss.max() < 1e-5
    # Tangent to the ellipsoid: in object space the quadratic's discriminant vanishes,
    # relative to its terms (closest approach to the centre exactly 1).
    o_obj, d_obj = o @ m_inv[:3, :3].T + m_inv[:3, 3], d @ m_inv[:3, :3].T
    closest = o_obj - (np.sum(o_obj * d_obj, 1) / np.sum(d_obj * d_obj, 1))[:, None] * d_obj
    np.testing.assert_allclose(np.linalg.norm(closest, axis=1), 1.0, atol=1e-5)
    # Rays just inside the silhouette (towards the centre) hit, rays just outside miss.
    centre = m[:3, 3]
    inward = centre - world
    inward -= np.sum(inward * d, 1)[:, None] * d
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    for sign, expect_hit in ((1.0, True), (-1.0, False)):
        target = world + sign * 1e-3 * inward
        d_side = (target - o) / np.linalg.norm(target - o, axis=1, keepdims=True)
        hits = scene.intersect(o, d_side)
        hit_sphere = hits.instance == 0
        assert hit_sphere.all() if expect_hit else not hit_sphere.any()


def test_extent_test_is_the_same_on_host_and_device_and_matches_barycentric_coordinates():
    """_within_extent (one code path for NumPy and Dr.Jit): the square, the disk and a
    triangle against float64 closed forms (barycentric coordinates by a linear solve)."""
    rng = np.random.default_rng(11)
    n = 4000
    local = rng.uniform(-1.3, 1.3, (n, 3)) * [1, 1, 0]
    extent = rng.integers(0, 3, n)
    corner = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0]
    edge1, edge2 = (rng.uniform(-1.5, 1.5, (n, 3)) * [1, 1, 0] for _ in range(2))
    host = bt._within_extent(local.T, extent, corner.T, edge1.T, edge2.T)
    device = np.array(bt._within_extent(tuple(Float(c) for c in local.T), UInt32(extent),
                                        *(Array3f(*a.T) for a in (corner, edge1, edge2))))
    st = np.array([np.linalg.solve(np.stack([a[:2], b[:2]], axis=1), p[:2] - c[:2])
                   for p, c, a, b in zip(local, corner, edge1, edge2)])
    triangle = (st >= 0).all(axis=1) & (st.sum(axis=1) <= 1)
    square = (np.abs(local) <= 1).all(axis=1)
    disk = np.hypot(local[:, 0], local[:, 1]) <= 1
    expected = np.choose(extent, [square, disk, triangle])
    # Away from the boundaries (the test's slack is 1e-5 relative), all agree exactly.
    margin = np.choose(extent, [np.abs(np.abs(local[:, :2]).max(axis=1) - 1),
                                np.abs(np.hypot(local[:, 0], local[:, 1]) - 1),
                                np.minimum(np.abs(st).min(axis=1), np.abs(st.sum(axis=1) - 1))])
    clear = margin > 1e-4
    assert clear.mean() > 0.99
    np.testing.assert_array_equal(host[clear], expected[clear])
    np.testing.assert_array_equal(device[clear], expected[clear])


def _contact_curve_length(model: str, receiver: str) -> tuple[float, int, float]:
    """Total world length of the contact curves of the contact cases' ``model`` in
    ``receiver`` where they lie on their receiving plane (a float64 check: barycentric
    coordinates in the curve's triangle, or the square of a face or floor), the number of
    curves with such a part, and the largest distance of those points from the plane z = 0
    and from the model's surface (unit sphere or cube in its object space)."""
    mesh = str(SCENES / "meshes" / "torus.obj")
    scene = instancing.load_scene(contact_scene(model, 16, mesh, receiver))
    scene.set_moving(np.array([0]))
    sampler = bt.contact_samplers(scene, [scene.camera])[0]
    real = np.array(sampler.cdf) <= 1.0
    curves = Curves(*(np.array(a)[real] for a in (sampler.instance, sampler.circle)),
                    *(np.array(a).T[real].astype(np.float64) for a in (sampler.c, sampler.u, sampler.v)))
    data = sampler.contact
    other, extent = (np.array(a)[real] for a in (data.other, data.extent))
    corner, edge1, edge2 = (np.array(a).T[real].astype(np.float64)
                            for a in (data.corner, data.edge1, data.edge2))
    s = np.linspace(0.0, 1.0, 4001)
    to_curve = scene.instances.to_world_of(curves.instance)
    world = np.einsum("kij,ksj->ksi", to_curve[:, :3, :3], curves.points(s)) + to_curve[:, None, :3, 3]
    from_other = scene.instances.from_world_of(other)
    local = np.einsum("kij,ksj->ksi", from_other[:, :3, :3], world) + from_other[:, None, :3, 3]
    gram = np.stack([edge1[:, :2], edge2[:, :2]], axis=2) + np.where(
        extent == bt.EXTENT_TRIANGLE, 0.0, 1.0)[:, None, None] * np.eye(2)  # regular for all
    st = np.linalg.solve(gram[:, None], (local[..., :2] - corner[:, None, :2])[..., None])[..., 0]
    inside = np.where((extent == bt.EXTENT_TRIANGLE)[:, None],
                      (st >= 0).all(axis=-1) & (st.sum(axis=-1) <= 1),
                      (np.abs(local) <= 1 + 1e-6).all(axis=-1))  # float32-stored curves
    # Each step counts by its share of inside ends (a boundary crossing costs half a step).
    share = 0.5 * (inside[:, 1:].astype(float) + inside[:, :-1])
    length = (np.linalg.norm(np.diff(world, axis=1), axis=-1) * share).sum()
    from_obj = scene.instances.from_world_of(np.array([0]))[0]
    obj = world @ from_obj[:3, :3].T + from_obj[:3, 3]
    surface = np.linalg.norm(obj, axis=-1) if model == "sphere" else np.abs(obj).max(axis=-1)
    off = max(np.abs(world[..., 2][inside]).max(), np.abs(surface - 1)[inside].max())
    return length, int(inside.any(axis=1).sum()), off


@pytest.mark.parametrize("model", ["sphere", "cube"])
def test_contact_curves_on_mesh_triangles_partition_the_section_with_the_floor(model):
    """An instance sinking into a floor of mesh tiles: each tile triangle is a receiving
    plane, the section clipped to it (a sphere); or the tiles are cut by the cube's faces,
    clipped to each face's square (a cube). Either way the parts give the same curve, of
    the same length, as the flat floor's one plane."""
    tiles, parts, off = _contact_curve_length(model, "tiles")
    floor, _, floor_off = _contact_curve_length(model, "floor")
    assert parts >= 2
    assert max(off, floor_off) < 1e-5
    assert abs(tiles - floor) < 2e-4 * floor


@pytest.mark.parametrize("radius, distance", [(0.15, 1.0), (1.0, 1.2)])
def test_points_moved_onto_two_spheres_circle_sample_it_with_its_exact_density(radius, distance):
    """Where two spheres meet (their circle: see test_models), the sampled points of the
    traced segments land on both spheres, and E[|dy/ds| / P(curve)] over the samples, the
    Monte Carlo length of the curve by the density the boundary term divides by, is the
    circle's length: not the segments' (shorter by their sagitta, more than ten times
    the tolerance on the smaller circle)."""
    scene = instancing.load_scene({"instances": [
        {"model": "sphere"},
        {"model": "sphere", "to_world": [{"translate": [distance, 0, 0]}, {"scale": radius}]}]})
    curves, fields = bt._quadric_contacts(scene, np.array(["sphere", "sphere"]), {0})
    chords = np.linalg.norm(curves.u, axis=1)
    sampler = bt.BoundarySampler.build(curves, chords)
    sampler.contact = bt.ContactData.build(*fields, sampler.count)
    rng = np.random.default_rng(3)
    n = 1 << 20
    curve, instance, x, tangent, probability, found = sampler.sample(
        *(Float(rng.random(n, np.float32)) for _ in range(2)))
    x, tangent, on_curve = bt._onto_intersection(scene, sampler, curve, instance, x, tangent)
    assert np.all(np.array(on_curve & found))
    points = np.array(x).T.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=4 * EPS32)
    np.testing.assert_allclose(np.linalg.norm(points - [distance, 0, 0], axis=1), radius,
                               atol=8 * EPS32)
    plane = (1.0 + distance ** 2 - radius ** 2) / (2.0 * distance)
    circumference = 2.0 * np.pi * math.sqrt(1.0 - plane ** 2)
    estimate = np.mean(np.array(dr.norm(tangent)) / np.array(probability), dtype=np.float64)
    assert abs(estimate - circumference) < 1e-5 * circumference
    if radius < 1.0:
        assert circumference - chords.sum() > 1e-4 * circumference


def test_a_recorded_steps_key_tells_contacts_of_two_quadrics_from_plane_contacts():
    """Whether the kernel moves points onto the curve of two quadrics is decided when it is
    traced: the recording key (the Python state of the curves) must change with it."""
    from instancing.core.kernel_recording import python_state
    zeros = np.zeros((1, 3))
    tables = [bt.ContactData.build(np.zeros(1, np.int64), np.array([extent]), zeros,
                                   np.zeros((1, 3, 3)), np.zeros(1, np.int64), zeros, 64)
              for extent in (bt.EXTENT_SQUARE, bt.EXTENT_SPHERE)]
    assert [t.quadrics for t in tables] == [False, True]
    assert python_state(tables[0]) != python_state(tables[1])


def test_curved_instances_apart_give_no_contact_curves():
    """Two ellipsoids whose boxes do not meet, one moving: no pair, no curves, no error."""
    scene = instancing.load_scene({"instances": [
        {"model": "sphere", "to_world": [{"scale": [1.0, 0.5, 0.7]}]},
        {"model": "sphere", "to_world": [{"translate": [4, 0, 0]}]}]})
    scene.set_moving(np.array([0]))
    assert bt._quadric_contacts(scene, np.array(["sphere", "sphere"]), {0}) is None
    assert bt.contact_samplers(scene, [scene.camera]) == [None]


def _sphere_field(count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random spheres in a 10-unit box: (to_world (count, 4, 4), centres, radii)."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-5.0, 5.0, (count, 3))
    radius = rng.uniform(0.2, 0.6, count)
    to_world = np.zeros((count, 4, 4))
    to_world[:, [0, 1, 2], [0, 1, 2]] = radius[:, None]
    to_world[:, :3, 3], to_world[:, 3, 3] = centre, 1.0
    return to_world, centre, radius


@pytest.mark.parametrize("light", [{"type": "point", "position": [3.0, -9.0, 4.0], "intensity": [1, 1, 1]},
                                   {"type": "directional", "direction": [0.4, 0.7, -0.6],
                                    "irradiance": [1, 1, 1]}])
def test_shadow_casters_hold_every_sphere_between_a_moving_one_and_the_light(light):
    """Every sphere that a segment from a point of a moving sphere to the light meets
    (float64, exact sphere tests) is among the light's casters; and the casters are a
    small part of the field (not every box of an axis-aligned span)."""
    to_world, centre, radius = _sphere_field(600, 3)
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": to_world}],
                                   "lights": [light]})
    moving = np.array([5, 77, 300, 421])
    scene.set_moving(moving)
    casters = bt.shadow_casters(scene, 0, scene.rendering_lights[0])
    rng = np.random.default_rng(0)
    unit = rng.normal(size=(4000, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    who = rng.choice(moving, 4000)
    start = centre[who] + radius[who, None] * unit
    if light["type"] == "point":
        end = np.asarray(light["position"], np.float64)
    else:
        end = start - 40.0 * np.asarray(light["direction"]) / np.linalg.norm(light["direction"])
    d = end - start
    # Closest point of each segment to each sphere's centre.
    s = np.clip(np.einsum("ksc,kc->ks", centre[None] - start[:, None], d)
                / np.einsum("kc,kc->k", d, d)[:, None], 0.0, 1.0)
    gap = np.linalg.norm(start[:, None] + s[..., None] * d[:, None] - centre[None], axis=-1)
    blocking = np.flatnonzero((gap <= radius[None]).any(axis=0))
    assert len(np.setdiff1d(blocking, moving)) > 5
    assert np.isin(blocking, casters).all()
    assert np.isin(moving, casters).all()
    assert len(casters) < 0.25 * len(centre)


def test_quadric_contacts_take_each_meeting_pair_with_a_moving_sphere_once():
    """Contact curves between curved instances: exactly the pairs of spheres that cut each
    other (centre distance between |r1 - r2| and r1 + r2, float64) with at least one of
    them moving, each pair once, also where both move."""
    to_world, centre, radius = _sphere_field(300, 4)
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": to_world}]})
    distance = np.linalg.norm(centre[:, None] - centre[None], axis=-1)
    cut = (distance < radius[:, None] + radius[None]) & (distance > np.abs(radius[:, None] - radius[None]))
    np.fill_diagonal(cut, False)
    # Movers: spheres that cut others, two of them cutting each other.
    i, j = np.nonzero(np.triu(cut))
    moving = np.unique(np.concatenate([[i[0], j[0]], i[5:40:7]]))
    scene.set_moving(moving)
    curves, fields = bt._quadric_contacts(scene, np.array(["sphere"] * len(centre)), set(moving.tolist()))
    found = {tuple(sorted(p)) for p in zip(curves.instance.tolist(), fields[0].tolist())}
    expected = {tuple(p) for p in zip(*np.nonzero(np.triu(cut) & (np.isin(np.arange(len(centre)), moving)[:, None]
                                                              | np.isin(np.arange(len(centre)), moving)[None])))}
    assert len(expected) > len(moving)
    assert found == expected
    # Each pair once: its curves all come from one ordering of the two.
    assert len({p for p in zip(curves.instance.tolist(), fields[0].tolist())}) == len(found)


def test_crease_scales_lower_the_terrains_silhouette_noise_and_keep_its_mean():
    """The faceted terrain (scenes/terrain.json) shows 148 000 creases and 1 300 silhouette
    edges, whose film length is 3 % of theirs; its horizon's jump is far larger than a
    shallow crease's. Creases drawn by how far their normals turn
    (:attr:`~instancing.models.curves.EdgeTopology.jump_scale`) against all curves drawn by
    film length alone (their scales dropped): the variance of the edge term over 12 seeds,
    summed over the pixels, is 0.36x (0.36 - 0.43x over three sets of seeds; asserted below
    0.6x), and the image sums' means agree within 3 standard errors (within 0.5 in those
    sets), as a change of the sampling density alone leaves the estimator's mean."""
    def images(scaled: bool) -> np.ndarray:
        scene = instancing.load_scene(SCENES / "terrain.json")
        scene.set_camera(scene.camera.with_size(64, 48))
        if not scaled:
            found = scene.discontinuity_curves
            scene.discontinuity_curves = lambda *a, **k: dataclasses.replace(found(*a, **k), scale=None)
        params = instancing.traverse(scene)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (the other terms are left out on purpose)
            return np.stack([gradient_image(params, "terrain.translation", [1.0, 0.0, 0.0], seed=seed,
                                            integrator="direct", spp=1, sppc=0, sppp=16, sppi=0)
                             for seed in range(12)])

    scaled, flat = images(True), images(False)
    assert scaled.var(axis=0, ddof=1).sum() < 0.6 * flat.var(axis=0, ddof=1).sum()
    sums = [images.sum(axis=(1, 2, 3)) for images in (scaled, flat)]
    error = math.sqrt(sum(s.var(ddof=1) / len(s) for s in sums))
    assert abs(sums[0].mean() - sums[1].mean()) < 3.0 * error, (sums, error)


def test_only_plain_diffuse_meshes_scale_their_creases():
    """The normals' turn bounds a crease's jump on a plain diffuse surface; a glossy one's
    highlight may jump far more across a shallow crease (a flat-shaded torus in
    roughconductor: the scaled density had 1.4 - 3.1x the edge term's variance). Two faceted
    tori seen alike: the diffuse one's creases carry scales below 1, every curve of the
    rough conductor's scale 1."""
    torus = str(SCENES / "meshes" / "torus.obj")
    scene = instancing.load_scene({
        "models": {"torus": {"type": "obj", "filename": torus, "face_normals": True}},
        "materials": {"matte": {"type": "diffuse"}, "metal": {"type": "roughconductor", "alpha": 0.05}},
        "instances": [{"id": "a", "model": "torus", "material": "matte",
                       "to_world": [{"translate": [-2, 0, 0]}]},
                      {"id": "b", "model": "torus", "material": "metal",
                       "to_world": [{"translate": [2, 0, 0]}]}],
        "camera": {"type": "perspective", "fov": 60, "width": 32, "height": 24,
                   "to_world": [{"look_at": {"origin": [0, -6, 4], "target": [0, 0, 0], "up": [0, 0, 1]}}]}})
    curves = scene.discontinuity_curves(np.array([0.0, -6.0, 4.0]), np.array([0, 1]))
    scales = curves.scales
    assert (scales[curves.instance == 0] < 1.0).sum() > 100
    np.testing.assert_array_equal(scales[curves.instance == 1], 1.0)


def _mirror_floor(floor: dict, **camera):
    """mirror_floor_scene with its ellipsoid moving (a grad-enabled translation)."""
    description = mirror_floor_scene(16, floor)
    if camera:
        description["camera"]["to_world"] = [{"look_at": camera}]
    scene = instancing.load_scene(description)
    params = instancing.traverse(scene)
    dr.enable_grad(params["obj.translation"])
    params.update()
    return scene


def test_silhouettes_are_sought_in_flat_mirrors_that_show_the_moving_instances():
    """The mirror floor's plane (y = -1.2, normal +y) carries the moving ellipsoid's curves
    seen from the camera's mirror image; a diffuse floor, or a camera that does not see the
    floor, carries none."""
    scene = _mirror_floor({"type": "conductor", "material": "Ag"})
    sampler = bt.mirror_sampler(scene, scene.camera)
    assert sampler is not None
    used = sampler.host["cdf"] <= 1.0  # (padding: 2)
    assert used.sum() > 0 and set(sampler.host["instance"][used]) == {0}
    np.testing.assert_allclose(sampler.mirror.host["normal"][used], [[0.0, 1.0, 0.0]] * used.sum(), atol=1e-6)
    np.testing.assert_allclose(sampler.mirror.host["offset"][used], -1.2, atol=1e-6)
    diffuse = _mirror_floor({"type": "diffuse"})
    assert bt.mirror_sampler(diffuse, diffuse.camera) is None
    # Looking up, away from the floor.
    away = _mirror_floor({"type": "conductor", "material": "Ag"},
                         origin=[0, 0, -5], target=[0, 5, -5], up=[0, 0, 1])
    assert bt.mirror_sampler(away, away.camera) is None
