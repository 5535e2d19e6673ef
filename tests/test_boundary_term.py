"""Curve selection for the boundary term (instancing/rendering/boundary_term.py): selection
weights against closed-form film lengths, the padded sampler's distribution against its
probabilities, and sampled silhouette points of a sphere instance against the float64
tangency condition of camera rays."""

import math

import numpy as np
import pytest

import instancing
from instancing.core.backend import Array3f, Float
from instancing.models.curves import Curves
from instancing.rendering import boundary_term as bt

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


@pytest.mark.parametrize("count, capacity", [(1, 1), (2, 2), (5, 8), (8, 8), (9, 16)])
def test_build_pads_to_a_power_of_two(count, capacity):
    rng = np.random.default_rng(count)
    curves = _segments(rng.normal(size=(count, 3)), rng.normal(size=(count, 3)), np.arange(1, count + 1))
    sampler = bt.BoundarySampler.build(curves, rng.uniform(0.1, 1.0, count))
    assert sampler.count == capacity
    assert all(len(np.asarray(a)) == capacity for a in (sampler.instance, sampler.cdf, sampler.probability))


def test_sampler_never_picks_padding_and_picks_curves_by_their_probability():
    """Five curves (instances 1..5; padding has instance 0) with weights spanning 30x, in
    a capacity of 8: over 2^17 uniform u_pick values, and the extremes 0 and the largest
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
    curve, instance, _, _, probability = sampler.sample(Float(u), Float(np.full(n, 0.5, np.float32)))
    curve, instance = np.asarray(curve), np.asarray(instance)
    probability = np.asarray(probability, np.float64)
    assert curve.max() < 5  # never one of the three padding entries
    np.testing.assert_array_equal(instance, curve + 1)
    assert curve[0] == 0 and curve[1] == 4
    expected = weights / weights.sum()
    # float32 storage of the probabilities.
    np.testing.assert_allclose(probability, expected[curve], rtol=2 * EPS32)
    freq = np.bincount(curve, minlength=5) / n
    se = np.sqrt(expected * (1 - expected) / n)
    assert (np.abs(freq - expected) < 5 * se).all(), (freq, expected)


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
    curve, instance, point, tangent, _ = sampler.sample(Float(pick), Float(s.astype(np.float32)))
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
    assert bt.boundary_term(None, scene, scene.camera, None, 3, 4, None, 1 << 10, None, 0.5) is None
    scene.set_moving(np.array([0]))
    assert bt.boundary_sampler(scene, scene.camera) is not None


def test_boundary_sampler_is_none_when_the_moving_instances_show_no_curve():
    """A camera inside a moving sphere sees no silhouette of it."""
    scene = _sphere_scene(moving=True)
    inside = dict(CAMERA, to_world=[{"look_at": {"origin": [0.5, -0.3, 1.0], "target": [0, 0, 5],
                                                 "up": [0, 1, 0]}}])
    assert bt.boundary_sampler(scene, instancing.parse_camera(inside)) is None


def test_sampled_silhouette_points_project_to_camera_rays_tangent_to_the_ellipsoid():
    """Points sampled on a moving sphere instance's curve, mapped to world space and
    projected to the film: the camera ray through that film position passes through them
    and touches the ellipsoid (float64 discriminant ~ 0 in object space)."""
    scene = _sphere_scene(moving=True)
    camera = scene.camera
    sampler = bt.boundary_sampler(scene, camera)
    assert sampler.count == 1
    rng = np.random.default_rng(12)
    n = 2048
    _, instance, x_obj, _, probability = sampler.sample(Float(rng.random(n, dtype=np.float32)),
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
