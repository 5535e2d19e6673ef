"""Normal maps (instancing/materials/normal_map.py): the tilted BSDFs against Mitsuba's own
``normalmap`` plugin holding the same texture and BSDF, evaluated and sampled on a surface
interaction whose shading frame is the identity (so that our shading-frame directions are
theirs), and the refusals of malformed ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import instancing  # noqa: F401  (selects libLLVM before Dr.Jit starts)
from instancing.core.backend import Array3f, Float, UInt32, dr, mitsuba_module
from instancing.core.errors import SceneError
from instancing.io.mitsuba_export import mitsuba_bsdf
from instancing.materials.bsdf import BSDFTable
from instancing.materials.material import parse_material
from instancing.materials.normal_map import shadowing
from instancing.validation.gradient_check import gradient_image
from scene_helpers import (assert_same_bsdf_values, assert_samples_are_mitsubas,
                           assert_textured_bsdf_is_mitsubas, mitsuba_interaction, read_image_file,
                           tilt_directions, with_textures)

N = 4096


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """Normal maps with random normals up to 70 degrees off +z, a tenth of them facing down
    (which the plugin flips): an 8-bit PNG (read raw) and a float EXR."""
    mi = mitsuba_module()
    folder = tmp_path_factory.mktemp("normal_maps")
    rng = np.random.default_rng(11)
    n = rng.normal(size=(9, 8, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.4
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[rng.random((9, 8)) < 0.1, 2] *= -1.0
    color = (n + 1.0) / 2.0
    png, exr = folder / "normals.png", folder / "normals.exr"
    mi.Bitmap(np.round(color * 255).astype(np.uint8), mi.Bitmap.PixelFormat.RGB).write(str(png))
    mi.Bitmap(color.astype(np.float32), mi.Bitmap.PixelFormat.RGB).write(str(exr))
    return {"png": {"type": "bitmap", "filename": str(png), "raw": True},
            "exr": {"type": "bitmap", "filename": str(exr), "filter_type": "nearest"}}


def _mapped(bsdf: dict, texture: str = "png", **options) -> dict:
    return {"type": "normalmap", "normalmap": texture, "bsdf": bsdf, **options}


#: Normal-mapped materials: lobes of every kind of reflection, the options, the map inside
#: the wrappers that may hold it.
MAPPED = {
    "diffuse": _mapped({"type": "diffuse", "reflectance": [0.2, 0.5, 0.7]}),
    "diffuse_exr": _mapped({"type": "diffuse"}, "exr"),
    "diffuse_no_flip": _mapped({"type": "diffuse"}, flip_invalid_normals=False),
    "diffuse_no_shadowing": _mapped({"type": "diffuse"}, use_shadowing_function=False),
    "roughplastic": _mapped({"type": "roughplastic", "alpha": 0.2}),
    "roughconductor_anisotropic": _mapped({"type": "roughconductor", "alpha_u": 0.05, "alpha_v": 0.3}),
    "roughconductor_ggx": _mapped({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}),
    "twosided": {"type": "twosided", "bsdf": _mapped({"type": "diffuse", "reflectance": 0.7})},
    "blend": {"type": "blendbsdf", "weight": 0.4,
              "a": _mapped({"type": "diffuse", "reflectance": [0.8, 0.2, 0.1]}, "exr"),
              "b": {"type": "roughconductor", "alpha": 0.2}},
    "mask": {"type": "mask", "opacity": 0.8, "leaf": _mapped({"type": "roughplastic", "alpha": 0.3})},
    # Around a wrapper: the frame tilts before the wrapper sees wi.
    "around_twosided": _mapped({"type": "twosided", "bsdf": {"type": "roughplastic", "alpha": 0.2}}),
    "around_twosided_two": _mapped({"type": "twosided", "front": {"type": "diffuse", "reflectance": 0.6},
                                    "back": {"type": "roughconductor", "alpha": 0.3}}, "exr"),
    "around_blend": _mapped({"type": "blendbsdf", "weight": 0.3, "a": {"type": "diffuse"},
                             "b": {"type": "roughconductor", "alpha": 0.2}}),
}
#: Nested lobes whose sampling routine is Mitsuba's own: the same random numbers give the
#: same directions.
SAME_DIRECTIONS = ("roughconductor_anisotropic", "roughconductor_ggx")


def _material(name: str, maps: dict):
    return parse_material("m", with_textures(MAPPED[name], "normalmap", maps), read_image_file)


def _setup(name, maps, seed):
    rng = np.random.default_rng([7, seed])
    wi = tilt_directions(rng, N)
    uv = rng.uniform(-0.3, 1.3, size=(2, N)).astype(np.float32)
    material = _material(name, maps)
    mi, si = mitsuba_interaction(wi, uv)
    return rng, wi, uv, BSDFTable([material]), mi, mi.load_dict(mitsuba_bsdf(material)), si


@pytest.mark.parametrize("name", sorted(MAPPED))
def test_tilted_eval_and_pdf_are_mitsubas(maps, name):
    """f cos and the density at random directions (a sixth of them below the surface) and
    random uv, against Mitsuba's normalmap holding the same texture and BSDF."""
    rng, wi, uv, table, mi, bsdf, si = _setup(name, maps, sorted(MAPPED).index(name))
    # (A narrow lobe: 18 % of random directions reach it.)
    assert_textured_bsdf_is_mitsubas(table, bsdf, si, wi, tilt_directions(rng, N), uv, reach=0.1)


