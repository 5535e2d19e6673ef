"""Bump maps (instancing/materials/bump_map.py): the tilted BSDFs against Mitsuba's own
``bumpmap`` plugin holding the same height texture and BSDF, evaluated and sampled on a
surface interaction whose shading frame is the identity and whose derivatives dp/du, dp/dv
and geometric normal are random (given to ours as the same vectors in the shading frame),
and the refusals of malformed ones."""

from __future__ import annotations

import numpy as np
import pytest

import instancing  # noqa: F401  (selects libLLVM before Dr.Jit starts)
from instancing.core.backend import Array3f, mitsuba_module
from instancing.core.errors import SceneError
from instancing.io.mitsuba_export import mitsuba_bsdf
from instancing.materials.bsdf import BSDFTable
from instancing.materials.bump_map import SurfaceFrame
from instancing.materials.material import parse_material
from scene_helpers import (as_vectors, assert_same_bsdf_values, assert_samples_are_mitsubas,
                           assert_textured_bsdf_is_mitsubas, mitsuba_interaction, read_image_file,
                           tilt_directions, with_textures)

N = 4096


@pytest.fixture(scope="module")
def heights(tmp_path_factory):
    """Height maps with random texels: an 8-bit grey PNG (read raw) and a float RGB EXR."""
    mi = mitsuba_module()
    folder = tmp_path_factory.mktemp("bump_maps")
    rng = np.random.default_rng(12)
    png, exr = folder / "heights.png", folder / "heights.exr"
    mi.Bitmap((rng.uniform(size=(7, 9, 1)) * 255).astype(np.uint8), mi.Bitmap.PixelFormat.Y).write(str(png))
    mi.Bitmap(rng.uniform(0, 1, size=(6, 5, 3)).astype(np.float32), mi.Bitmap.PixelFormat.RGB).write(str(exr))
    return {"png": {"type": "bitmap", "filename": str(png), "raw": True},
            "exr": {"type": "bitmap", "filename": str(exr), "wrap_mode": "mirror",
                    "to_uv": [[1.5, -0.8, 0.3], [0.6, 2.0, -0.2], [0, 0, 1]]}}


def _bumped(bsdf: dict, texture: str = "png", **options) -> dict:
    return {"type": "bumpmap", "heights": texture, "bsdf": bsdf, **options}


#: Bump-mapped materials: lobes of every kind of reflection, the options and scales, the
#: map inside the wrappers that may hold it.
BUMPED = {
    "diffuse": _bumped({"type": "diffuse", "reflectance": [0.2, 0.5, 0.7]}, scale=0.05),
    "diffuse_exr": _bumped({"type": "diffuse"}, "exr", scale=0.1),
    "diffuse_steep": _bumped({"type": "diffuse"}, scale=0.4),
    "diffuse_no_flip": _bumped({"type": "diffuse"}, scale=0.2, flip_invalid_normals=False),
    "diffuse_no_shadowing": _bumped({"type": "diffuse"}, scale=0.2, use_shadowing_function=False),
    "roughplastic": _bumped({"type": "roughplastic", "alpha": 0.2}, scale=0.1),
    "roughconductor_ggx": _bumped({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}, scale=0.1),
    "twosided": {"type": "twosided", "bsdf": _bumped({"type": "diffuse", "reflectance": 0.7}, scale=0.1)},
    "blend": {"type": "blendbsdf", "weight": 0.4,
              "a": _bumped({"type": "diffuse", "reflectance": [0.8, 0.2, 0.1]}, "exr", scale=0.1),
              "b": {"type": "roughconductor", "alpha": 0.2}},
    "mask": {"type": "mask", "opacity": 0.8, "leaf": _bumped({"type": "roughplastic", "alpha": 0.3}, scale=0.1)},
    "around_twosided": _bumped({"type": "twosided", "bsdf": {"type": "roughplastic", "alpha": 0.2}}, scale=0.1),
    "around_mask": _bumped({"type": "mask", "opacity": 0.7, "leaf": {"type": "diffuse"}}, scale=0.1),
}


def _material(name: str, heights: dict):
    return parse_material("m", with_textures(BUMPED[name], "heights", heights), read_image_file)


