"""The environment (instancing/scene/environment.py): envmap lookups against Mitsuba's own
``envmap`` plugin, its importance sampling against an independent float64 quadrature of
the same map, parsing and errors.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import instancing
from instancing.core.backend import BACKEND_NAME, Array3f, Float, dr, mitsuba_module
from instancing.core.errors import SceneError
from instancing.io.image import read_texture
from instancing.scene.description import EnvironmentMap
from instancing.scene.environment import Environment

#: A rotation that turns the map's +y pole away from every axis.
ROTATION = np.eye(4)
ROTATION[:3, :3] = (np.array([[np.cos(0.7), 0, np.sin(0.7)], [0, 1, 0], [-np.sin(0.7), 0, np.cos(0.7)]])
                    @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]))


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """A float EXR map (odd sizes, a black patch and a bright spot) and an 8-bit PNG one."""
    mi = mitsuba_module()
    folder = tmp_path_factory.mktemp("maps")
    rng = np.random.default_rng(8)
    texels = rng.uniform(0.0, 2.0, size=(7, 12, 3)).astype(np.float32)
    texels[2:4, 3:6] = 0.0
    texels[5, 9] = [60.0, 50.0, 40.0]
    exr = folder / "map.exr"
    mi.Bitmap(texels, mi.Bitmap.PixelFormat.RGB).write(str(exr))
    png = folder / "map.png"
    mi.Bitmap((rng.uniform(size=(6, 10, 3)) * 255).astype(np.uint8), mi.Bitmap.PixelFormat.RGB).write(str(png))
    return {"exr": str(exr), "png": str(png)}


def _environment(filename: str, scale: float = 1.5) -> Environment:
    return Environment(EnvironmentMap(filename, read_texture(filename), ROTATION, scale))


def _texture_unit_error(filename: str, scale: float) -> float:
    """How far Mitsuba's envmap lookups may be from float32 bilinear interpolation: on CUDA
    they run in the texture units, whose weights hold 8 fractional bits (CUDA programming
    guide, linear filtering), so each axis's weight is off by up to 2^-8 of the texel range;
    0 on LLVM, where Mitsuba interpolates in float32 as ours does."""
    if BACKEND_NAME != "cuda":
        return 0.0
    texels = read_texture(filename)
    return 2 * 2.0 ** -8 * scale * float(texels.max() - texels.min())


def _directions(rng, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("image", ["exr", "png"])
def test_envmap_radiance_is_mitsubas(maps, image):
    """Random directions through a rotated, scaled map: Mitsuba's ``eval`` to float32
    round-off (the rotation of the direction)."""
    mi = mitsuba_module()
    rng = np.random.default_rng(2)
    d = _directions(rng, 20_000)
    theirs = mi.load_dict({"type": "envmap", "filename": maps[image], "scale": 1.5,
                           "to_world": mi.ScalarTransform4f(ROTATION)})
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*(-d.T))
    reference = np.asarray(theirs.eval(si), np.float64)
    ours = np.asarray(_environment(maps[image]).radiance(Array3f(*d.T)), np.float64)
    np.testing.assert_allclose(ours, reference, rtol=1e-4, atol=1e-5 * reference.max()
                               + _texture_unit_error(maps[image], 1.5))


def _bilinear_reference(texels: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The map's radiance at (u, v) in float64, written from the module docstring's rule
    (texel centres across u, periodic; rows on [0, 1] down v)."""
    height, width = texels.shape[:2]
    x, y = u * width - 0.5, v * (height - 1)
    x0, y0 = np.floor(x).astype(int), np.minimum(np.floor(y).astype(int), height - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    t = lambda r, c: texels[r, c % width]  # noqa: E731
    return ((1 - fy) * ((1 - fx) * t(y0, x0) + fx * t(y0, x0 + 1))
            + fy * ((1 - fx) * t(y0 + 1, x0) + fx * t(y0 + 1, x0 + 1)))


def test_importance_sampling_integrates_the_map(maps):
    """E[L / pdf] over 2^20 samples equals the integral of L over the sphere, computed by a
    float64 midpoint quadrature (2000 x 2000 in (u, v), sin(theta) Jacobian) of the map's
    own bilinear rule; every sample's density is what ``pdf`` says, and nothing lands
    where the map is black."""
    environment = _environment(maps["exr"], scale=1.0)
    texels = read_texture(maps["exr"]).astype(np.float64)
    grid = (np.arange(2000) + 0.5) / 2000
    u, v = (a.ravel() for a in np.meshgrid(grid, grid))
    integral = (_bilinear_reference(texels, u, v) * np.sin(np.pi * v)[:, None]).mean(axis=0) * 2 * np.pi ** 2
    rng = np.random.default_rng(4)
    numbers = rng.random((3, 1 << 20)).astype(np.float32)
    d, pdf, radiance = environment.sample(*(Float(n) for n in numbers))
    pdf, radiance = np.asarray(pdf, np.float64), np.asarray(radiance, np.float64)
    assert (pdf > 0).all()
    np.testing.assert_allclose(np.asarray(environment.pdf(d)), pdf, rtol=1e-6)
    terms = radiance / pdf
    estimate, error = terms.mean(axis=1), terms.std(axis=1) / np.sqrt(terms.shape[1])
    assert (np.abs(estimate - integral) < 4 * error).all(), (estimate, integral, error)
    assert (error < 2e-3 * integral).all()  # the test is sharp: importance sampling works
    # The density is a density: its integral over the sphere (uniform directions) is 1.
    uniform = _directions(rng, 1 << 20)
    mass = np.asarray(environment.pdf(Array3f(*uniform.T)), np.float64).mean() * 4 * np.pi
    assert abs(mass - 1.0) < 0.01, mass


def test_a_black_map_is_not_sampled(tmp_path):
    mi = mitsuba_module()
    path = tmp_path / "black.exr"
    mi.Bitmap(np.zeros((4, 8, 3), np.float32), mi.Bitmap.PixelFormat.RGB).write(str(path))
    environment = _environment(str(path))
    assert not environment.sampled
    assert not np.asarray(environment.radiance(Array3f(0.0, 0.0, 1.0))).any()


def _scene(light: dict) -> dict:
    return {"lights": [light], "instances": [{"model": "sphere"}]}


def test_envmap_in_a_scene_file_and_its_export(maps, tmp_path):
    """A JSON scene's envmap (its file relative to the scene, to_world as operations, scale):
    parsed once, written back by ``to_mitsuba`` so that Mitsuba's plugin sees the same map."""
    mi = mitsuba_module()
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "sky.exr").write_bytes(open(maps["exr"], "rb").read())
    light = {"type": "envmap", "filename": "maps/sky.exr", "scale": 0.5,
             "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 90}}]}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_scene(light)))
    scene = instancing.load_scene(path)
    (environment,) = scene.lights
    assert environment.filename == str((tmp_path / "maps" / "sky.exr").resolve())
    np.testing.assert_allclose(environment.to_world[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    exported = mi.load_dict(instancing.to_mitsuba(scene))
    emitter = exported.environment()
    d = _directions(np.random.default_rng(1), 5000)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*(-d.T))
    ours = np.asarray(Environment(environment).radiance(Array3f(*d.T)), np.float64)
    np.testing.assert_allclose(ours, np.asarray(emitter.eval(si)), rtol=1e-4,
                               atol=1e-6 + _texture_unit_error(maps["exr"], 0.5))


@pytest.mark.parametrize("light, words", [
    ({"type": "envmap"}, ["missing keys ['filename']"]),
    ({"type": "envmap", "filename": "none.exr"}, ["lights[0]", "none.exr", "does not exist"]),
    ({"type": "envmap", "filename": "sky.exr", "scale": -1}, ["scale", "non-negative"]),
    ({"type": "envmap", "filename": "sky.exr", "to_world": [{"scale": 2}]}, ["to_world", "rotation"]),
    ({"type": "envmap", "filename": "sky.exr", "radiance": 1}, ["unknown keys ['radiance']"]),
])
def test_bad_envmaps_name_the_problem(maps, tmp_path, light, words):
    (tmp_path / "sky.exr").write_bytes(open(maps["exr"], "rb").read())
    with pytest.raises(SceneError) as err:
        instancing.load_scene(_scene(light), base_dir=tmp_path)
    for word in words:
        assert word in str(err.value), str(err.value)


def test_one_environment_per_scene(maps):
    scene = _scene({"type": "constant", "radiance": 1})
    scene["lights"].append({"type": "envmap", "filename": maps["exr"]})
    with pytest.raises(SceneError, match="only one environment"):
        instancing.load_scene(scene)
