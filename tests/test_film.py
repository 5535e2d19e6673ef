"""Rendering: determinism, AOV channels against direct intersection, bad settings."""

import dataclasses
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.core.backend import Float, dr
from instancing.core.errors import SceneError
from instancing.io.scene_file import parse_camera

SCENE = {
    "materials": {"red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}},
    "instances": [
        {"id": "ball", "model": "sphere", "material": "red",
         "to_world": [{"translate": [0, 0, 1]}, {"scale": [1.5, 1, 0.7]}]},
        {"id": "floor", "model": "rectangle", "to_world": [{"scale": 5}]},
    ],
    "camera": {"type": "perspective", "fov": 40, "width": 40, "height": 30,
               "to_world": [{"look_at": {"origin": [0, -8, 4], "target": [0, 0, 0.5], "up": [0, 0, 1]}}]},
}


def _surrounded(inst: np.ndarray, value: int) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood of pixel-centre hits all show instance ``value``."""
    out = inst == value
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out &= np.roll(np.roll(inst, dy, 0), dx, 1) == value
    out[[0, -1], :] = out[:, [0, -1]] = False
    return out


def test_same_seed_gives_bit_identical_images_and_other_seeds_differ():
    scene = instancing.load_scene(SCENE)
    a = np.asarray(instancing.render(scene, "aov", spp=3, seed=5))
    b = np.asarray(instancing.render(scene, "aov", spp=3, seed=5))
    c = np.asarray(instancing.render(scene, "aov", spp=3, seed=6))
    assert a.shape == (30, 40, len(instancing.channel_names("aov")))
    assert np.isfinite(a).all()
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_aov_channels_at_one_sample_equal_the_intersection_of_pixel_rays():
    """Pixels whose 3x3 neighbourhood of pixel-centre rays sees one instance only hold
    exactly that instance's index, albedo and (on the flat floor) normal, whatever the
    random sub-pixel offsets of their 64 samples."""
    scene = instancing.load_scene(SCENE)
    img = np.asarray(instancing.render(scene, "aov", spp=64, seed=1, aovs=["instance", "albedo", "normal"]))
    names = instancing.channel_names("aov", ["instance", "albedo", "normal"])
    assert names == ["instance", "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z"]
    camera = parse_camera(SCENE["camera"])
    o, d = camera.pixel_centre_rays()
    hits = scene.intersect(np.asarray(o).T, np.asarray(d).T)
    inst = hits.instance.reshape(30, 40)
    interior = _surrounded(inst, 0) | _surrounded(inst, 1) | _surrounded(inst, -1)
    assert interior.sum() > 300
    np.testing.assert_array_equal(img[..., 0][interior], inst[interior])
    albedo = np.where(inst[..., None] == 0, [0.8, 0.1, 0.1], np.where(inst[..., None] == 1, 0.5, 0.0))
    np.testing.assert_allclose(img[..., 1:4][interior], albedo[interior], rtol=1e-6)
    # Flat floor: the normal is exactly +z wherever the floor fills the neighbourhood.
    floor = interior & (inst == 1)
    np.testing.assert_allclose(img[..., 4:7][floor], np.tile([0, 0, 1.0], (floor.sum(), 1)), atol=1e-6)


@pytest.mark.parametrize("kwargs, message", [
    ({"integrator": "photon"}, "unknown integrator"),
    ({"integrator": "aov", "aovs": ["curvature"]}, "unknown AOVs"),
    ({"integrator": "aov", "spp": 0}, "spp must be"),
    ({"integrator": "aov", "width": 0}, "width must be an integer in"),
    ({"integrator": "aov", "height": -3}, "height must be an integer in"),
    ({"integrator": "aov", "width": 2.5}, "width must be an integer in"),
    ({"integrator": "direct", "sppi": -1}, "sppi must be an integer >= 0"),
    ({"integrator": "path", "emitter_samples": 2}, "emitter_samples is the 'direct' integrator's"),
    ({"integrator": "direct", "bsdf_samples": -1}, r"bsdf_samples must be an integer in \[0, 64\]"),
    ({"integrator": "direct", "emitter_samples": 65}, r"emitter_samples must be an integer in \[0, 64\]"),
    ({"integrator": "direct", "emitter_samples": 0, "bsdf_samples": 0}, "both 0"),
])
def test_bad_render_settings_raise_scene_errors(kwargs, message):
    scene = instancing.load_scene(SCENE)
    with pytest.raises(instancing.SceneError, match=message):
        instancing.render(scene, **kwargs)


def _with_settings(integrator: dict | None, spp: int | None = None) -> dict:
    """SCENE lit by a sky and a point lamp, naming an integrator and a camera sample count."""
    camera = dict(SCENE["camera"], width=16, height=12)
    if spp is not None:
        camera["spp"] = spp
    scene = {**SCENE, "camera": camera, "lights": [
        {"type": "constant", "radiance": [0.3, 0.3, 0.3]},
        {"type": "point", "position": [2, -2, 4], "intensity": [20, 20, 20]}]}
    return scene if integrator is None else {**scene, "integrator": integrator}


def test_renders_that_name_no_integrator_or_spp_take_the_scenes():
    """As Mitsuba renders a file: the scene's integrator with its max_depth and the camera's
    sample count, unless the render names its own; none named anywhere: direct at 64 spp."""
    scene = instancing.load_scene(_with_settings({"type": "path", "max_depth": 3}, spp=8))
    image = np.asarray(instancing.render(scene, seed=1))
    np.testing.assert_array_equal(image, np.asarray(instancing.render(scene, "path", spp=8, seed=1,
                                                                      max_depth=3)))
    assert not np.array_equal(image, np.asarray(instancing.render(scene, "path", spp=8, seed=1)))
    np.testing.assert_array_equal(np.asarray(instancing.render(scene, "direct", seed=1)),
                                  np.asarray(instancing.render(scene, "direct", spp=8, seed=1)))
    np.testing.assert_array_equal(np.asarray(instancing.render(scene, spp=2, max_depth=-1, seed=1)),
                                  np.asarray(instancing.render(scene, "path", spp=2, seed=1)))
    plain = instancing.load_scene(_with_settings(None))
    np.testing.assert_array_equal(np.asarray(instancing.render(plain, seed=1)),
                                  np.asarray(instancing.render(plain, "direct", spp=64, seed=1)))


@pytest.mark.parametrize("given, ours, rr_depth", [
    ("direct", "direct", None), ("direct_projective", "direct", None), ("path", "path", None),
    ("prb", "path", 6), ("prb_basic", "path", 2 ** 32 - 1), ("prb_projective", "path", 6),
    ("volpath", "volpath", None), ("volpathmis", "volpath", None), ("prbvolpath", "volpath", None)])
def test_mitsubas_integrators_are_rendered_by_ours_of_the_same_image(given, ours, rr_depth):
    """By ours of the same image, with Russian roulette where theirs starts it at their
    default rr_depth 5 (tests/test_mitsuba_render.py checks where each starts it)."""
    choice = instancing.load_scene(_with_settings({"type": given, "sppi": 0})).description.integrator
    assert (choice.given, choice.name, choice.rr_depth) == (given, ours, rr_depth)


@pytest.mark.parametrize("integrator, words", [
    ({"type": "ptracer"}, "'ptracer' has no counterpart here"),
    ({"type": "aov", "aovs": "dd.y:depth, a:albedo, i:prim_index"},
     "'aov' with the AOV types ['albedo', 'prim_index'], which ours do not give"),
    ({"type": "aov", "aovs": "dd.y:depth", "integrators": [{"type": "ptracer"}]},
     "'aov' around 'ptracer': 'ptracer' has no counterpart here"),
    ({"type": "aov", "aovs": "dd.y:depth", "integrators": [{"type": "aov", "aovs": "n:uv"}]},
     "'aov' around 'aov': an 'aov' nested in 'aov'"),
    ({"type": "aov", "aovs": "dd.y:depth", "nested": "<bsdf type=\"diffuse\">"}, "'aov' with ['nested']"),
    ({"type": "aov", "aovs": " "}, "'aov' with neither AOVs nor integrators"),
    ({"type": "direct", "max_depth": 2}, "['max_depth']"),
    ({"type": "direct", "rr_depth": 3}, "['rr_depth']"),
    ({"type": "path", "nested": '<integrator type="path">'}, "['nested']"),
    ({"type": "volpath", "samples_per_pass": 4}, "['samples_per_pass']"),
])
def test_a_scenes_integrator_that_ours_do_not_render_as_asked_is_named_by_renders_relying_on_it(
        integrator, words):
    scene = instancing.load_scene(_with_settings(integrator, spp=2))
    with pytest.raises(SceneError) as raised:
        instancing.render(scene)
    assert words in str(raised.value) and "name the render's integrator" in str(raised.value)
    assert np.asarray(instancing.render(scene, "direct")).shape == (12, 16, 3)


def test_a_scenes_moment_integrator_renders_its_nested_integrators_with_their_squares():
    """Each nested integrator renders with its own settings: the moment image's RGB is the
    first one's image, its XYZ channels each one's image by the sRGB-to-XYZ matrix, and its
    second moments the mean of the squared samples (with one sample per pixel and a box
    filter: the squares of the XYZ channels). With 16 samples per pixel the first moments
    vary across independent renders as the samples' own variance over 16, which each
    render's (m2 - m1^2) / 15 estimates (pooled over pixels and channels, 8 renders).
    Settings the nested ones would not take, and derivatives, are refused."""
    spec = {"type": "moment", "integrators": [{"type": "path", "max_depth": 3, "id": "lit"},
                                              {"type": "direct", "id": "d"}]}
    scene = instancing.load_scene(_with_settings(spec, spp=1))
    image = np.asarray(instancing.render(scene, seed=3), np.float64)
    parts = [np.asarray(instancing.render(scene, "path", max_depth=3, seed=3), np.float64),
             np.asarray(instancing.render(scene, "direct", seed=3), np.float64)]
    assert instancing.channel_names(None, scene=scene) == [
        "R", "G", "B", "lit.X", "lit.Y", "lit.Z", "d.X", "d.Y", "d.Z",
        "m2_lit.X", "m2_lit.Y", "m2_lit.Z", "m2_d.X", "m2_d.Y", "m2_d.Z"]
    np.testing.assert_array_equal(image[..., :3], parts[0])
    matrix = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169],
                       [0.019334, 0.119193, 0.950227]])
    xyz = np.concatenate([part @ matrix.T for part in parts], axis=2)
    np.testing.assert_allclose(image[..., 3:9], xyz, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(image[..., 9:], xyz ** 2, rtol=1e-4, atol=1e-6)
    renders = np.stack([np.asarray(instancing.render(scene, spp=16, seed=10 + k), np.float64)
                        for k in range(8)])
    m1, m2 = renders[..., 3:9], renders[..., 9:]
    across, within = m1.var(axis=0, ddof=1).sum(), ((m2 - m1 ** 2) / 15).mean(axis=0).sum()
    assert abs(across / within - 1) < 0.2
    for setting in ({"max_depth": 2}, {"hide_emitters": True}):
        with pytest.raises(SceneError, match=r"set with the scene file's 'moment' integrator"):
            instancing.render(scene, **setting)
    params = instancing.traverse(scene)
    dr.enable_grad(params["lights[1].intensity"])
    params.update()
    with pytest.raises(SceneError, match="the scene file's 'moment' integrator renders no derivatives"):
        instancing.render(scene)


@pytest.mark.parametrize("integrator, refusal", [
    ({"type": "moment", "integrators": [{"type": "aov", "aovs": "d:depth"}]},
     "'moment' around 'aov': an 'aov' nested in 'moment'"),
    ({"type": "moment", "integrators": [{"type": "ptracer"}]}, "'moment' around 'ptracer': 'ptracer' has no"),
    ({"type": "aov", "integrators": [{"type": "moment", "integrators": [{"type": "path"}]}]},
     "'aov' around 'moment': an 'moment' nested in 'aov'"),
    ({"type": "moment", "integrators": [{"type": "path"}], "samples": 3}, "'moment' with ['samples']"),
])
def test_a_moment_integrator_ours_cannot_render_as_asked_is_refused_when_rendered(integrator, refusal):
    scene = instancing.load_scene(_with_settings(integrator))
    assert refusal in scene.description.integrator.refusal, scene.description.integrator.refusal
    with pytest.raises(SceneError, match="name the render's integrator"):
        instancing.render(scene)


def test_a_scenes_aov_integrator_renders_its_nested_integrators_then_its_aovs():
    """As Mitsuba's mi.render: each nested integrator's RGB with its own settings, then the
    AOVs, channels named as Mitsuba's; settings the nested ones would not take are refused."""
    spec = {"type": "aov", "aovs": "dd.y:depth, nn:sh_normal, p:position, g:geo_normal, t:uv",
            "integrators": [{"type": "path", "max_depth": 3, "id": "lit"}, {"type": "direct", "id": "d"}]}
    scene = instancing.load_scene(_with_settings(spec, spp=2))
    image = np.asarray(instancing.render(scene, seed=3))
    parts = [np.asarray(instancing.render(scene, "path", max_depth=3, seed=3)),
             np.asarray(instancing.render(scene, "direct", seed=3)),
             np.asarray(instancing.render(scene, "aov", seed=3,
                                          aovs=["depth", "shading_normal", "position", "normal", "uv"]))]
    np.testing.assert_array_equal(image, np.concatenate(parts, axis=2))
    names = ["lit.R", "lit.G", "lit.B", "d.R", "d.G", "d.B", "dd.y.T", "nn.X", "nn.Y", "nn.Z",
             "p.X", "p.Y", "p.Z", "g.X", "g.Y", "g.Z", "t.U", "t.V"]
    assert instancing.channel_names(None, scene=scene) == names and image.shape[2] == len(names)
    only_aovs = instancing.load_scene(_with_settings({"type": "aov", "aovs": "d:depth"}, spp=2))
    np.testing.assert_array_equal(np.asarray(instancing.render(only_aovs, seed=3)),
                                  np.asarray(instancing.render(only_aovs, "aov", aovs=["depth"], seed=3)))
    for setting in ({"max_depth": 2}, {"aovs": ["depth"]}, {"hide_emitters": True}):
        with pytest.raises(SceneError, match=r"set with the scene file's 'aov' integrator"):
            instancing.render(scene, **setting)


@pytest.mark.parametrize("integrator, message", [
    ({"type": "aov", "aovs": "depth"}, "integrator: aovs entries ['depth'] are not 'label:type'"),
    ({"type": "aov", "aovs": "d:depth, :uv"}, "integrator: aovs entries [':uv'] are not 'label:type'"),
    ({"type": "aov", "aovs": 3}, "integrator: aovs must be a string of 'label:type' entries"),
    ({"type": "aov", "aovs": "d:depth", "integrators": {"type": "path"}},
     "integrator: 'integrators' (those nested in 'aov') must be a list of integrators"),
    ({"type": "aov", "aovs": "n:sh_normal, n:geo_normal"},
     "integrator: the aov integrator names the channels ['n.X', 'n.Y', 'n.Z'] twice"),
    ({"type": "moment"}, "integrator: 'moment' needs an integrator nested in it"),
    ({"type": "moment", "integrators": {"type": "path"}},
     "integrator: 'integrators' (those nested in 'moment') must be a list of integrators"),
    ({"type": "moment", "integrators": [{"type": "path", "id": "a"}, {"type": "direct", "id": "a"}]},
     "integrator: the moment integrator names the integrators ['a'] twice"),
])
def test_a_malformed_aov_or_moment_integrator_is_refused_at_load(integrator, message):
    with pytest.raises(SceneError) as raised:
        instancing.load_scene(_with_settings(integrator))
    assert message in str(raised.value), str(raised.value)


@pytest.mark.parametrize("integrator, spp, message", [
    ("path", None, "integrator must be a dict with a 'type'"),
    ({"max_depth": 3}, None, "integrator must be a dict with a 'type'"),
    ({"type": "pathtracer"}, None, "integrator: unknown type 'pathtracer'"),
    ({"type": "path", "max_depth": -2}, None, "integrator: max_depth must be an integer in [-1,"),
    ({"type": "path", "max_depth": 2.5}, None, "integrator: max_depth must be an integer"),
    ({"type": "path", "rr_depth": 0}, None, "integrator: rr_depth must be an integer in [1,"),
    ({"type": "volpath", "rr_depth": 2.5}, None, "integrator: rr_depth must be an integer"),
    ({"type": "direct", "hide_emitters": "true"}, None, "integrator: hide_emitters must be true or false"),
    ({"type": "path", "rr_depth": [5]}, None, "integrator: 'rr_depth' must be a number, a flag or a string"),
    (None, 0, "camera: spp must be an integer >= 1"),
    (None, 1.5, "camera: spp must be an integer >= 1"),
    ({"type": "direct", "shading_samples": 2, "bsdf_samples": 1}, None,
     "integrator: shading_samples sets both emitter_samples and bsdf_samples"),
    ({"type": "direct", "emitter_samples": 0, "bsdf_samples": 0}, None,
     "integrator: emitter_samples and bsdf_samples are both 0"),
    ({"type": "direct", "bsdf_samples": 1.5}, None, "integrator: bsdf_samples must be an integer in [0, 64]"),
])
def test_bad_render_settings_in_a_scene_name_the_culprit(integrator, spp, message):
    with pytest.raises(SceneError) as raised:
        instancing.load_scene(_with_settings(integrator, spp))
    assert message in str(raised.value), str(raised.value)


@pytest.mark.parametrize("seed", ["x", 1.5, None, True, [1], -1, 2 ** 32, 7 + 2 ** 32])
def test_a_seed_that_is_no_32_bit_integer_is_refused_naming_seed(seed):
    """Seeds are 32-bit, as Mitsuba's: a larger one had given a smaller one's image."""
    scene = instancing.load_scene(SCENE)
    with pytest.raises(instancing.SceneError,
                       match=f"seed must be an integer in \\[0, 4294967295\\], got {re.escape(repr(seed))}"):
        instancing.render(scene, "aov", spp=1, seed=seed)
    # Integers of any kind are seeds.
    a, b = (np.asarray(instancing.render(scene, "aov", spp=1, seed=s)) for s in (np.int64(7), 7))
    np.testing.assert_array_equal(a, b)


def test_numpy_integers_are_taken_for_counts_and_sizes():
    """Sample counts, film sizes and depths from a NumPy sweep render as the same Python
    integers do (they were refused: 'spp must be a positive integer, got 2')."""
    scene = instancing.load_scene(SCENE)
    for integrator, extra in (("aov", {}), ("path", {"max_depth": 2, "sppi": 1})):
        plain = instancing.render(scene, integrator, spp=2, width=12, height=9, seed=3, **extra)
        wrapped = instancing.render(scene, integrator, spp=np.int64(2), width=np.int32(12),
                                    height=np.uint16(9), seed=3,
                                    **{k: np.int64(v) for k, v in extra.items()})
        np.testing.assert_array_equal(np.asarray(plain), np.asarray(wrapped))
    with pytest.raises(instancing.SceneError, match="spp must be an integer >= 1, got"):
        instancing.render(scene, "aov", spp=np.bool_(True))


def test_derivative_sample_counts_on_a_render_without_derivatives_are_warned_about():
    """sppc, sppp and sppi sample derivative terms: set on a render whose scene has no
    grad-enabled parameter they change nothing, and are warned about by name (not where the
    render has derivatives, or where they are not set)."""
    scene = instancing.load_scene(SCENE)
    with pytest.warns(UserWarning, match="sppp, sppi set on a render without derivatives"):
        image = instancing.render(scene, "direct", spp=2, sppp=16, sppi=3, seed=1, width=12, height=9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plain = instancing.render(scene, "direct", spp=2, seed=1, width=12, height=9)
        np.testing.assert_array_equal(np.asarray(image), np.asarray(plain))
        params = instancing.traverse(scene)
        dr.enable_grad(params["ball.translation"])
        params.update()
        instancing.render(scene, "direct", spp=2, sppp=4, sppi=0, seed=1, width=12, height=9)


@pytest.mark.parametrize("name", ["spp", "sppc", "sppp", "sppi"])
def test_more_samples_than_32_bit_sample_indices_are_refused_naming_the_count(name):
    """Each sample's random stream is chosen by pixel * spp + sample, a 32-bit index: at
    40x30 pixels (1200) spp may be at most 2^32 // 1200 = 3579139; 2^40 once failed deep
    inside Dr.Jit, a count just over the limit would have repeated streams."""
    scene = instancing.load_scene(SCENE)
    limit = 2 ** 32 // (40 * 30)
    for count in (2 ** 40, limit + 1):
        with pytest.raises(instancing.SceneError) as err:
            instancing.render(scene, "direct", **{"spp": 1, name: count})
        message = str(err.value)
        assert f"{name}={count}" in message and "2^32" in message and f"{name} <= {limit}" in message
    # At a smaller film the same count fits.
    with pytest.raises(instancing.SceneError, match=f"{name} <= {2 ** 32 // 4}"):
        instancing.render(scene, "direct", width=2, height=2, **{"spp": 1, name: 2 ** 32 // 4 + 1})


@pytest.mark.parametrize("source", [SCENE, "scene.json", None])
def test_render_of_a_scene_description_says_to_load_it_first(source):
    with pytest.raises(TypeError) as err:
        instancing.render(source, "aov", spp=1)
    message = str(err.value)
    assert "render: scene must be a Scene" in message and "load_scene" in message
    assert type(source).__name__ in message


def test_rendering_without_a_camera_is_an_error():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    with pytest.raises(instancing.SceneError, match="no 'camera'"):
        instancing.render(scene, "aov")


def _lit_scene(instances, lights, width=48, height=36, origin=(0, -6, 0), fov=35, models=None):
    return instancing.load_scene({
        "models": models or {},
        "materials": {"white": {"type": "diffuse", "reflectance": 1.0},
                      "grey": {"type": "diffuse", "reflectance": [0.6, 0.5, 0.4]}},
        "instances": instances, "lights": lights,
        "camera": {"type": "perspective", "fov": fov, "width": width, "height": height,
                   "to_world": [{"look_at": {"origin": list(origin), "target": [0, 0, 0], "up": [0, 0, 1]}}]},
    })


def test_directional_light_on_a_sphere_matches_lambert_shading():
    """Radiance = albedo / pi * E * max(0, n . l) (Lambert), n from the pixel's own hits.

    The expected pixel value averages the closed-form shading over a 16x16 grid of
    sub-pixel positions (the box filter's footprint); the render's 1024 random samples
    per pixel differ from that by Monte Carlo error only (measured below 0.9 % at the
    99th percentile), within the 1 % tolerance on pixels that see only the sphere and
    are away from the terminator (expected red above 0.15), where shading is smooth."""
    direction = np.array([-1.0, 2.0, -1.5])
    albedo, irradiance = np.array([0.6, 0.5, 0.4]), np.array([3.0, 2.0, 1.0])
    scene = _lit_scene([{"model": "sphere", "material": "grey", "to_world": [{"scale": [1.5, 1, 1]}]}],
                       [{"type": "directional", "direction": direction.tolist(),
                         "irradiance": irradiance.tolist()}])
    img = np.asarray(instancing.render(scene, "direct", spp=1024, seed=2))
    h, w = img.shape[:2]
    camera = scene.camera
    to_light = -direction / np.linalg.norm(direction)
    expected = np.zeros((h, w, 3))
    on_sphere = np.ones((h, w), bool)
    y, x = np.mgrid[0:h, 0:w]
    for sy in (np.arange(16) + 0.5) / 16:
        for sx in (np.arange(16) + 0.5) / 16:
            u = Float(((x + sx) / w).ravel().astype(np.float32))
            v = Float(((y + sy) / h).ravel().astype(np.float32))
            o, d = camera.rays(u, v)
            hits = scene.intersect(np.asarray(o).T, np.asarray(d).T)
            shading = np.clip(hits.n @ to_light, 0, None)[:, None] * albedo / np.pi * irradiance
            expected += shading.reshape(h, w, 3) / 256
            on_sphere &= hits.instance.reshape(h, w) == 0
    lit = on_sphere & (expected[..., 0] > 0.15)
    assert lit.sum() > 100
    # 1.5 %: the largest Monte Carlo deviation measured over these pixels at 1024 spp
    # was 1.3 %, the 99th percentile 0.84 % (a 10 % error, e.g. a wrong cosine, fails).
    np.testing.assert_allclose(img[lit], expected[lit], rtol=0.015)
    # Pixels that never see the sphere see nothing (no environment): exactly black.
    camera_o, camera_d = camera.pixel_centre_rays()
    inst = scene.intersect(np.asarray(camera_o).T, np.asarray(camera_d).T).instance.reshape(h, w)
    background = _surrounded(inst, -1)
    assert background.sum() > 100 and np.all(img[background] == 0)


def test_area_light_seen_directly_renders_its_radiance_exactly():
    scene = _lit_scene([{"id": "lamp", "model": "disk", "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 90}},
                                                                    {"scale": [3, 2, 1]}],
                         "emitter": {"type": "area", "radiance": [4, 2, 1]}}], [])
    img = np.asarray(instancing.render(scene, "direct", spp=16, seed=0))
    camera = scene.camera
    o, d = camera.pixel_centre_rays()
    inst = scene.intersect(np.asarray(o).T, np.asarray(d).T).instance.reshape(36, 48)
    inside = _surrounded(inst, 0)
    assert inside.sum() > 200
    # Rotated +90 deg about x, the disk's normal points to -y: towards the camera at y = -6.
    assert np.array_equal(img[inside], np.tile([4.0, 2.0, 1.0], (inside.sum(), 1)).astype(np.float32))


@pytest.mark.parametrize("model, to_world", [
    ("sphere", [{"scale": [1.5, 0.7, 1.0]}]),
    ("cube", [{"rotate": {"axis": [1, 1, 0], "angle": 30}}, {"scale": [1, 0.5, 0.8]}]),
])
def test_white_furnace_convex_object_renders_the_environment(model, to_world):
    """A convex white (reflectance 1) diffuse object in a constant environment reflects
    exactly the environment (no self-occlusion, so direct lighting is the whole answer).
    The environment is found by cosine-weighted BSDF samples alone, each of which
    carries albedo * radiance where it escapes: every sample, hence every pixel, is the
    environment's radiance at any spp. A ray that re-hit its own surface (acne) or an
    emitter sample of the environment (weighted by MIS) would leave a pixel off."""
    scene = _lit_scene([{"model": model, "material": "white", "to_world": to_world}],
                       [{"type": "constant", "radiance": 0.75}], width=32, height=24)
    img = np.asarray(instancing.render(scene, "direct", spp=4, seed=4))
    aov = np.asarray(instancing.render(scene, "aov", spp=1, seed=4, aovs=["instance"]))
    assert (aov[..., 0] == 0).sum() > 100  # the object covers part of the image
    np.testing.assert_allclose(img, 0.75, rtol=1e-6)


@pytest.mark.parametrize("environment", [False, True])
def test_bsdf_rays_that_test_the_emitters_first_equal_the_nearest_hit_search(monkeypatch, environment):
    """With a few area emitters, direct's BSDF rays test them first and ask the scene only
    whether something lies in front (or, with an environment, whether a ray escapes).
    The image equals the one from the scene's nearest hit on every BSDF ray: a flat
    (disk), a curved (sphere) and a mesh (torus) emitter, partly hidden behind a sphere,
    over a floor."""
    import instancing.scene.lights as lights_module
    from pathlib import Path
    torus = str(Path(__file__).resolve().parent.parent / "scenes" / "meshes" / "torus.obj")
    instances = [
        {"model": "rectangle", "material": "grey", "to_world": [{"translate": [0, 0, -1]}, {"scale": [4, 4, 1]}]},
        {"model": "sphere", "material": "white", "to_world": [{"translate": [0.3, 0, 0]}, {"scale": 0.6}]},
        {"model": "disk", "material": "grey", "emitter": {"type": "area", "radiance": [6, 5, 4]},
         "to_world": [{"translate": [-1, 0.5, 1.5]}, {"rotate": {"axis": [1, 0, 0], "angle": 160}}, {"scale": 0.7}]},
        {"model": "sphere", "material": "grey", "emitter": {"type": "area", "radiance": [2, 3, 4]},
         "to_world": [{"translate": [1.5, 0.5, 1.2]}, {"scale": 0.3}]},
        {"model": "torus", "material": "grey", "emitter": {"type": "area", "radiance": [3, 1, 1]},
         "to_world": [{"translate": [0.2, 1.5, 1.8]}, {"rotate": {"axis": [1, 0, 0], "angle": 70}},
                      {"scale": 0.4}]},
    ]
    lights = [{"type": "constant", "radiance": 0.2}] if environment else []
    models = {"torus": {"type": "obj", "filename": torus}}
    first = _lit_scene(instances, lights, width=40, height=30, origin=(0, -6, 3), models=models)
    assert first.light_set().boxes is not None  # the emitters are tested first
    img = np.asarray(instancing.render(first, "direct", spp=16, seed=5))
    monkeypatch.setattr(lights_module, "EMITTERS_TESTED_FIRST", 0)
    nearest = _lit_scene(instances, lights, width=40, height=30, origin=(0, -6, 3), models=models)
    assert nearest.light_set().boxes is None
    reference = np.asarray(instancing.render(nearest, "direct", spp=16, seed=5))
    assert (reference > 0).mean() > 0.5
    np.testing.assert_allclose(img, reference, rtol=1e-6, atol=1e-7)


def test_passes_change_only_the_summation_order_and_reuse_one_kernel(monkeypatch):
    import drjit as dr
    import instancing.rendering.film as rendering
    scene = instancing.load_scene(SCENE)
    one_pass = np.asarray(instancing.render(scene, "aov", spp=8, seed=3))
    monkeypatch.setattr(rendering, "MAX_LANES", 40 * 30 * 3)  # passes of 3, 3 and 2 samples
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        passes = np.asarray(instancing.render(scene, "aov", spp=8, seed=3))
        history = dr.kernel_history()
    # Same samples, summed in another order: equal to float32 rounding.
    np.testing.assert_allclose(passes, one_pass, rtol=1e-6, atol=1e-6)
    tracing = [k for k in history if k["type"] == dr.KernelType.JIT and k["operation_count"] > 200]
    assert len(tracing) == 3 and len({k["hash"] for k in tracing}) == 1


def test_second_render_of_an_area_lit_scene_compiles_nothing():
    # The first render builds the lights; nothing it leaves pending may end up in its
    # kernel only (then the second render, the same kernel, compiled again).
    import drjit as dr
    from pathlib import Path
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "light_area.json")
    for integrator in ("direct", "path"):
        instancing.render(scene, integrator, spp=2, width=16, height=12, seed=1)
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            dr.eval(instancing.render(scene, integrator, spp=2, width=16, height=12, seed=2))
            history = dr.kernel_history()
        jit = [k for k in history if k["type"] == dr.KernelType.JIT]
        assert jit and all(k["cache_hit"] for k in jit), integrator


@pytest.mark.parametrize("frozen", [True, False])
def test_renders_after_moving_an_instance_compile_nothing(frozen):
    """An animation: every frame moves the floor (set_transforms) and renders. The one
    emitter's and the one material's arrays hold one entry each, which kernels load as
    scalars; made from NumPy buffers, their alignment entered the code and the render
    kernel compiled anew on most frames (0.5 s each here, 2.4 s on showcase)."""
    import drjit as dr
    from pathlib import Path
    from instancing.core.backend import Array3f
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "cornell_box.json")
    params = instancing.traverse(scene)
    compiled = []
    for frame in range(4):
        params["floor.translation"] = params["floor.translation"] + Array3f(0.0, -0.01, 0.0)
        params.update()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            dr.eval(instancing.render(scene, "direct", spp=1, width=16, height=12, seed=frame,
                                      frozen=frozen))
            history = dr.kernel_history()
        compiled.append(sum(1 for k in history if k["type"] == dr.KernelType.JIT and not k["cache_hit"]))
    assert compiled[1:] == [0, 0, 0], compiled


def test_renders_from_a_moving_camera_compile_nothing():
    """A turntable: every frame turns the camera. Its pose enters kernels as opaque values;
    as literals, every pose compiled a new render kernel (2 s per frame on showcase)."""
    import drjit as dr
    from pathlib import Path
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "cornell_box.json")
    camera = scene.camera
    compiled, images = [], []
    for angle in (0.0, 4.0, 8.0):
        scene.set_camera(dataclasses.replace(
            camera, world_from_camera=instancing.rotate([0, 1, 0], angle) @ camera.world_from_camera))
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            images.append(np.asarray(instancing.render(scene, "direct", spp=1, width=16, height=12)))
            history = dr.kernel_history()
        compiled.append(sum(1 for k in history if k["type"] == dr.KernelType.JIT and not k["cache_hit"]))
    assert compiled[1:] == [0, 0], compiled
    assert not np.array_equal(images[0], images[1])  # the camera did turn


