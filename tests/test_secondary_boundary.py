"""Curve sampling of the secondary boundary term (instancing/rendering/secondary_boundary.py):
the resampled curve points' weights against the closed-form angular length of a sphere's
silhouette seen from a point, and the shadow curves' against the length of the shadows that
spheres cast on a floor."""

import math

import numpy as np
import pytest

import instancing
from instancing.core.backend import Array3f, Bool, Int32, UInt32, dr
from instancing.core.rng import sample_streams
from instancing.rendering import secondary_boundary as sb

LANES = 1 << 18


def _scene(lamp: bool) -> "instancing.Scene":
    """A moving ellipsoid (the occluder) over a floor, with a rectangle lamp above it or an
    environment instead."""
    description = {
        "camera": {"type": "perspective", "fov": 40, "width": 8, "height": 8,
                   "to_world": [{"look_at": {"origin": [0, -6, 2], "target": [0, 0, 0], "up": [0, 0, 1]}}]},
        "lights": [] if lamp else [{"type": "constant", "radiance": [1, 1, 1]}],
        "instances": [
            {"id": "ball", "model": "sphere",
             "to_world": [{"translate": [0.3, 0.2, 1.5]}, {"rotate": {"axis": [1, 1, 0], "angle": 40}},
                          {"scale": [0.5, 0.8, 0.6]}]},
            {"id": "floor", "model": "rectangle", "to_world": [{"scale": 4}]}]}
    if lamp:
        description["instances"].append(
            {"id": "lamp", "model": "rectangle", "emitter": {"type": "area", "radiance": [5, 5, 5]},
             "to_world": [{"translate": [1, 0, 4]}, {"rotate": {"axis": [1, 0, 0], "angle": 180}},
                          {"scale": 0.5}]})
    scene = instancing.load_scene(description)
    scene.set_moving(np.array([0]))
    return scene


def _silhouette(scene, instance: int, x: np.ndarray) -> np.ndarray:
    """World points (float64, a fine closed polyline) of a sphere instance's silhouette
    seen from x: its object-space circle of tangency mapped to world space."""
    to_world = scene.instances.to_world_of(np.array([instance]))[0]
    view = np.linalg.solve(to_world, np.append(x, 1.0))[:3]
    # Circle of tangency of the unit sphere seen from `view`: x . view = 1.
    d = np.linalg.norm(view)
    centre, radius = view / d ** 2, math.sqrt(1 - 1 / d ** 2)
    a = np.cross(view, [1.0, 0.0, 0.0] if abs(view[0]) < 0.9 * d else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(view / d, a)
    phi = np.linspace(0.0, 2 * math.pi, 200001)
    points = centre + radius * (np.outer(np.cos(phi), a) + np.outer(np.sin(phi), b))
    return points @ to_world[:3, :3].T + to_world[:3, 3]


def _length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _angular_length(scene, x: np.ndarray) -> float:
    """Length on the unit sphere of directions around x of the ellipsoid's silhouette, by
    float64 quadrature."""
    world = _silhouette(scene, 0, x)
    return _length((world - x) / np.linalg.norm(world - x, axis=1, keepdims=True))


@pytest.mark.parametrize("lamp", [True, False])
def test_resampled_curve_points_integrate_the_silhouette_length(lamp):
    """E[1/pdf * speed] over the kept curve points is the silhouette's angular length seen
    from x, whatever the guide (lamp-guided weights or the environment's uniform ones):
    resampling changes the density, not the integral."""
    scene = _scene(lamp)
    occluders = sb.occluder_set(scene, "direct")
    x = np.array([0.1, -0.2, 0.0])
    n = np.array([0.0, 0.0, 1.0])
    xs, ns = (Array3f(*[np.full(LANES, v, np.float32) for v in a]) for a in (x, n))
    sampler = sample_streams(dr.arange(UInt32, LANES), 12345)
    instance, point, tangent, size, convex, valid, inverse_pdf = occluders.sample(
        scene.instances, sampler, xs, ns, dr.full(Int32, 1, LANES), creases=False)  # on the floor
    w = np.array(dr.detach(point)).T.astype(np.float64) - x
    t = np.array(tangent).T.astype(np.float64)
    r = np.linalg.norm(w, axis=1)
    unit = w / r[:, None]
    speed = np.linalg.norm(t - unit * np.einsum("ij,ij->i", unit, t)[:, None], axis=1) / r
    values = np.where(np.array(valid), np.array(inverse_pdf) * speed, 0.0)
    expected = _angular_length(scene, x)
    standard_error = values.std() / math.sqrt(LANES)
    assert abs(values.mean() - expected) < 4 * standard_error + 1e-4 * expected, \
        (values.mean(), expected, standard_error)


def test_shadow_curve_points_integrate_the_shadow_outline_length():
    """E[1/pdf * |dz/du|] over the shadow curve points is the world length of the shadow
    outlines on the floor (float64: the spheres' circles of tangency seen from the point
    light, projected from it onto the floor's plane): for static shading points the moving
    ellipsoid's shadow only, for shading points on a moving instance every sphere's."""
    light = np.array([0.5, -0.3, 5.0])
    scene = instancing.load_scene({
        "camera": {"type": "perspective", "fov": 40, "width": 8, "height": 8,
                   "to_world": [{"look_at": {"origin": [0, -6, 2], "target": [0, 0, 0], "up": [0, 0, 1]}}]},
        "lights": [{"type": "point", "position": light.tolist(), "intensity": [1, 1, 1]}],
        "instances": [
            {"id": "ball", "model": "sphere",
             "to_world": [{"translate": [0.3, 0.2, 1.5]}, {"rotate": {"axis": [1, 1, 0], "angle": 40}},
                          {"scale": [0.5, 0.8, 0.6]}]},
            {"id": "other", "model": "sphere", "to_world": [{"translate": [-2.5, 2.5, 0.8]}, {"scale": 0.3}]},
            {"id": "floor", "model": "rectangle", "to_world": [{"scale": 4}]}]})
    scene.set_moving(np.array([0]))
    shadows = sb.ShadowCurves.build(scene)

    def shadow_length(instance: int) -> float:
        world = _silhouette(scene, instance, light)
        return _length(light + (world - light) * (light[2] / (light[2] - world[:, 2]))[:, None])

    ball, other = shadow_length(0), shadow_length(1)
    for moving, expected in ((False, ball), (True, ball + other)):
        sampler = sample_streams(dr.arange(UInt32, LANES), 777)
        z, dz, size, found, inverse_pdf = shadows.sample(
            scene, scene.light_set(), sampler, dr.full(Bool, moving, LANES), dr.full(Bool, True, LANES))
        on_floor = np.abs(np.array(dr.detach(z.z))) < 1e-4
        values = np.where(np.array(found), np.array(inverse_pdf) * np.linalg.norm(np.array(dz), axis=0), 0.0)
        assert on_floor[np.array(found)].all()
        standard_error = values.std() / math.sqrt(LANES)
        assert abs(values.mean() - expected) < 4 * standard_error + 1e-4 * expected, \
            (moving, values.mean(), expected, standard_error)