def test_an_untilted_map_changes_nothing(tmp_path):
    """A map of (0.5, 0.5, 1) everywhere gives the plain BSDF's values."""
    mi = mitsuba_module()
    flat = tmp_path / "flat.exr"
    mi.Bitmap(np.broadcast_to(np.float32([0.5, 0.5, 1.0]), (2, 2, 3)).copy(),
              mi.Bitmap.PixelFormat.RGB).write(str(flat))
    plain = {"type": "roughplastic", "alpha": 0.3}
    tilted = BSDFTable([parse_material("m", _mapped(plain, {"type": "bitmap", "filename": str(flat)}),
                                       read_image_file)])
    assert_same_bsdf_values(tilted, BSDFTable([parse_material("m", plain)]), np.random.default_rng(5))


#: Materials that let light straight through, with a map inside or around them.
PASSING_MAPPED = {
    "thindielectric": _mapped({"type": "thindielectric", "int_ior": 1.6}),
    "mask_of_mapped_thindielectric": {"type": "mask", "opacity": 0.6,
                                      "leaf": _mapped({"type": "thindielectric"}, "exr")},
    "around_mask": _mapped({"type": "mask", "opacity": 0.3, "leaf": {"type": "diffuse"}}),
}


@pytest.mark.parametrize("name", sorted(PASSING_MAPPED))
def test_a_map_lets_no_light_straight_through_as_in_mitsuba(maps, name):
    """Mitsuba's normalmap does not pass ``eval_null_transmission`` on (volpath's shadow
    rays stop at a normal-mapped thin pane, pass a mask of one by 1 - opacity): ours are its
    values at random wi and uv, 0 and 0.4 everywhere."""
    material = parse_material("m", with_textures(PASSING_MAPPED[name], "normalmap", maps), read_image_file)
    rng = np.random.default_rng(3)
    wi = tilt_directions(rng, N)
    uv = rng.uniform(-0.3, 1.3, size=(2, N)).astype(np.float32)
    mi, si = mitsuba_interaction(wi, uv)
    theirs = np.asarray(mi.load_dict(mitsuba_bsdf(material)).eval_null_transmission(si), np.float64)
    ours = np.asarray(BSDFTable([material]).null_transmission(
        UInt32(0), Array3f(*wi.T.astype(np.float32)), (Float(uv[0]), Float(uv[1]))), np.float64)
    expected = 0.4 if name.startswith("mask") else 0.0
    np.testing.assert_allclose(np.broadcast_to(theirs, (3, N)), expected, atol=1e-6)
    np.testing.assert_allclose(np.broadcast_to(ours, (3, N)), expected, atol=1e-6)


@pytest.mark.parametrize("name", sorted(MAPPED))
def test_tilted_samples_agree_with_mitsuba(maps, name):
    """Sampled directions: their weight is Mitsuba's f cos / pdf there and their density
    Mitsuba's; where the nested sampling routine is Mitsuba's, the same random numbers give
    its directions and weights."""
    rng, wi, uv, table, mi, bsdf, si = _setup(name, maps, 100 + sorted(MAPPED).index(name))
    u, valid, delta, wo, weight = assert_samples_are_mitsubas(table, bsdf, si, wi, uv, rng)
    if name in SAME_DIRECTIONS:
        bs, theirs = bsdf.sample(mi.BSDFContext(), si, Float(u[:, 0]),
                                 mi.Point2f(Float(u[:, 1]), Float(u[:, 2])))
        theirs_valid = np.asarray(theirs, np.float64).T.max(axis=1) > 0
        both = valid & theirs_valid
        assert both.sum() > 0.9 * max(valid.sum(), theirs_valid.sum())
        np.testing.assert_allclose(wo[both], np.asarray(bs.wo, np.float64).T[both], atol=2e-5)
        np.testing.assert_allclose(weight[both], np.asarray(theirs, np.float64).T[both], rtol=2e-4, atol=1e-5)
    # A mask's null lobe passes the ray on untilted.
    assert delta.any() == (name == "mask")
    np.testing.assert_allclose(wo[delta], -wi[delta], atol=1e-6)