def _setup(name, heights, seed):
    """Random wi and uv, and a surface around the shading frame: dp/du and dp/dv of random
    lengths (0.5 - 3) and directions near the tangent plane, the geometric normal their
    cross product (a smooth mesh's shading normal differs from it)."""
    rng = np.random.default_rng([8, seed])
    wi = tilt_directions(rng, N)
    uv = rng.uniform(-0.3, 1.3, size=(2, N)).astype(np.float32)
    angle = rng.uniform(0, 2 * np.pi, N)
    skew = rng.uniform(0.6, 2.5, N)
    dpdu = np.stack([np.cos(angle), np.sin(angle), rng.normal(0, 0.1, N)], 1) * rng.uniform(0.5, 3, (N, 1))
    dpdv = (np.stack([np.cos(angle + skew), np.sin(angle + skew), rng.normal(0, 0.1, N)], 1)
            * rng.uniform(0.5, 3, (N, 1)))
    n = np.cross(dpdu, dpdv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dpdu, dpdv, n = (x.astype(np.float32) for x in (dpdu, dpdv, n))
    material = _material(name, heights)
    mi, si = mitsuba_interaction(wi, uv, n, dpdu, dpdv)
    surface = SurfaceFrame(as_vectors(dpdu), as_vectors(dpdv), as_vectors(n))
    return rng, wi, uv, BSDFTable([material]), mi, mi.load_dict(mitsuba_bsdf(material)), si, surface


@pytest.mark.parametrize("name", sorted(BUMPED))
def test_bumped_eval_and_pdf_are_mitsubas(heights, name):
    """f cos and the density at random directions (a sixth of them below the surface), uv
    and surface derivatives, against Mitsuba's bumpmap holding the same texture and BSDF."""
    rng, wi, uv, table, mi, bsdf, si, surface = _setup(name, heights, sorted(BUMPED).index(name))
    assert_textured_bsdf_is_mitsubas(table, bsdf, si, wi, tilt_directions(rng, N), uv, reach=0.1,
                                     surface=surface)


@pytest.mark.parametrize("name", sorted(BUMPED))
def test_bumped_samples_agree_with_mitsuba(heights, name):
    """Sampled directions: their weight is Mitsuba's f cos / pdf there and their density
    Mitsuba's. (Their azimuths are not Mitsuba's: its frame's first axis is dp/du given in
    world space made orthogonal to a normal in the shading frame; ours is dp/du in the
    shading frame. The two agree where the shading frame is the world's, as here.)"""
    rng, wi, uv, table, mi, bsdf, si, surface = _setup(name, heights, 100 + sorted(BUMPED).index(name))
    assert_samples_are_mitsubas(table, bsdf, si, wi, uv, rng, surface)


def test_a_flat_height_map_changes_nothing(tmp_path):
    """A constant height gives the plain BSDF's values (the surface's own normal)."""
    mi = mitsuba_module()
    flat = tmp_path / "flat.exr"
    mi.Bitmap(np.full((3, 3, 3), 0.4, np.float32), mi.Bitmap.PixelFormat.RGB).write(str(flat))
    plain = {"type": "roughplastic", "alpha": 0.3}
    bumped = BSDFTable([parse_material("m", _bumped(plain, {"type": "bitmap", "filename": str(flat)}),
                                       read_image_file)])
    surface = SurfaceFrame(Array3f(2.0, 0.0, 0.0), Array3f(0.0, 3.0, 0.0), Array3f(0.0, 0.0, 1.0))
    assert_same_bsdf_values(bumped, BSDFTable([parse_material("m", plain)]), np.random.default_rng(6),
                            surface)


@pytest.mark.parametrize("spec, message", [
    ({"type": "bumpmap", "bsdf": {"type": "diffuse"}}, "a texture"),
    ({"type": "bumpmap", "h": {"type": "checkerboard"}, "bsdf": {"type": "diffuse"}}, "needs a bitmap"),
    ({"type": "bumpmap", "h": {"type": "bitmap", "filename": "x.png"}, "a": {"type": "diffuse"},
      "b": {"type": "diffuse"}}, "one BSDF"),
    ({"type": "bumpmap", "h": {"type": "bitmap", "filename": "x.png"},
      "bsdf": {"type": "normalmap", "normalmap": {"type": "checkerboard"}, "bsdf": {"type": "diffuse"}}},
     "cannot hold another map"),
    ({"type": "bumpmap", "h": {"type": "bitmap", "filename": "x.png"}, "scale": "big",
      "bsdf": {"type": "diffuse"}}, "'scale'"),
    ({"type": "bumpmap", "h": {"type": "bitmap", "filename": "x.png"}, "scale": float("inf"),
      "bsdf": {"type": "diffuse"}}, "'scale' must be a finite number, got inf"),
])
def test_malformed_bump_maps_are_refused_naming_the_culprit(spec, message):
    def read(filename, raw):
        return np.zeros((2, 2, 3), np.float32), filename
    with pytest.raises(SceneError, match=message):
        parse_material("bumpy", spec, read)
