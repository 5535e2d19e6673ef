"""The integrators called directly on camera rays (instancing/rendering/integrators/:
aov.py, direct.py, path.py): AOV channels against the scene's intersection, direct light
from delta lights against Lambert's closed form, the path tracer at depth 2 against the
direct integrator, and multi-bounce path tracing in a closed emitting cavity against the
geometric series of its albedo."""

import math

import numpy as np
import pytest

import instancing
from instancing.core.backend import Float, UInt32, device_arrays, dr
from instancing.core.rng import sample_streams
from instancing.rendering.integrators.aov import integrate_aov
from instancing.rendering.integrators.direct import integrate_direct
from instancing.rendering.integrators.path import integrate_path
from scene_helpers import assert_roulette_closed_form, mirror_corner

#: float32 unit roundoff.
EPS32 = 2.0 ** -24


def _camera(origin, target, width=48, height=36, fov=45, up=(0, 0, 1)):
    return {"type": "perspective", "fov": fov, "width": width, "height": height,
            "to_world": [{"look_at": {"origin": list(origin), "target": list(target), "up": list(up)}}]}


def _camera_rays(scene, spp: int = 1, seed: int = 0):
    """spp rays per pixel at random film positions (seeded), as the film would trace them:
    in the scene's rendering space, as the integrators take them."""
    camera = scene.view()
    rng = np.random.default_rng(seed)
    n = camera.width * camera.height * spp
    pixel = np.repeat(np.arange(camera.width * camera.height), spp)
    x = (pixel % camera.width + rng.random(n)) / camera.width
    y = (pixel // camera.width + rng.random(n)) / camera.height
    # In Dr.Jit's own (aligned) storage: kernels reading wrapped NumPy buffers are compiled
    # for the buffers' alignment, so each call could compile anew (backend.device_array).
    return camera.rays(*device_arrays(Float, x.astype(np.float32), y.astype(np.float32)))


def _sampler(n: int, seed: int):
    # The seed is opaque (as in film.py): other seeds reuse the compiled kernels.
    return sample_streams(dr.arange(UInt32, n), dr.opaque(UInt32, seed))


def _rgb(v) -> np.ndarray:
    return np.asarray(v, np.float64).T


def _evaluated(hit):
    """Evaluate every field of a Dr.Jit hit record in one kernel (read one by one, each
    field would trace and compile the whole intersection again)."""
    dr.eval(hit.t, hit.p, hit.n, hit.error, hit.instance, hit.prim, hit.valid)
    return hit


# -- aov --------------------------------------------------------------------------------------

def test_aov_channels_equal_the_scene_intersection_of_the_same_rays():
    scene = instancing.load_scene({
        "materials": {"red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}},
        "instances": [
            {"model": "sphere", "material": "red", "to_world": [{"translate": [0, 0, 1]}, {"scale": [1.5, 1, 0.7]}]},
            {"model": "cube", "to_world": [{"translate": [2, 1, 0.5]}, {"rotate": {"axis": [1, 1, 0], "angle": 30}},
                                           {"scale": 0.5}]},
            {"model": "rectangle", "to_world": [{"scale": 5}]}],
        "camera": _camera([0, -8, 4], [0, 0, 0.5])})
    o, d = _camera_rays(scene)
    aovs = ["depth", "position", "normal", "instance", "albedo"]
    out = [np.asarray(c, np.float64) for c in integrate_aov(scene, o, d, aovs)]
    assert len(out) == len(instancing.channel_names("aov", aovs)) == 11
    hit = _evaluated(scene.intersect_surface(o, d))
    valid = np.asarray(hit.valid)
    instance = np.asarray(hit.instance)
    assert 0.3 < valid.mean() < 0.99 and len(set(instance[valid])) == 3
    # The same kernels on the same rays: bit-identical.
    np.testing.assert_array_equal(out[0], np.where(valid, np.asarray(hit.t, np.float64), 0.0))
    # Positions in world space: the rendering-space hit plus the origin (float32 sums).
    world = np.where(valid[:, None], _rgb(hit.p).astype(np.float32) + scene.origin.astype(np.float32),
                     _rgb(hit.p))
    np.testing.assert_array_equal(np.stack(out[1:4], 1), world)
    np.testing.assert_array_equal(np.stack(out[4:7], 1), _rgb(hit.n))
    np.testing.assert_array_equal(out[7], instance)
    assert (out[7][~valid] == -1).all()
    albedo = np.array([[0.8, 0.1, 0.1], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0, 0, 0]], np.float32)
    np.testing.assert_array_equal(np.stack(out[8:11], 1), albedo[instance])
    # Depth is the distance along the unit camera ray.
    np.testing.assert_allclose(np.linalg.norm(_rgb(d), axis=1), 1.0, atol=4 * EPS32)


def test_aov_uv_and_roughness_channels():
    """``uv`` gives the hits' surface coordinates in scenes without textures too (the same
    as a textured scene's records), ``roughness`` each material's alpha: a constant, a
    checkerboard texture's two values, a principled material's roughness squared, an
    anisotropic one's geometric mean of alpha_u and alpha_v, 0 for diffuse; both 0 on
    misses."""
    scene = instancing.load_scene({
        "materials": {"rough": {"type": "roughconductor", "alpha": 0.3},
                      "checked": {"type": "roughdielectric", "alpha": {
                          "type": "checkerboard", "color0": 0.05, "color1": 0.6,
                          "to_uv": [[4, 0, 0], [0, 4, 0], [0, 0, 1]]}},
                      "disney": {"type": "principled", "roughness": 0.5},
                      "brushed": {"type": "roughconductor", "alpha_u": 0.04, "alpha_v": 0.25}},
        "instances": [
            {"model": "sphere", "material": "rough", "to_world": [{"translate": [-1.2, 0, 1]}]},
            {"model": "cube", "material": "checked", "to_world": [{"translate": [1.2, 0, 0.8]}, {"scale": 0.7}]},
            {"model": "rectangle", "to_world": [{"scale": 5}]},
            {"model": "sphere", "material": "disney", "to_world": [{"translate": [0, 2, 1]}, {"scale": 0.6}]},
            {"model": "sphere", "material": "brushed", "to_world": [{"translate": [0, -2, 1]}, {"scale": 0.4}]}],
        "camera": _camera([0, -8, 4], [0, 0, 0.5])})
    o, d = _camera_rays(scene)
    u, v, roughness = (np.asarray(c, np.float64) for c in integrate_aov(scene, o, d, ["uv", "roughness"]))
    hit = _evaluated(scene.intersect_surface(o, d, uv=True))
    instance, valid = np.asarray(hit.instance), np.asarray(hit.valid)
    np.testing.assert_array_equal(np.stack([u, v]), np.asarray(hit.uv, np.float64))
    assert (u[valid] > 0).mean() > 0.9 and not u[~valid].any() and not roughness[~valid].any()
    np.testing.assert_allclose(roughness[instance == 0], 0.3, rtol=1e-6)
    np.testing.assert_allclose(np.unique(roughness[instance == 1]), [0.05, 0.6], rtol=1e-6)
    assert not roughness[instance == 2].any()
    assert (instance == 4).sum() > 20
    np.testing.assert_allclose(roughness[instance == 4], 0.1, rtol=1e-6)
    assert (instance == 3).any()
    np.testing.assert_allclose(roughness[instance == 3], 0.25, rtol=1e-6)


# -- direct -----------------------------------------------------------------------------------

ALBEDO = np.array([0.8, 0.5, 0.2])
#: A sheared, non-uniformly scaled plane, tilted: its normal is A^-T (0, 0, 1).
PLANE = [[2.5, 0.8, 0.1, 0.3], [0.2, 1.7, 0.3, -0.2], [0.1, -0.3, 0.9, 0.1], [0, 0, 0, 1]]


def _plane_scene(light, occluder=False):
    instances = [{"model": "rectangle", "material": "m", "to_world": [{"matrix": PLANE}]}]
    if occluder:
        instances.append({"model": "sphere", "to_world": [{"translate": [0.2, 0.1, 1.5]}, {"scale": 0.4}]})
    return instancing.load_scene({
        "materials": {"m": {"type": "diffuse", "reflectance": ALBEDO.tolist()}},
        "instances": instances, "lights": [light],
        "camera": _camera([1.0, -6.0, 5.0], [0, 0, 0])})


def _plane_normal():
    m = np.asarray(PLANE, np.float32).astype(np.float64)
    n = np.linalg.inv(m[:3, :3]).T @ [0, 0, 1.0]
    return n / np.linalg.norm(n)


def test_direct_light_from_a_point_light_is_lamberts_closed_form():
    """L = albedo / pi * I cos / r^2 at every hit of the plane's front, 0 on misses."""
    position, intensity = np.array([0.5, -1.0, 3.0]), np.array([10.0, 20.0, 5.0])
    scene = _plane_scene({"type": "point", "position": position.tolist(), "intensity": intensity.tolist()})
    o, d = _camera_rays(scene, spp=2)
    rgb = _rgb(integrate_direct(scene, scene.light_set(), o, d, _sampler(dr.width(o), 0)))
    hit = _evaluated(scene.intersect_surface(o, d))
    valid = np.asarray(hit.valid)
    assert 0.2 < valid.mean() < 0.99
    p = _rgb(hit.p)[valid] + scene.origin
    to_light = position - p
    r2 = np.sum(to_light ** 2, 1)
    cos = to_light @ _plane_normal() / np.sqrt(r2)
    assert (cos > 0.1).all()  # the light is in front of the whole visible plane
    expected = ALBEDO / np.pi * intensity * (cos / r2)[:, None]
    # float32 hit points, normal and shading: a few units of roundoff per factor.
    np.testing.assert_allclose(rgb[valid], expected, rtol=2e-6)
    assert (rgb[~valid] == 0).all()


def test_direct_light_from_a_directional_light_is_lamberts_closed_form():
    direction, irradiance = np.array([-0.3, 0.4, -1.0]), np.array([2.0, 1.0, 3.0])
    scene = _plane_scene({"type": "directional", "direction": direction.tolist(), "irradiance": irradiance.tolist()})
    o, d = _camera_rays(scene, spp=2, seed=1)
    rgb = _rgb(integrate_direct(scene, scene.light_set(), o, d, _sampler(dr.width(o), 0)))
    valid = np.asarray(scene.intersect_surface(o, d).valid)
    cos = -direction @ _plane_normal() / np.linalg.norm(direction)
    assert cos > 0.1
    # Constant over the plane: one value, up to float32 shading arithmetic.
    np.testing.assert_allclose(rgb[valid], np.tile(ALBEDO / np.pi * irradiance * cos, (valid.sum(), 1)), rtol=2e-6)


def test_direct_light_is_zero_in_the_shadow_of_an_occluder():
    """A sphere between the point light and the plane: points whose segment to the light
    crosses the sphere (float64 test, away from the shadow's edge) get 0, the others the
    closed form."""
    position, intensity = np.array([0.5, 0.3, 4.0]), np.array([10.0, 10.0, 10.0])
    scene = _plane_scene({"type": "point", "position": position.tolist(), "intensity": intensity.tolist()}, True)
    o, d = _camera_rays(scene, spp=2, seed=2)
    rgb = _rgb(integrate_direct(scene, scene.light_set(), o, d, _sampler(dr.width(o), 0)))
    hit = _evaluated(scene.intersect_surface(o, d))
    on_plane = np.asarray(hit.instance) == 0
    p = _rgb(hit.p)[on_plane] + scene.origin
    # Distance of the segment p -> light from the sphere's centre, against its radius.
    centre, radius = np.array([0.2, 0.1, 1.5]), 0.4
    seg = position - p
    s = np.clip(np.sum((centre - p) * seg, 1) / np.sum(seg * seg, 1), 0, 1)
    gap = np.linalg.norm(p + s[:, None] * seg - centre, axis=1) - radius
    shadow, lit = gap < -1e-3, gap > 1e-3  # float32 geometry: 1e-3 from the shadow's edge
    assert shadow.sum() > 50 and lit.sum() > 500
    assert (rgb[on_plane][shadow] == 0).all()
    r2 = np.sum(seg ** 2, 1)
    expected = ALBEDO / np.pi * intensity * (seg @ _plane_normal() / r2 ** 1.5)[:, None]
    np.testing.assert_allclose(rgb[on_plane][lit], expected[lit], rtol=2e-6)


# -- path against direct ------------------------------------------------------------------------

def _mixed_scene(white: dict | None = None):
    """Delta, area and environment lights over diffuse shapes (the sphere's material
    ``white`` where given); one emitter flat, one curved."""
    return instancing.load_scene({
        "materials": {"grey": {"type": "diffuse", "reflectance": [0.6, 0.5, 0.4]},
                      "white": white or {"type": "diffuse", "reflectance": 0.9}},
        "instances": [
            {"model": "rectangle", "material": "grey", "to_world": [{"scale": [4, 4, 1]}]},
            {"model": "sphere", "material": "white", "to_world": [{"translate": [0.3, 0, 0.6]}, {"scale": 0.6}]},
            {"model": "disk", "material": "grey", "emitter": {"type": "area", "radiance": [6, 5, 4]},
             "to_world": [{"translate": [-1, 0.5, 2.5]}, {"rotate": {"axis": [1, 0, 0], "angle": 160}},
                          {"scale": 0.7}]},
            {"model": "sphere", "emitter": {"type": "area", "radiance": [2, 3, 4]},
             "to_world": [{"translate": [1.5, 0.5, 1.6]}, {"scale": [0.3, 0.2, 0.3]}]}],
        "lights": [{"type": "point", "position": [0, -2, 3], "intensity": 5.0},
                   {"type": "constant", "radiance": [0.2, 0.25, 0.3]}],
        "camera": _camera([0, -6, 3], [0, 0, 0.5], width=40, height=30)})


@pytest.mark.parametrize("seed", [0, 7])  # the second reuses the kernels
def test_path_with_max_depth_2_equals_direct_on_the_same_rays_and_streams(seed):
    """Depth 2 is the camera hit plus direct light: the same estimators, drawing the same
    random numbers in the same order from per-ray streams."""
    scene = _mixed_scene()
    lights = scene.light_set()
    o, d = _camera_rays(scene, spp=4, seed=seed)
    n = dr.width(o)
    direct = _rgb(integrate_direct(scene, lights, o, d, _sampler(n, seed)))
    path = _rgb(integrate_path(scene, lights, o, d, _sampler(n, seed), max_depth=2))
    assert (direct > 0).mean() > 0.5
    # Direct's BSDF rays test the few emitters first and the path tracer searches the
    # nearest hit, but both find the same emitter hits: bit-identical.
    np.testing.assert_array_equal(path, direct)
    # Another stream gives other estimates (the comparison is not vacuous).
    other = _rgb(integrate_direct(scene, lights, o, d, _sampler(n, seed + 1)))
    assert not np.allclose(other, direct)


def test_direct_light_is_the_same_whether_derivatives_are_tracked_or_not():
    """Without derivatives a hit's light samples run in a branch that SIMD packets with no
    lane to shade skip, and each BSDF kernel in one that packets without a lane of its type
    skip; with derivatives tracked, every lane runs them: the same estimates bit for bit (the
    mixed scene, its sphere made of rough plastic: two BSDF kernels)."""
    scene = _mixed_scene({"type": "roughplastic", "diffuse_reflectance": 0.9, "alpha": 0.2})
    lights = scene.light_set()
    o, d = _camera_rays(scene, spp=4, seed=3)
    n = dr.width(o)
    plain = _rgb(integrate_direct(scene, lights, o, d, _sampler(n, 3)))
    params = instancing.traverse(scene)
    dr.enable_grad(params["grey.reflectance"])
    params.update()
    tracked = integrate_direct(scene, lights, o, d, _sampler(n, 3))
    assert dr.grad_enabled(tracked)
    assert (plain > 0).mean() > 0.5
    np.testing.assert_array_equal(_rgb(dr.detach(tracked)), plain)


@pytest.mark.parametrize("integrator", ["direct", "path"])
def test_convex_diffuse_object_under_a_constant_environment_reflects_albedo_times_radiance(integrator):
    """A convex object never sees itself: every cosine-weighted BSDF ray from its front
    escapes to the environment (weight 1, no emitter sampling of it), so every ray that
    hits the object returns exactly albedo * L, at any depth, and every miss L."""
    env, albedo = np.array([0.8, 0.5, 0.25]), np.array([0.3, 0.6, 0.9])
    scene = instancing.load_scene({
        "materials": {"m": {"type": "diffuse", "reflectance": albedo.tolist()}},
        "instances": [{"model": "sphere", "material": "m",
                       "to_world": [{"rotate": {"axis": [1, 1, 0], "angle": 30}}, {"scale": [1.5, 0.7, 1.0]}]}],
        "lights": [{"type": "constant", "radiance": env.tolist()}],
        "camera": _camera([0, -6, 1], [0, 0, 0], width=32, height=24)})
    lights = scene.light_set()
    o, d = _camera_rays(scene, spp=2, seed=5)
    n = dr.width(o)
    if integrator == "direct":
        rgb = _rgb(integrate_direct(scene, lights, o, d, _sampler(n, 5)))
    else:
        rgb = _rgb(integrate_path(scene, lights, o, d, _sampler(n, 5), max_depth=-1))
    valid = np.asarray(_evaluated(scene.intersect_surface(o, d)).valid)
    assert 0.2 < valid.mean() < 0.9
    # One float32 product albedo * L (the constants themselves are float32).
    expected = np.where(valid[:, None], np.float32(albedo) * np.float32(env), np.float32(env))
    np.testing.assert_allclose(rgb, expected, rtol=2 * EPS32)


# -- a closed emitting cavity -----------------------------------------------------------------

LE, A = 0.5, 0.6


def _inward_cube(path):
    """A closed box of 12 triangles wound so that their normals point inwards (the front
    side of a one-sided diffuse surface and of an emitter faces the inside)."""
    v = [[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = [t[::-1] for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]  # reversed: inward
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return path


@pytest.fixture(scope="module")
def cavity(tmp_path_factory):
    """A sheared box whose inner walls all emit LE and reflect with albedo A, seen from
    inside: the radiance is LE (1 + A + ... + A^(k-1)) at depth k and LE / (1 - A)
    unbounded, whatever the box's shape."""
    obj = _inward_cube(tmp_path_factory.mktemp("cavity") / "box.obj")
    return instancing.load_scene({
        # Flat walls: smooth normals averaged over a box's corners do not conserve energy.
        "models": {"box": {"type": "obj", "filename": str(obj), "face_normals": True}},
        "materials": {"wall": {"type": "diffuse", "reflectance": A}},
        "instances": [{"model": "box", "material": "wall", "emitter": {"type": "area", "radiance": LE},
                       "to_world": [{"matrix": [[3.0, 0.6, 0.2, 0], [0, 2.0, 0.5, 0], [0.3, 0, 1.5, 0], [0, 0, 0, 1]]}]}],
        "camera": _camera([0.2, -0.5, 0.1], [1, 2, 0.5], width=32, height=32, fov=70)})


def _mean_within(values: np.ndarray, expected: float):
    """Sample mean within 5 standard errors of the closed form (fixed seed)."""
    se = values.std() / math.sqrt(len(values))
    assert abs(values.mean() - expected) < 5 * se, (values.mean(), expected, se)
    # The estimate is informative: 5 standard errors are under 2 % of the answer.
    assert 5 * se < 0.02 * expected


def test_path_with_max_depth_1_sees_only_emission_and_with_0_nothing(cavity):
    """Depth 1: the walls' emission seen directly, exactly LE on every ray (all hit a
    wall's front); depth 0: nothing."""
    lights = cavity.light_set()
    o, d = _camera_rays(cavity, seed=1)
    n = dr.width(o)
    hit = _evaluated(cavity.intersect_surface(o, d))
    assert np.asarray(hit.valid).all() and (np.sum(_rgb(hit.n) * _rgb(d), 1) < 0).all()
    one = _rgb(integrate_path(cavity, lights, o, d, _sampler(n, 0), max_depth=1))
    np.testing.assert_array_equal(one, np.full((n, 3), LE))
    zero = _rgb(integrate_path(cavity, lights, o, d, _sampler(n, 0), max_depth=0))
    assert zero.shape == (n, 3) and (zero == 0).all()


@pytest.mark.parametrize("max_depth", [2, 4])
def test_path_in_an_emitting_cavity_sums_the_first_bounces(cavity, max_depth):
    lights = cavity.light_set()
    o, d = _camera_rays(cavity, spp=16, seed=max_depth)
    n = dr.width(o)
    rgb = _rgb(integrate_path(cavity, lights, o, d, _sampler(n, max_depth), max_depth=max_depth))
    np.testing.assert_array_equal(rgb[:, 0], rgb[:, 1])  # grey in, grey out
    _mean_within(rgb[:, 0], LE * (1 - A ** max_depth) / (1 - A))
    if max_depth == 2:
        direct = _rgb(integrate_direct(cavity, lights, o, d, _sampler(n, max_depth)))
        np.testing.assert_array_equal(rgb, direct)


def test_unbounded_path_in_an_emitting_cavity_converges_to_the_geometric_series(cavity):
    """Russian roulette (from depth 5) stops paths without bias: the mean is LE / (1 - A)."""
    lights = cavity.light_set()
    o, d = _camera_rays(cavity, spp=32, seed=11)
    rgb = _rgb(integrate_path(cavity, lights, o, d, _sampler(dr.width(o), 11), max_depth=-1))
    _mean_within(rgb[:, 0], LE / (1 - A))




@pytest.mark.parametrize("integrator", ["path", "volpath"])
@pytest.mark.parametrize("reflectance", [0.3, 0.97])
def test_russian_roulette_starts_at_rr_depth_as_mitsubas(integrator, reflectance):
    """Closed form of the roulette on the mirror corner (two bounces: scene_helpers'
    mirror_corner and assert_roulette_closed_form) at rr_depth 1, 2, 3, 5 and by default;
    a file's rr_depth is the render's unless the render names its own."""
    spp = 64
    scene = instancing.load_scene(mirror_corner(reflectance))
    for rr_depth in (1, 2, 3, 5, None):
        image = instancing.render(scene, integrator, spp=spp, seed=5, rr_depth=rr_depth)
        assert_roulette_closed_form(image, spp, reflectance, integrator, rr_depth or 5)
    from_file = instancing.load_scene(mirror_corner(reflectance, {"type": integrator, "rr_depth": 1}))
    np.testing.assert_array_equal(np.asarray(instancing.render(from_file, spp=spp, seed=5)),
                                  np.asarray(instancing.render(scene, integrator, spp=spp, seed=5,
                                                               rr_depth=1)))
    np.testing.assert_allclose(np.asarray(instancing.render(from_file, spp=spp, seed=5, rr_depth=3)),
                               reflectance ** 2, rtol=1e-5)
