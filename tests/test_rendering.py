"""Rendering: determinism, AOV channels against direct intersection, bad settings."""

import numpy as np
import pytest

import instancing
from instancing.camera import PerspectiveCamera

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
    camera = PerspectiveCamera.from_dict(SCENE["camera"])
    o, d = camera.pixel_centre_rays()
    hits = scene.intersect(np.asarray(o).T, np.asarray(d).T)
    inst = hits.instance.reshape(30, 40)
    interior = np.ones_like(inst, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            interior &= np.roll(np.roll(inst, dy, 0), dx, 1) == inst
    interior[[0, -1], :] = interior[:, [0, -1]] = False
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
])
def test_bad_render_settings_raise_scene_errors(kwargs, message):
    scene = instancing.load_scene(SCENE)
    with pytest.raises(instancing.SceneError, match=message):
        instancing.render(scene, **kwargs)


def test_rendering_without_a_camera_is_an_error():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    with pytest.raises(instancing.SceneError, match="no 'camera'"):
        instancing.render(scene, "aov")