def test_a_scene_with_moved_or_recoloured_lights_compiles_nothing():
    """Point and directional lights and the environment enter kernels as opaque values:
    a scene loaded again with other light values renders with the compiled kernels."""
    import drjit as dr
    compiled, images = [], []
    for k in range(3):
        spec = dict(SCENE)
        spec["lights"] = [{"type": "point", "position": [0.5 * k, 4.0, 1.0], "intensity": 10.0 + k},
                          {"type": "directional", "direction": [0.1 * k, -1.0, 0.2], "irradiance": 1.0},
                          {"type": "constant", "radiance": 0.1 * (k + 1)}]
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            images.append(np.asarray(instancing.render(instancing.load_scene(spec), "direct", spp=1,
                                                       width=16, height=12)))
            history = dr.kernel_history()
        compiled.append(sum(1 for k in history if k["type"] == dr.KernelType.JIT and not k["cache_hit"]))
    assert compiled[1:] == [0, 0], compiled
    assert not np.array_equal(images[0], images[1])


def test_renders_at_other_film_sizes_compile_nothing():
    import drjit as dr
    from pathlib import Path
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "cornell_box.json")
    compiled = []
    for width, height in ((16, 12), (20, 15), (9, 31)):
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            image = np.asarray(instancing.render(scene, "direct", spp=1, width=width, height=height))
            history = dr.kernel_history()
        assert image.shape[:2] == (height, width)
        compiled.append(sum(1 for k in history if k["type"] == dr.KernelType.JIT and not k["cache_hit"]))
    assert compiled[1:] == [0, 0], compiled


