"""Placement invariance (instancing.scene.rendering_space): a scene far from the world origin
renders, intersects and differentiates as well as at the origin, against float64 closed forms.

The scenes are moved by offsets that no power of two divides (stress.placement), so the
float32 data differ from those at the origin and the comparison is not one of identical
numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.validation import stress
from instancing.validation.gradient_check import gradient_image
from instancing.validation.measures import block_error

ROOT = Path(__file__).resolve().parent.parent

LIGHT = np.array([2.0, -1.0, 5.0])


def test_far_from_origin_renders_as_well_as_at_the_origin_without_acne():
    """The stress suite's placement case (its full table: python -m benchmarks.stress) at
    96 x 72: lit pixels within 3 % of the float64 closed form no fewer than at the origin
    minus 0.1 %, and no acne, at 1e5, 1e6 and 1e7."""
    rows = {(r.case, r.measure): r.ours
            for r in stress.placement_rows((0.0, 1e5, 1e6, 1e7), 96, 72, mitsuba=False)}
    at_origin = rows["placement 0", "lit within 3 %"]
    assert at_origin > 0.995 and rows["placement 0", "acne pixels"] == 0
    for distance in (1e5, 1e6, 1e7):
        assert rows[f"placement {distance:g}", "acne pixels"] == 0, distance
        assert rows[f"placement {distance:g}", "lit within 3 %"] >= at_origin - 0.001, distance


def test_origin_is_the_camera_and_results_come_back_in_world():
    at = stress.placement(1e6)
    scene = instancing.load_scene(stress.ball_on_floor(at))
    eye = at + [0, -7, 4]
    np.testing.assert_array_equal(scene.origin, eye)
    np.testing.assert_array_equal(scene.to_world[1][:3, 3], (at + [0, 0, 1.0] - scene.origin)
                                  .astype(np.float32).astype(np.float64) + scene.origin)
    lo, hi = scene.bounds
    assert np.all(lo <= at + [-10, -10, 0] + 1e-6) and np.all(hi >= at + [10, 10, 2] - 1e-6)
    assert np.all(hi - lo < 21)
    # The camera and the light keep their world values.
    np.testing.assert_array_equal(scene.camera.world_from_camera.to_numpy()[0][:3, 3], eye)
    np.testing.assert_array_equal(scene.lights[0].position, at + LIGHT)
    # Every camera of a scene shares the first one's origin.
    two = stress.ball_on_floor(at)
    second = dict(two["camera"], to_world=[{"look_at": {"origin": (at + [7, 0, 4]).tolist(),
                                                        "target": at.tolist(), "up": [0, 0, 1]}}])
    two["cameras"] = [two.pop("camera"), second]
    both = instancing.load_scene(two)
    np.testing.assert_array_equal(both.origin, scene.origin)
    np.testing.assert_allclose(both.view(1).world_from_camera.to_numpy()[0][:3, 3],
                               at + [7, 0, 4] - scene.origin, atol=1e-9)


def test_intersect_answers_float64_rays_with_float64_hits_at_1e6():
    """Float64 rays 1e6 from the origin: hits within a few float32 ulps of the *local*
    coordinates (their distance from the camera, ~8), not of 1e6 (0.06)."""
    at = stress.placement(1e6)
    scene = instancing.load_scene(stress.ball_on_floor(at))
    rng = np.random.default_rng(5)
    o = np.tile(at + [0, -7, 4], (4000, 1))
    aim = at + [0, 0, 1.0] + rng.normal(size=(4000, 3)) * 0.8
    d = (aim - o).astype(np.float32).astype(np.float64)  # exact in float32, as o - origin (0)
    hits = scene.intersect(o, d)
    assert hits.p.dtype == np.float64
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    oc = o - (at + [0, 0, 1.0])
    b = np.sum(oc * unit, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - 1.0)
    ball = disc > 1e-3
    t_ref = -b[ball] - np.sqrt(disc[ball])
    p_ref = o[ball] + t_ref[:, None] * unit[ball]
    assert ball.sum() > 1000 and (hits.instance[ball] == 1).all()
    local = np.abs(p_ref - scene.origin).max()
    assert np.abs(hits.p[ball] - p_ref).max() <= 4 * np.spacing(np.float32(local))


def test_intersect_moves_float32_rays_into_rendering_space_too():
    """Float32 rays 1e6 from the origin (exact float32 values): hits as the float64
    reference of the same rays finds them, to the float32 rounding of the world points;
    the answer keeps their type. (They were left in world space and missed the scene.)"""
    at = stress.placement(1e6)
    scene = instancing.load_scene(stress.ball_on_floor(at))
    assert scene.space.moved
    rng = np.random.default_rng(6)
    o = np.tile(at + [0, -7, 4], (4000, 1)).astype(np.float32)
    d = ((at + [0, 0, 1.0] + rng.normal(size=(4000, 3)) * 0.8) - o).astype(np.float32)
    hits = scene.intersect(o, d)
    assert hits.p.dtype == np.float32 and hits.t.dtype == np.float32
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    unit = d64 / np.linalg.norm(d64, axis=1, keepdims=True)
    oc = o64 - (at + [0, 0, 1.0])
    b = np.sum(oc * unit, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - 1.0)
    ball = disc > 1e-3
    p_ref = o64[ball] + (-b[ball] - np.sqrt(disc[ball]))[:, None] * unit[ball]
    assert ball.sum() > 1000 and (hits.instance[ball] == 1).all()
    assert np.abs(hits.p[ball] - p_ref).max() <= np.spacing(np.float32(np.abs(p_ref).max()))


def test_position_aov_and_export_are_in_world_space():
    at = stress.placement(1e6)
    scene = instancing.load_scene(stress.ball_on_floor(at, 16, 12))
    image = np.asarray(instancing.render(scene, "aov", spp=1, aovs=["position", "instance"]))
    ball = image[..., 3] == 1
    assert ball.sum() > 4
    centre = at + [0, 0, 1.0]
    # World positions on the unit sphere, to float32 precision of 1e6 (0.0625 per axis).
    np.testing.assert_allclose(np.linalg.norm(image[ball][:, :3] - centre, axis=1), 1.0, atol=0.2)
    exported = instancing.to_mitsuba(scene)
    shapes = [v for v in exported.values() if isinstance(v, dict) and "to_world" in v]
    matrices = [np.asarray(s["to_world"].matrix, np.float64) for s in shapes]
    assert any(np.allclose(m[:3, 3], centre, atol=0.1) for m in matrices)


def test_translation_gradient_far_from_origin_agrees_with_the_origin_within_noise():
    """The gradient image of the ball's translation (interior, silhouette and shadow terms),
    1e6 from the origin and at it, same seed: the parameter is in world units in both, the
    rendering space holds the same float32 geometry, and the same samples drive both, so
    the two agree to rounding, far inside the Monte Carlo noise (two seeds at the origin):
    writing the parameter back for the derivative leaves the far ball where it was loaded,
    not on the float32 grid of the value read."""
    images = {}
    for distance, seed in ((0.0, 1), (0.0, 2), (1e6, 1)):
        at = stress.placement(distance)
        scene = instancing.load_scene(stress.ball_on_floor(at, 32, 24))
        params = instancing.traverse(scene)
        np.testing.assert_allclose(np.asarray(params["ball.translation"], np.float64).ravel(),
                                   at + [0, 0, 1.0], rtol=1e-7)
        images[distance, seed] = gradient_image(
            params, "ball.translation", np.array([1.0, 0.5, 0.0]), integrator="direct", spp=8,
            sppp=32, sppi=32, seed=seed)

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    near, far = images[0.0, 1], images[1e6, 1]
    assert np.abs(near).max() > 0.5
    # Seeds 1 - 14 (each against the next at the origin): 1e-5 - 5e-4.
    assert rms(far - near) < 0.01 * rms(images[0.0, 2] - near)


#: Bundled scenes whose features place things in the world: meshes, an area lamp, a spot, an
#: environment map, a heterogeneous medium, a volume-textured material, a thin lens.
MOVED_SCENES = ["forest.json", "light_area.json", "light_spot.json", "envmap.xml", "media/plume.xml",
                "materials/volume.xml", "sensors/thinlens.xml"]


@pytest.mark.parametrize("name", MOVED_SCENES)
def test_a_scene_moved_1e6_away_renders_as_where_it_was(name):
    """Everything in the scene translated by 1e6 (``stress.moved_scene``) and rendered with
    the same seed: the image of the scene where it was, up to rounding (block error against
    it under 5 % of two seeds' at the origin; 0 - 0.02 % measured)."""
    near = instancing.load_scene(ROOT / "scenes" / name)
    far = stress.moved_scene(near, stress.placement(1e6))
    assert far.space.moved and not near.space.moved
    integrator = "volpath" if near.description.media else None
    images = {}
    for key, scene, seed in (("near", near, 1), ("other seed", near, 2), ("far", far, 1)):
        scene.set_camera(scene.camera.with_size(64, 48))
        images[key] = np.asarray(instancing.render(scene, integrator, spp=32, seed=seed))[..., :3]
    assert images["near"].mean() > 0.01
    noise = block_error(images["other seed"], images["near"])
    assert block_error(images["far"], images["near"]) < 0.05 * noise


@pytest.mark.parametrize("name, integrator", [("envmap.xml", "direct"), ("light_area.json", "path")])
def test_gradients_of_a_scene_moved_1e6_away_are_those_where_it_was(name, integrator):
    """The gradient image of the first instance's translation (interior, silhouette and
    secondary terms) of a scene moved as a whole 1e6 away, same seed: the one where it was,
    to rounding (rms difference under 1 % of two seeds'; 0.03 % under the environment map
    and 0.2 % under the area lamp measured). The environment's samples are directions, held
    fixed as such in the secondary term: taken as points, the rendering space's origin, they
    made the term depend on where the scene lies (95 % of the seeds' difference)."""
    near = instancing.load_scene(ROOT / "scenes" / name)
    key = f"{near.instance_ids[0]}.translation"
    images = {}
    for label, scene, seed in (("near", near, 1), ("other seed", near, 2),
                               ("far", stress.moved_scene(near, stress.placement(1e6)), 1)):
        scene.set_camera(scene.camera.with_size(48, 36))
        images[label] = gradient_image(instancing.traverse(scene), key, np.array([1.0, 0.5, 0.2]),
                                       integrator=integrator, spp=16, sppp=16, sppi=16, seed=seed)

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    assert rms(images["near"]) > 0.05
    assert rms(images["far"] - images["near"]) < 0.01 * rms(images["other seed"] - images["near"])


def test_cameras_share_the_first_cameras_space_without_losing_precision():
    """The second camera of a scene 1e6 from the origin, rendered in the first camera's
    space 1 000 units away, sees the ball as precisely as in its own space."""
    at = stress.placement(1e6)
    desc = stress.ball_on_floor(at, 96, 72)
    far_eye = at + [0, -7, 4] + [1000.0, -1000.0, 300.0]
    first = dict(desc["camera"], to_world=[{"look_at": {
        "origin": far_eye.tolist(), "target": (at + [0, 0, 0.8]).tolist(), "up": [0, 0, 1]}}])
    desc["cameras"] = [first, desc.pop("camera")]
    shared = instancing.load_scene(desc)
    np.testing.assert_array_equal(shared.origin, far_eye)
    own = instancing.load_scene(stress.ball_on_floor(at, 96, 72))
    fraction, acne = stress.placement_figures(shared, at, 1)
    assert acne == 0 and fraction >= stress.placement_figures(own, at, 0)[0] - 0.001