@pytest.mark.parametrize("spec, message", [
    ({"type": "normalmap", "bsdf": {"type": "diffuse"}}, "its texture under 'normalmap'"),
    ({"type": "normalmap", "normalmap": 0.5, "bsdf": {"type": "diffuse"}}, "must be a texture"),
    ({"type": "normalmap", "normalmap": {"type": "checkerboard"}}, "one BSDF"),
    ({"type": "normalmap", "normalmap": {"type": "checkerboard"}, "a": {"type": "diffuse"},
      "b": {"type": "diffuse"}}, "one BSDF"),
    ({"type": "normalmap", "normalmap": {"type": "checkerboard"},
      "bsdf": {"type": "normalmap", "normalmap": {"type": "checkerboard"}, "bsdf": {"type": "diffuse"}}},
     "cannot hold another map"),
    ({"type": "blendbsdf", "weight": 0.5, "a": {"type": "diffuse"}, "b": {
        "type": "normalmap", "normalmap": {"type": "checkerboard"},
        "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}}, "supported as a whole material"),
    ({"type": "normalmap", "normalmap": {"type": "checkerboard"}, "flip_invalid_normals": 1,
      "bsdf": {"type": "diffuse"}}, "'flip_invalid_normals' must be true or false"),
    ({"type": "normalmap", "normalmap": {"type": "checkerboard", "colour0": 1},
      "bsdf": {"type": "diffuse"}}, "colour0"),
])
def test_malformed_normal_maps_are_refused_naming_the_culprit(spec, message):
    with pytest.raises(SceneError, match=message):
        parse_material("bumpy", spec, read_image_file)


def test_the_shadowing_term_is_estevez_and_has_finite_derivatives_at_zero_cosine():
    """Estevez et al.'s term against its float64 tangent form on random tilted normals and
    directions (relative error within 2e-5: float32's, 8.3e-6 at most for either form), and
    at a direction of zero cosine (a lane without a sample, wo = 0) the value 0 with a
    finite derivative: the tangent form's inf / inf gave NaN derivatives there, which a
    zero BSDF value multiplied into the path gradients."""
    rng = np.random.default_rng(4)
    n_np, wo_np = (rng.normal(size=(20000, 3)) for _ in range(2))
    for v in (n_np, wo_np):
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v[:, 2] = np.abs(v[:, 2])
    n_np, wo_np = n_np.astype(np.float32).astype(np.float64), wo_np.astype(np.float32).astype(np.float64)

    def tan2(z):
        return (1.0 - z * z) / (z * z)

    a = np.minimum(tan2(n_np[:, 2]) / 8.0, 1.0)
    expected = 2.0 / (1.0 + np.sqrt(1.0 + a * tan2(wo_np[:, 2])))
    ours = np.asarray(shadowing(Array3f(*n_np.T), Array3f(*wo_np.T)), np.float64)
    np.testing.assert_allclose(ours, expected, rtol=2e-5)
    n, wo = Array3f(0.3, 0.1, 0.95), Array3f(0.0, 0.0, 0.0)
    dr.enable_grad(n, wo)
    value = shadowing(n, wo)
    dr.backward(value)
    assert float(value[0]) == 0.0
    assert all(np.isfinite(np.asarray(dr.grad(v))).all() for v in (n, wo))


@pytest.mark.parametrize("name", ["normalmap.xml", "bumpmap.xml"])
def test_path_gradients_through_a_mapped_frame_are_finite(name):
    """The translation gradient of the bundled torus wearing a normal or bump map, under
    `path` (three bounces: the mapped BSDF is evaluated where paths bounce off it): every
    pixel finite (11 - 17 NaN pixels of 1 200 before the shadowing term's cosine form)."""
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "materials" / name)
    scene.set_camera(scene.camera.with_size(40, 30))
    key = f"{scene.instance_ids[0]}.translation"
    image = gradient_image(instancing.traverse(scene), key, np.array([1.0, 0.5, 0.2]), integrator="path",
                           spp=8, sppc=8, sppp=0, sppi=0, max_depth=3, seed=1)
    assert np.abs(image).max() > 0.01 and np.isfinite(image).all()