def _showcase():
    from pathlib import Path
    return instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "showcase.json")


def test_path_with_max_depth_2_is_exactly_the_direct_integrator():
    """Both gather direct light with the same estimators and the same random numbers."""
    scene = _showcase()
    direct = np.asarray(instancing.render(scene, "direct", spp=4, seed=9, width=64, height=48))
    path = np.asarray(instancing.render(scene, "path", spp=4, seed=9, width=64, height=48, max_depth=2))
    np.testing.assert_array_equal(path, direct)


def test_path_with_max_depth_1_shows_only_emitters_seen_directly():
    scene = _showcase()
    path = np.asarray(instancing.render(scene, "path", spp=4, seed=1, width=64, height=48, max_depth=1))
    aov = np.asarray(instancing.render(scene, "aov", spp=4, seed=1, width=64, height=48, aovs=["instance"]))
    sky = np.array(scene.lights[1].radiance, np.float32)
    background = aov[..., 0] == -1
    assert background.sum() > 100
    np.testing.assert_allclose(path[background], np.tile(sky, (background.sum(), 1)), rtol=1e-6)
    lamp = scene.instance_ids.index("lamp")
    floor = aov[..., 0] == scene.instance_ids.index("floor")
    assert floor.sum() > 100 and np.all(path[floor] == 0)
    assert np.any(aov[..., 0] == lamp)


def test_white_furnace_non_convex_mesh_renders_the_environment_with_path_tracing():
    """A closed white torus (reflectance 1, concave parts see themselves) in a constant
    environment: light is conserved, so every pixel is the environment radiance. Direct
    lighting alone is darker in the hole; the path tracer (unbounded depth, Russian
    roulette) must reach 0.75 within 1 % on the image mean at 256 spp."""
    from pathlib import Path
    mesh = str(Path(__file__).resolve().parent.parent / "scenes" / "meshes" / "torus.obj")
    scene = instancing.load_scene({
        "models": {"torus": {"type": "obj", "filename": mesh}},
        "materials": {"white": {"type": "diffuse", "reflectance": 1.0}},
        "instances": [{"model": "torus", "material": "white",
                       "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 60}}, {"scale": [2, 2, 3]}]}],
        "lights": [{"type": "constant", "radiance": 0.75}],
        "camera": {"type": "perspective", "fov": 40, "width": 32, "height": 24,
                   "to_world": [{"look_at": {"origin": [0, -7, 0], "target": [0, 0, 0], "up": [0, 0, 1]}}]}})
    direct = np.asarray(instancing.render(scene, "direct", spp=256, seed=4))
    path = np.asarray(instancing.render(scene, "path", spp=256, seed=4))
    assert abs(path.mean() / 0.75 - 1) < 0.01
    assert direct.mean() < 0.99 * 0.75  # the test can tell the difference


@pytest.mark.parametrize("aovs, words", [("depth", "aovs must be a list of AOV names"),
                                         (3, "aovs must be a list of AOV names"),
                                         (["depth", "depth"], "aovs names an AOV twice")])
def test_aovs_that_are_no_list_of_distinct_names_are_refused(aovs, words):
    with pytest.raises(instancing.SceneError, match=words):
        instancing.render(_showcase(), "aov", spp=1, width=8, height=6, aovs=aovs)


def test_bad_max_depth_is_rejected():
    for depth in (-2, 2 ** 32):
        with pytest.raises(instancing.SceneError, match=r"max_depth must be an integer in \[-1, 4294967295\]"):
            instancing.render(_showcase(), "path", spp=1, max_depth=depth)


def _render_operations(scene, integrator, **kwargs) -> int:
    import drjit as dr
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        image = instancing.render(scene, integrator, spp=1, width=8, height=6, **kwargs)
        dr.eval(image)
        history = dr.kernel_history()
    return sum(k["operation_count"] for k in history if k["type"] == dr.KernelType.JIT)


def test_renders_trace_only_what_the_scene_needs():
    import drjit as dr
    base = {"instances": [{"model": "sphere"}], "camera": SCENE["camera"]}
    unlit = instancing.load_scene(base)
    point = instancing.load_scene({**base, "lights": [{"type": "point", "position": [0, 0, 5], "intensity": 1}]})
    point_env = instancing.load_scene({**base, "lights": [{"type": "point", "position": [0, 0, 5], "intensity": 1},
                                                          {"type": "constant", "radiance": 1}]})
    aov = _render_operations(point_env, "aov", aovs=["depth"])
    no_lights = _render_operations(unlit, "direct")
    with_point = _render_operations(point, "direct")
    with_env = _render_operations(point_env, "direct")
    # An AOV render does no shading; no lights: no shadow rays; each light type adds its code.
    assert aov < with_point and no_lights + 100 < with_point < with_env
    # Without lights the direct integrator is the camera ray alone (same work as a depth AOV).
    assert no_lights < aov + 100
    # No AD graph is recorded when no parameter requires gradients.
    assert not dr.grad_enabled(instancing.render(point_env, "path", spp=1, width=8, height=6))


@pytest.mark.parametrize("lights, emitter, message", [
    ([{"type": "sunsky", "position": [0, 0, 1]}], None, "unknown light type 'sunsky'"),
    ([{"type": "spot", "position": [0, 0, 1]}], None, "unknown keys \\['position'\\], missing keys \\['to_world'\\]"),
    ([{"type": "spot", "to_world": [], "cutoff_angle": 100}], None, "cutoff_angle must be"),
    ([{"type": "point", "position": [0, 0, 1]}], None, "missing keys \\['intensity'\\]"),
    ([{"type": "point", "position": [0, 0, 1], "intensity": -1}], None, "non-negative"),
    ([{"type": "directional", "direction": [0, 0, 0], "irradiance": 1}], None, "zero vector"),
    ([{"type": "constant", "radiance": 1}, {"type": "constant", "radiance": 2}], None, "only one"),
    ([], {"type": "spot", "radiance": 1}, "emitter"),
    ([], {"type": "area", "radiance": [1, 2]}, "emitter.radiance"),
])
def test_bad_lights_fail_at_load_time_naming_the_light(lights, emitter, message):
    instance = {"id": "ball", "model": "sphere"}
    if emitter is not None:
        instance["emitter"] = emitter
    with pytest.raises(instancing.SceneError, match=message):
        instancing.load_scene({"instances": [instance], "lights": lights, "camera": SCENE["camera"]})


def test_flat_emitter_records_equal_the_re_intersected_ones():
    """BSDF rays that find a flat emitter take phase 1's t and the light set's normal; the
    re-intersection (phase 2) gives the same record to float32 rounding."""
    from instancing.rendering.integrators.direct import emitter_hit
    from instancing.core.backend import Array3f
    lamp = {"type": "area", "radiance": [5, 5, 5]}
    scene = instancing.load_scene({"instances": [
        {"id": "disk", "model": "disk", "emitter": lamp,
         "to_world": [{"translate": [-1, 0.5, 3]}, {"rotate": {"axis": [1, 1, 0], "angle": 160}},
                      {"reflect": "x"}, {"scale": [1.5, 0.6, 1]}]},
        {"id": "rect", "model": "rectangle", "emitter": lamp,
         "to_world": [{"translate": [1.2, -0.3, 2.5]}, {"rotate": {"axis": [0, 1, 0], "angle": 200}},
                      {"scale": [0.8, 1.3, 1]}]},
        {"id": "ball", "model": "sphere", "to_world": [{"translate": [0, 0, 1.5]}, {"scale": 0.4}]},
    ]})
    lights = scene.light_set()
    assert lights.flat_normals is not None
    rng = np.random.default_rng(5)
    n = 20000
    o = rng.uniform([-2, -2, -0.5], [2, 2, 0.5], (n, 3)).astype(np.float32)
    target = rng.uniform([-2.5, -1.5, 2], [2.5, 1.5, 3.5], (n, 3))
    d = (target - o) / np.linalg.norm(target - o, axis=1, keepdims=True)
    o, d = Array3f(*o.T), Array3f(*d.astype(np.float32).T)
    first = scene.intersect_preliminary(o, d)
    flat = emitter_hit(scene, lights, o, d, first)
    lights.flat_normals = None  # the general path: phase 2 on the emitter hits
    full = emitter_hit(scene, lights, o, d, first)
    valid = np.asarray(flat.valid)
    assert np.array_equal(valid, np.asarray(full.valid)) and valid.mean() > 0.3
    assert np.array_equal(np.asarray(flat.instance), np.asarray(full.instance))
    np.testing.assert_allclose(np.asarray(flat.t)[valid], np.asarray(full.t)[valid], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(flat.n)[:, valid], np.asarray(full.n)[:, valid], atol=2e-6)


def test_a_lens_camera_refuses_film_edge_gradients_by_name():
    """Silhouettes and shadow edges are sampled as seen from one viewpoint: with a thin lens a
    render with moving instances says so, and renders the interior term with sppp=0 and
    sppi=0."""
    for camera in ({"type": "thinlens", "fov": 40, "aperture_radius": 0.1, "focus_distance": 5},):
        scene = instancing.load_scene({
            "instances": [{"id": "ball", "model": "sphere"},
                          {"id": "floor", "model": "rectangle",
                           "to_world": [{"translate": [0, 0, 2]}, {"scale": 4}]}],
            "lights": [{"type": "point", "position": [1, 1, -4], "intensity": 10}],
            "camera": {**camera, "width": 16, "height": 12, "to_world": [
                {"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0], "up": [0, 1, 0]}}]}})
        params = instancing.traverse(scene)
        dr.enable_grad(params["ball.translation"])
        params.update()
        with pytest.raises(SceneError, match=f"'{camera['type']}' camera has no single viewpoint.*"
                                             "silhouettes.*shadow edges"):
            instancing.render(scene, "direct", spp=2)
        with pytest.warns(UserWarning, match="leave out"):
            image = instancing.render(scene, "direct", spp=2, sppp=0, sppi=0)
        dr.backward(dr.sum(image.array))
        assert np.abs(np.array(dr.grad(params["ball.translation"]))).sum() > 0


def _two_view_scene():
    """SCENE with a second, named camera looking from the side (half the width)."""
    side = {"type": "perspective", "fov": 30, "width": 20, "height": 30, "id": "side",
            "to_world": [{"look_at": {"origin": [7, 0, 1], "target": [0, 0, 0.5], "up": [0, 0, 1]}}]}
    return {**{k: v for k, v in SCENE.items() if k != "camera"},
            "cameras": [SCENE["camera"], side]}


def test_each_camera_renders_as_a_scene_whose_only_camera_it_is():
    """render(camera=k or id) equals rendering the one-camera scene made of camera k; the
    default is the first camera."""
    scene = instancing.load_scene(_two_view_scene())
    front = instancing.load_scene(SCENE)
    side = instancing.load_scene({**SCENE, "camera": _two_view_scene()["cameras"][1]})
    assert [c.id for c in scene.cameras] == ["", "side"]
    np.testing.assert_array_equal(instancing.render(scene, "aov", spp=2),
                                  instancing.render(front, "aov", spp=2))
    for which in (1, "side"):
        image = instancing.render(scene, "direct", spp=2, camera=which)
        assert image.shape == (30, 20, 3)
        np.testing.assert_array_equal(image, instancing.render(side, "direct", spp=2))


@pytest.mark.parametrize("which, message", [(2, "no such camera"), ("top", "no such camera"),
                                            (-1, "no such camera"), (True, "no such camera"),
                                            # the first camera has no id: "" names none
                                            ("", "no such camera")])
def test_unknown_cameras_are_named_in_the_error(which, message):
    scene = instancing.load_scene(_two_view_scene())
    with pytest.raises(SceneError, match=message) as err:
        instancing.render(scene, "aov", spp=1, camera=which)
    assert repr(which) in str(err.value) and "'side'" in str(err.value)


@pytest.mark.parametrize("sample_border", [False, True])
@pytest.mark.parametrize("rfilter", ["gaussian", "tent"])
def test_pixels_at_the_film_edge_average_the_part_of_their_filter_on_the_film(rfilter, sample_border):
    """Mitsuba draws film samples on the film only, so a pixel whose filter reaches past
    the film's edge averages the part of its filter on the film; with the film's
    ``sample_border`` it averages its whole filter (the mean points stay at the centres). An orthographic camera
    looking down on a plane makes the position AOV affine in the film point, so each
    pixel's expected position is that of its filter's mean film point; the reference
    integrates Mitsuba's filters (the Gaussian minus its value at the radius) over the
    film in float64. The edge pixels' mean points move inwards by 0.14 px (Gaussian) and
    0.10 px (tent); the Monte Carlo error at 4096 spp is 0.008 px (1 sigma)."""
    width, height = 16, 12
    scene = instancing.load_scene({
        "instances": [{"model": "rectangle", "to_world": [{"scale": 100}]}],
        "camera": {"type": "orthographic", "width": width, "height": height, "rfilter": rfilter,
                   "sample_border": sample_border,
                   "to_world": [{"look_at": {"origin": [0, 0, 10], "target": [0, 0, 0], "up": [0, 1, 0]}},
                                {"scale": [2, 2, 1]}]},
    })
    image = np.asarray(instancing.render(scene, "aov", spp=4096, seed=1, aovs=["position"]))
    # The position at film point (x, y) in pixels: affine, read off three film points.
    o, d = scene.camera.rays(Float([0.0, 1.0, 0.0]), Float([0.0, 0.0, 1.0]))
    o, d = np.asarray(o, np.float64).T, np.asarray(d, np.float64).T
    p = o - (o[:, 2] / d[:, 2])[:, None] * d
    x_axis, y_axis = (p[1] - p[0]) / width, (p[2] - p[0]) / height

    def mean_point(size):
        """Per pixel: the filter-weighted mean film coordinate over the film [0, size] (with
        the border sampled, over the filter's whole reach)."""
        radius = 2.0 if rfilter == "gaussian" else 1.0
        x = np.linspace(-radius if sample_border else 0.0, size + (radius if sample_border else 0.0),
                        200_001)
        centres = np.arange(size) + 0.5
        offset = x[None, :] - centres[:, None]
        if rfilter == "gaussian":
            weight = np.maximum(np.exp(-2.0 * offset ** 2) - np.exp(-2.0 * radius ** 2), 0.0)
        else:
            weight = np.maximum(1.0 - np.abs(offset), 0.0)
        return (weight * x).sum(axis=1) / weight.sum(axis=1)

    mx, my = mean_point(width), mean_point(height)
    expected = p[0] + mx[None, :, None] * x_axis + my[:, None, None] * y_axis
    # Errors in pixels along the film's axes.
    error = image[..., :3] - expected
    error_px = np.stack([error @ x_axis / (x_axis @ x_axis), error @ y_axis / (y_axis @ y_axis)], -1)
    # The edge pixels' mean points do move on the film alone, and stay with its border.
    assert abs(mx[0] - 0.5) > 0.09 if not sample_border else abs(mx[0] - 0.5) < 1e-6
    assert np.abs(error_px).max() < 0.04, np.abs(error_px).max()


#: SCENE seen by two more cameras of the first one's type and film size.
VIEWS = {**{k: v for k, v in SCENE.items() if k != "camera"}, "cameras": [
    SCENE["camera"],
    {**SCENE["camera"], "fov": 55, "near_clip": 0.5,
     "to_world": [{"look_at": {"origin": [6, -3, 5], "target": [0, 0, 0.5], "up": [0, 0, 1]}}]},
    {**SCENE["camera"], "fov": 30,
     "to_world": [{"look_at": {"origin": [-2, 7, 3], "target": [0, 0, 0.5], "up": [0, 0, 1]}}]}],
    "lights": [{"type": "point", "position": [2, -3, 6], "intensity": 60}]}


def _batch_images(scene, views, integrator, spp, seed):
    from instancing.rendering.film import RenderSettings, _check_aovs, images
    from instancing.scene.camera import CameraBatch
    batch = CameraBatch([scene.view(k) for k in views])
    aovs = tuple(_check_aovs(None)) if integrator == "aov" else None
    settings = RenderSettings(integrator, aovs, -1, 5, False, spp, spp, 0, 0)
    lights = scene.light_set() if integrator != "aov" else None
    return [np.asarray(image) for image in
            images(scene, batch, lights, settings, dr.opaque(instancing.core.backend.UInt32, seed))]


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_views_traced_as_one_wavefront_give_each_views_image(rfilter):
    """Three views rendered as one batch against each rendered alone: another estimate of
    the same image, so the batch's difference from a lone render is as large as the
    difference between two lone renders with other seeds (and a view given another's pose
    or field of view would differ everywhere along the edges; with the Gaussian, whose
    samples are splatted into neighbouring pixels, none reaches another view)."""
    scene = instancing.load_scene({**VIEWS, "cameras": [{**camera, "rfilter": rfilter}
                                                        for camera in VIEWS["cameras"]]})
    batched = _batch_images(scene, [0, 1, 2], "direct", 64, seed=1)
    for k, image in enumerate(batched):
        alone, other = (np.asarray(instancing.render(scene, "direct", spp=64, seed=s, camera=k))
                        for s in (2, 3))
        noise = np.abs(other - alone).mean()
        assert 0 < np.abs(image - alone).mean() < 1.25 * noise, k
        assert np.abs(image - alone).mean() < 0.1 * np.abs(batched[(k + 1) % 3] - alone).mean()


def test_views_of_a_batch_share_one_tracing_kernel():
    """A batch of three views traces its samples in one kernel of three views' lanes."""
    scene = instancing.load_scene(VIEWS)
    _batch_images(scene, [0, 1, 2], "aov", 2, seed=1)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        _batch_images(scene, [0, 1, 2], "aov", 2, seed=4)
        history = dr.kernel_history()
    tracing = [k for k in history if k["type"] == dr.KernelType.JIT and k["operation_count"] > 200]
    assert [k["size"] for k in tracing] == [3 * 40 * 30 * 2]


#: VIEWS with the ball sunk into the floor (contact curves) and moved off-centre; as a
#: sphere, or as a smoothly shaded icosphere mesh (terminator arcs too).
SUNK = {**VIEWS, "instances": [
    {**VIEWS["instances"][0], "to_world": [{"translate": [0.2, 0, 0.4]}, {"scale": [1.5, 1, 0.7]}]},
    VIEWS["instances"][1]]}
SUNK_MESH = {**SUNK, "models": {"ico": {"type": "obj", "filename": str(
    Path(instancing.__file__).parent / "validation" / "data" / "icosphere.obj")}},
    "instances": [{**SUNK["instances"][0], "model": "ico"}, SUNK["instances"][1]]}
#: SUNK_MESH seen by orthographic cameras in the same poses (each 5 units across).
SUNK_ORTHOGRAPHIC = {**SUNK_MESH, "cameras": [
    {"type": "orthographic", "width": c["width"], "height": c["height"], "near_clip": c.get("near_clip", 0),
     "to_world": c["to_world"] + [{"scale": [2.5, 2.5, 1]}]} for c in VIEWS["cameras"]]}
#: Which kinds of curve each scene has: silhouettes, contacts, terminators, curves seen in
#: flat mirrors, shadows.
SUNK_CURVES = {"sphere": (SUNK, [True, True, False, False, True]),
               "smooth mesh": (SUNK_MESH, [True, True, True, False, True]),
               "orthographic": (SUNK_ORTHOGRAPHIC, [True, True, True, False, True])}


def _batch_gradients(scene, views, seed, kinds):
    """Per view of one camera batch, the forward derivative along a move of the ball of its
    boundary terms alone (sppc=0): silhouettes, the contact curve, terminator arcs (``kinds``
    says which the scene has) and the shadow curves."""
    from instancing.core.backend import Array3f, UInt32
    from instancing.rendering.film import RenderSettings, boundary_samplers, images
    from instancing.scene.camera import CameraBatch
    params = instancing.traverse(scene)
    value = params["ball.translation"]
    dr.enable_grad(value)
    params.update()
    batch = CameraBatch([scene.view(k) for k in views])
    settings = RenderSettings("direct", None, -1, 5, False, 2, 0, 16, 16)
    curves = boundary_samplers(scene, [batch], settings)[0]
    assert [c is not None for c in curves[:5]] == kinds
    out = images(scene, batch, scene.light_set(), settings, dr.opaque(UInt32, seed), None, curves)
    dr.set_grad(value, Array3f(1.0, 0.3, 0.2))
    dr.enqueue(dr.ADMode.Forward, value)
    dr.traverse(dr.ADMode.Forward)
    grads = [np.array(dr.grad(image)) for image in out]
    dr.disable_grad(value)
    params.update()
    return grads


@pytest.mark.parametrize("model", SUNK_CURVES)
def test_boundary_terms_of_a_batch_estimate_each_views_own(model):
    """The boundary terms of three views sampled as one wavefront against each view's alone:
    the first view draws the lone render's random numbers (equal to float32 rounding); the
    others are other estimates of the same derivative, as far from the lone render as two
    lone renders with other seeds are from each other (a sample weighted by the batch's
    count, or projected through another view's camera, is off by far more)."""
    spec, kinds = SUNK_CURVES[model]
    scene = instancing.load_scene(spec)
    batched = _batch_gradients(scene, [0, 1, 2], 1, kinds)
    for k, gradient in enumerate(batched):
        alone = _batch_gradients(scene, [k], 1, kinds)[0]
        if k == 0:
            np.testing.assert_allclose(gradient, alone, rtol=0, atol=1e-5 * np.abs(alone).max())
            continue
        others = [_batch_gradients(scene, [k], s, kinds)[0] for s in (2, 3)]
        noise = np.mean([np.abs(o - alone).mean() for o in others])
        assert 0 < np.abs(gradient - alone).mean() < 1.5 * noise, k
        assert np.abs(gradient - alone).mean() < 0.2 * np.abs(batched[(k + 1) % 3] - alone).mean(), k


def test_boundary_terms_of_a_batch_share_one_kernel_per_kind():
    """Three views' silhouettes, contact curves and shadow curves are sampled in kernels of
    three views' lanes (one per kind, and the forward derivative's), none of one view's."""
    scene = instancing.load_scene(SUNK)
    _batch_gradients(scene, [0, 1, 2], 1, SUNK_CURVES["sphere"][1])
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        _batch_gradients(scene, [0, 1, 2], 4, SUNK_CURVES["sphere"][1])
        history = dr.kernel_history()
    sizes = [k["size"] for k in history if k["type"] == dr.KernelType.JIT]
    assert sizes.count(3 * 40 * 30 * 16) >= 3 and 40 * 30 * 16 not in sizes, sizes


@pytest.mark.parametrize("args, named", [
    (("direct",), {"aovs": ["depth"]}),
    (("path",), {"aovs": ["albedo"]}),
    (("direct",), {"max_depth": 3}),
    (("aov",), {"max_depth": 2}),
    (("direct",), {"rr_depth": 3}),
    (("aov",), {"rr_depth": 2}),
    (("path",), {"rr_depth": 0}),
    (("volpath",), {"rr_depth": "5"}),
    (("aov",), {"hide_emitters": True}),
    (("direct",), {"hide_emitters": 1}),
    (("direct",), {"frozen": "no"}),
    (("direct",), {"progress": 5})])
def test_settings_another_integrator_reads_or_of_the_wrong_type_are_refused_by_name(args, named):
    """A setting that this render would ignore, or not read as given, is an error naming it."""
    scene = instancing.load_scene(SCENE)
    with pytest.raises(SceneError, match=next(iter(named))):
        instancing.render(scene, *args, spp=1, **named)


def test_channel_names_refuse_an_unknown_integrator():
    with pytest.raises(SceneError, match="'foo'"):
        instancing.channel_names("foo")


def test_a_cropped_camera_renders_the_window_of_the_whole_films_image():
    """The showcase at 48 x 36 and a 24 x 18 window of it (a crop): the window's pixels
    differ from the whole image's there by no more than two renders of the whole image with
    different seeds differ (Monte Carlo noise, measured), while a window moved by 4 pixels
    differs by much more."""
    import json
    root = Path(__file__).resolve().parent.parent / "scenes"
    spec = json.loads((root / "showcase.json").read_text())
    spec["camera"].update(width=48, height=36)
    whole = instancing.load_scene(spec, base_dir=root)
    spec["camera"]["crop"] = {"x": 12, "y": 6, "width": 24, "height": 18}
    cropped = instancing.load_scene(spec, base_dir=root)
    assert cropped.camera.width == 24 and cropped.camera.height == 18

    def image(scene, seed):
        return np.asarray(instancing.render(scene, "direct", spp=128, seed=seed))

    a, b = image(whole, 1), image(whole, 2)
    window = np.s_[6:24, 12:36]
    noise = np.abs(a[window] - b[window]).mean()
    c = image(cropped, 3)
    assert np.abs(c - a[window]).mean() < 1.3 * noise
    assert np.abs(c - a[10:28, 12:36]).mean() > 3 * noise



def test_a_constant_image_splatted_through_a_wide_filter_is_exact_to_the_edges():
    """Splatted samples (a Gaussian, a tent) of a constant radiance: every pixel is that
    radiance, the film's edge pixels too (each pixel divides by its own weights' sum)."""
    for rfilter in ("gaussian", "tent"):
        scene = instancing.load_scene({"lights": [{"type": "constant", "radiance": [0.7, 0.2, 0.45]}],
                                       "camera": {**SCENE["camera"], "width": 17, "height": 11,
                                                  "rfilter": rfilter}})
        image = np.asarray(instancing.render(scene, "direct", spp=5, seed=2))
        np.testing.assert_allclose(image, np.broadcast_to([0.7, 0.2, 0.45], image.shape), rtol=2e-6)


@pytest.mark.parametrize("rfilter", ["gaussian", "tent"])
@pytest.mark.parametrize("all_rows", [True, False])
def test_a_splat_weights_every_sample_towards_every_pixel_its_filter_reaches(rfilter, all_rows, monkeypatch):
    """The film's splat of a pass (two views of 7x5 pixels, 3 samples each at random film
    points) against a float64 sum over every (pixel, sample) pair of the views: each pixel's
    channel sums and weights' sum, the filter's rows of sums computed all at once and one by
    one (``SPLAT_SUMS_BYTES`` 0)."""
    from instancing.rendering import film
    from instancing.rendering.pixel_filter import PixelFilter
    from instancing.scene.camera import CameraBatch
    if not all_rows:
        monkeypatch.setattr(film, "SPLAT_SUMS_BYTES", 0)
    width, height, count = 7, 5, 3
    scene = instancing.load_scene({**VIEWS, "cameras": [{**camera, "rfilter": rfilter, "width": width,
                                                         "height": height} for camera in VIEWS["cameras"]]})
    batch = CameraBatch([scene.view(0), scene.view(1)])
    pixel_filter = PixelFilter.of(batch.camera)
    pixels = width * height * len(batch)
    side = 2 * pixel_filter.reach + 1  # 5 (Gaussian), 3 (tent)
    assert film.splat_rows(pixel_filter, 2, pixels, count) == (side if all_rows else 1)
    rng = np.random.default_rng(4)
    own = np.repeat(np.arange(pixels), count)  # each sample's pixel (view-major)
    px = own % width + rng.random(own.size)
    py = (own // width) % height + rng.random(own.size)
    values = rng.random((2, own.size))
    sums = film._splat(batch, [Float(v.astype(np.float32)) for v in values],
                       Float(px.astype(np.float32)), Float(py.astype(np.float32)), count, pixel_filter)
    got = np.array([np.asarray(s) for s in sums])

    def weight(x):
        if rfilter == "tent":
            return np.maximum(1.0 - np.abs(x), 0.0)
        norm = 0.5 * np.sqrt(2 * np.pi) * math.erf(4.0 / np.sqrt(2.0))
        return np.where(np.abs(x) <= 2.0, np.exp(-2.0 * x ** 2) / norm, 0.0)

    target = np.arange(pixels)
    same_view = (target[:, None] // (width * height)) == (own[None, :] // (width * height))
    w = (weight(px.astype(np.float32)[None, :] - (target[:, None] % width + 0.5))
         * weight(py.astype(np.float32)[None, :] - ((target[:, None] // width) % height + 0.5)) * same_view)
    expected = np.concatenate([w @ values.astype(np.float32).T, w.sum(axis=1, keepdims=True)], axis=1).T
    assert (w > 0).sum(axis=1).min() > count  # each pixel gathers from its neighbours too
    np.testing.assert_allclose(got, expected, rtol=2e-5, atol=1e-6)


# --- alpha (an rgba film) ----------------------------------------------------------------------

#: An ellipsoid seen along z by an orthographic camera whose film spans ALPHA_EXTENT world
#: units: its image is the ellipse x^2 / a^2 + y^2 / b^2 <= 1, nothing behind it.
ALPHA_AXES = (1.3, 0.8)
ALPHA_EXTENT = 3.0
ALPHA_SIZE = 16


def _ellipsoid_scene(pixel_format: str = "rgba", lights: list | None = None) -> instancing.Scene:
    half = ALPHA_EXTENT / 2
    return instancing.load_scene({
        "instances": [{"model": "sphere", "to_world": [{"scale": [*ALPHA_AXES, 1.0]}]}],
        "lights": [{"type": "point", "position": [0, 0, -5], "intensity": 30}] if lights is None else lights,
        "camera": {"type": "orthographic", "width": ALPHA_SIZE, "height": ALPHA_SIZE, "pixel_format": pixel_format,
                   "to_world": [{"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0], "up": [0, 1, 0]}},
                                {"scale": [half, half, 1]}]}})


def _ellipse_coverage(n: int = 256) -> np.ndarray:
    """Each pixel's covered fraction, float64 NumPy: the share of an n x n grid of points
    in the pixel that lie inside the ellipse (the image is symmetric under the film's flips)."""
    pixel = ALPHA_EXTENT / ALPHA_SIZE
    offsets = (np.arange(n) + 0.5) / n
    x = (-ALPHA_EXTENT / 2 + (np.arange(ALPHA_SIZE)[:, None] + offsets[None, :]) * pixel).ravel()
    a, b = ALPHA_AXES
    inside = (x[None, :] / a) ** 2 + (x[:, None] / b) ** 2 <= 1.0
    return inside.reshape(ALPHA_SIZE, n, ALPHA_SIZE, n).mean(axis=(1, 3))


@pytest.mark.parametrize("integrator", ["direct", "path", "volpath"])
def test_an_rgba_film_adds_alpha_after_the_same_rgb(integrator):
    """A camera whose pixel_format is rgba renders R, G, B, A: the RGB bit-identical to the
    rgb film's, the alpha in [0, 1], 1 inside the silhouette and 0 outside it."""
    rgba = _ellipsoid_scene("rgba")
    image = np.asarray(instancing.render(rgba, integrator, spp=16, seed=4))
    rgb = np.asarray(instancing.render(_ellipsoid_scene("rgb"), integrator, spp=16, seed=4))
    assert instancing.channel_names(integrator, scene=rgba) == ["R", "G", "B", "A"]
    assert image.shape == (ALPHA_SIZE, ALPHA_SIZE, 4)
    np.testing.assert_array_equal(image[..., :3], rgb)
    coverage = _ellipse_coverage(16)
    assert (image[..., 3][coverage == 1] == 1).all() and (image[..., 3][coverage == 0] == 0).all()
    assert ((image[..., 3] > 0) & (image[..., 3] < 1)).any()


@pytest.mark.parametrize("integrator", ["direct", "path"])
def test_alpha_is_the_covered_fraction_of_each_pixel(integrator):
    """At 4 096 independent samples per pixel, each pixel's alpha is the fraction of it that
    the ellipsoid covers (float64 NumPy on a 256 x 256 grid per pixel) within five standard
    errors of a mean of 0-or-1 samples, plus 0.001 for the grid (it differs from a 1 024 x
    1 024 grid's by 9e-5 at most); and so is the mean over the
    film (a miss counts 0 even where a constant environment lights the scene in direct,
    whose alpha, as Mitsuba's, is the camera ray's hit)."""
    spp = 4096
    lights = [{"type": "constant", "radiance": 0.5}] if integrator == "direct" else None
    alpha = np.asarray(instancing.render(_ellipsoid_scene(lights=lights), integrator, spp=spp, seed=2))[..., 3]
    coverage = _ellipse_coverage()
    sigma = np.sqrt(coverage * (1 - coverage) / spp)
    assert (np.abs(alpha - coverage) <= 5 * sigma + 0.001).all(), np.abs(alpha - coverage).max()
    assert abs(alpha.mean() - coverage.mean()) <= 5 * np.sqrt((sigma ** 2).sum()) / alpha.size + 1e-4


def test_a_path_that_sees_the_environment_is_opaque_unless_emitters_are_hidden():
    """Mitsuba's path and volpath count a visible environment as covering every pixel; with
    hide_emitters the alpha is the silhouette's again (as direct's)."""
    scene = _ellipsoid_scene(lights=[{"type": "constant", "radiance": 0.5}])
    for integrator in ("path", "volpath"):
        shown = np.asarray(instancing.render(scene, integrator, spp=64, seed=1))[..., 3]
        hidden = np.asarray(instancing.render(scene, integrator, spp=64, seed=1, hide_emitters=True))[..., 3]
        direct = np.asarray(instancing.render(scene, "direct", spp=64, seed=1))[..., 3]
        assert (shown == 1).all()
        np.testing.assert_array_equal(hidden, direct)


def test_an_unknown_pixel_format_is_refused_by_name():
    with pytest.raises(SceneError, match=r"camera: pixel_format must be one of \['rgb', 'rgba'\], got 'rgbx'"):
        _ellipsoid_scene("rgbx")
