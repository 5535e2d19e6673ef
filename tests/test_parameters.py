"""``instancing.traverse``: keys, update semantics, bad values, and derivatives of hits with
respect to every parameter against central differences of the float64 reference."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.validation import reference, stress
from instancing.core import transform as tf
from instancing.core.backend import Array3f, Array3f64, Float, Matrix4f, Matrix4f64, TensorXf, dr
from instancing.core.errors import SceneError, TransformError
from instancing.io.image import read_texture, write_exr
from instancing.io.scene_file import parse_transform, write_scene_with_transforms

SHEAR = [[1, 0.3, 0, 0], [0, 1, 0.2, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
SCENE = {
    "materials": {"red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}},
    "instances": [
        {"id": "ball", "model": "sphere", "material": "red",
         "to_world": [{"translate": [0.2, -0.1, 0.3]}, {"rotate": {"axis": [1, 2, 0], "angle": 25}},
                      {"scale": [1.3, 0.8, 1.1]}, {"matrix": SHEAR}]},
        {"id": "mirror", "model": "cylinder",
         "to_world": [{"translate": [4, 0, 0]}, {"reflect": "x"}, {"scale": [0.5, 0.5, 2]}]},
    ],
}


def _rays(n=64, seed=3):
    """Rays from z = -8 towards the ball, with float32-exact coordinates."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-0.4, 0.6, n), rng.uniform(-0.5, 0.3, n), np.full(n, -8.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    return o.astype(np.float32).astype(np.float64), d


def _jit(a):
    return Array3f(*[Float(np.ascontiguousarray(a[:, k], np.float32)) for k in range(3)])


def test_keys_values_and_mapping_interface():
    scene = instancing.load_scene(SCENE)
    params = instancing.traverse(scene)
    keys = list(params)
    assert keys == [f"{i}.{p}" for i in ("ball", "mirror")
                    for p in ("translation", "rotation", "scale", "to_world")] + \
        [f"{m}.reflectance" for m in scene.material_names]
    assert "red" in scene.material_names
    assert len(params) == len(keys)
    assert "red.reflectance" in params and "nobody.translation" not in params
    with pytest.raises(KeyError):
        params["ball.colour"]
    # The parts recompose to_world; the reflected cylinder has a negative z scale.
    m = np.array(params["ball.to_world"]).reshape(4, 4)
    np.testing.assert_allclose(m, scene.to_world[0], atol=1e-6)
    t = np.array(params["ball.translation"]).ravel()
    np.testing.assert_allclose(t, [0.2, -0.1, 0.3], atol=1e-7)
    assert np.array(params["mirror.scale"]).ravel()[2] < 0
    np.testing.assert_allclose(np.array(params["red.reflectance"]).ravel(), [0.8, 0.1, 0.1], atol=1e-7)


def test_setting_parts_moves_the_instance_like_the_reference():
    scene = instancing.load_scene(SCENE)
    params = instancing.traverse(scene)
    params["ball.translation"] = Array3f(0.5, 0.0, 1.0)
    params["ball.scale"] = [0.9, 0.9, 0.9]
    params.update()
    _, q, _, shear = tf.decompose(instancing.load_scene(SCENE).to_world[0])
    expected = (tf.translate([0.5, 0, 1]) @ tf.rotate_quaternion(q) @ tf.scale(0.9)).to_numpy()[0]
    expected[:3, :3] = expected[:3, :3] @ shear
    np.testing.assert_allclose(scene.to_world[0], expected, atol=1e-6)
    np.testing.assert_allclose(np.array(params["ball.to_world"]).reshape(4, 4), expected, atol=1e-6)
    o, d = _rays()
    ours = scene.intersect(o, d)
    ref = reference.intersect_instances([{"kind": "sphere", "to_world": expected}], o, d)
    np.testing.assert_array_equal(ours.instance, ref["instance"])
    assert (ref["instance"] == 0).sum() > 40
    np.testing.assert_allclose(ours.t, ref["t"], rtol=2e-6)


def test_setting_to_world_installs_it_and_redecomposes():
    scene = instancing.load_scene(SCENE)
    params = instancing.traverse(scene)
    m = (tf.translate([0, 0, 2]) @ tf.from_matrix(SHEAR) @ tf.reflect("y")).to_numpy()[0]
    params["ball.to_world"] = Matrix4f(m.tolist())
    params.update()
    np.testing.assert_allclose(scene.to_world[0], m, atol=1e-6)
    t, q, s, h = (np.array(params[f"ball.{p}"]).ravel() for p in ("translation", "rotation", "scale", "to_world"))
    np.testing.assert_allclose(t, [0, 0, 2], atol=1e-7)
    assert s[2] < 0  # the reflection
    with pytest.raises(SceneError, match=r"ball.*scale.*through \['ball.scale', 'ball.to_world'\]"):
        params["ball.to_world"] = Matrix4f(m.tolist())
        params["ball.scale"] = [1, 1, 1]
        params.update()


@pytest.mark.parametrize("key, value, words", [
    ("ball.translation", [0, float("nan"), 0], "non-finite"),
    ("ball.scale", [1, 0, 1], "zero factor"),
    ("ball.rotation", [0, 0, 0, 0], "zero quaternion"),
    ("ball.rotation", [0, 0, 0, 1e-25], "squared norm is outside float32"),  # NaN once attached
    ("ball.to_world", [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]], "singular"),
    ("red.reflectance", [0.5, float("inf"), 0.5], "non-finite"),
])
def test_bad_values_are_rejected_naming_the_parameter(key, value, words):
    params = instancing.traverse(instancing.load_scene(SCENE))
    with pytest.raises((SceneError, TransformError), match=words) as info:
        params[key] = Matrix4f(value) if key.endswith("to_world") else value
        params.update()
    assert key.split(".")[0] in str(info.value)


def test_an_update_from_a_dict_names_a_key_that_is_no_parameter():
    """A misspelt key of a dict (it had been skipped silently); an optimiser's entries that
    are no parameters' (latent variables) are skipped, as Mitsuba's update skips them."""
    params = instancing.traverse(instancing.load_scene(SCENE))
    with pytest.raises(SceneError, match="no parameter 'ball.translaton' \\(did you mean 'ball.translation'\\?\\)"):
        params.update({"ball.translaton": Array3f(0.5, 0.0, 1.0)})
    opt = dr.opt.Adam(lr=0.01)
    opt["ball.translation"] = Array3f(0.5, 0.0, 1.0)
    opt["latent"] = Float(1.0)
    params.update(opt)
    np.testing.assert_allclose(np.array(params["ball.translation"]).ravel(), [0.5, 0.0, 1.0])


def test_a_refused_update_leaves_the_scene_as_it_was():
    """A value refused at update() (here a zero scale of the mirror) stores none of the
    update's values, neither the other instances' nor the materials' and lights'; once it
    is corrected, the next update stores them all (against float64 NumPy)."""
    scene = instancing.load_scene({**SCENE, "lights": [
        {"type": "point", "id": "lamp", "position": [1, 2, -3], "intensity": 5}]})
    params = instancing.traverse(scene)
    to_world, rows, lamp = scene.to_world.copy(), _stored_rows(scene), scene.lights[0]
    params["ball.translation"] = [1.0, 2.0, 3.0]
    params["red.reflectance"] = [0.5, 0.5, 0.5]
    params["lamp.position"] = [0.0, 5.0, -5.0]
    params["mirror.scale"] = [0.0, 1.0, 1.0]
    with pytest.raises(SceneError, match="'mirror'.scale: a zero factor"):
        params.update()
    np.testing.assert_array_equal(scene.to_world, to_world)
    for stored, loaded in zip(_stored_rows(scene), rows):
        np.testing.assert_array_equal(stored, loaded)
    assert scene.materials["red"]["reflectance"] == pytest.approx([0.8, 0.1, 0.1])
    assert scene.lights[0] == lamp
    params["mirror.scale"] = [0.5, 0.5, 2.0]
    params.update()
    expected = to_world[0].copy()
    expected[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(scene.to_world[0], expected, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.diag(scene.to_world[1])[:3]), [0.5, 0.5, 2.0], atol=1e-6)
    assert scene.materials["red"]["reflectance"] == pytest.approx([0.5, 0.5, 0.5])
    assert scene.lights[0].position == (0.0, 5.0, -5.0)


def test_wrong_width_and_unconvertible_values_are_rejected():
    params = instancing.traverse(instancing.load_scene(SCENE))
    with pytest.raises(SceneError, match="width"):
        params["ball.translation"] = Array3f(Float(1, 2), 0, 0)
    with pytest.raises(SceneError, match="cannot convert"):
        params["ball.translation"] = "left"


def _reference_t(m, o, d):
    return reference.intersect_instances([{"kind": "sphere", "to_world": m}], o, d)["t"]


def _compose(t, q, s, shear):
    m = (tf.translate(t) @ tf.rotate_quaternion(q) @ tf.scale(s)).to_numpy()[0]
    m[:3, :3] = m[:3, :3] @ shear
    return m


@pytest.mark.parametrize("name", ["translation", "rotation", "scale", "to_world"])
def test_hit_derivatives_reach_every_parameter_through_the_inverse(name):
    """dt/d(param) along a random tangent vs the central difference of the float64 reference
    (step 1e-4: truncation ~1e-8, far below the 2e-3 relative tolerance that covers float32)."""
    scene = instancing.load_scene(SCENE)
    params = instancing.traverse(scene)
    base = scene.to_world[0].copy()
    t0, q0, s0, shear = tf.decompose(base)
    rng = np.random.default_rng(11)
    key = f"ball.{name}"
    value = params[key]
    dr.enable_grad(value)
    params.update()
    o, d = _rays()
    hit = scene.intersect(_jit(o), _jit(d))
    if name == "to_world":
        tangent = np.zeros((4, 4))
        tangent[:3] = rng.normal(size=(3, 4))
        dr.set_grad(value, Matrix4f(tangent.tolist()))
    else:
        tangent = rng.normal(size=4 if name == "rotation" else 3)
        dr.set_grad(value, type(value)(*tangent.tolist()))
    dr.enqueue(dr.ADMode.Forward, value)
    dr.traverse(dr.ADMode.Forward)
    ours = np.array(dr.grad(hit.t))

    h = 1e-4
    parts = {"translation": t0, "rotation": q0, "scale": s0}

    def matrix(offset):
        if name == "to_world":
            return base + offset * tangent
        moved = dict(parts)
        moved[name] = parts[name] + offset * tangent
        return _compose(moved["translation"], moved["rotation"], moved["scale"], shear)

    fd = (_reference_t(matrix(h), o, d) - _reference_t(matrix(-h), o, d)) / (2 * h)
    assert np.isfinite(fd).all()
    np.testing.assert_allclose(ours, fd, rtol=2e-3, atol=2e-3 * np.abs(fd).max())


def test_reflectance_gradient_of_the_albedo_image_is_one_on_the_instance():
    scene = instancing.load_scene({**SCENE, "camera": {
        "type": "perspective", "fov": 30, "width": 16, "height": 16,
        "to_world": [{"look_at": {"origin": [0, 0, -8], "target": [0, 0, 0], "up": [0, 1, 0]}}]}})
    params = instancing.traverse(scene)
    refl = params["red.reflectance"]
    dr.enable_grad(refl)
    params.update()
    image = instancing.render(scene, "aov", spp=4, aovs=["albedo"])
    dr.backward(dr.sum(image.array))
    # The albedo image is reflectance x coverage per channel: d(sum)/d(reflectance_c) is the
    # covered area, the same for the three channels, and the red channel's sum / 0.8.
    grad = np.array(dr.grad(refl)).ravel()
    coverage = np.array(image)[..., 0].sum() / 0.8
    assert coverage > 10
    np.testing.assert_allclose(grad, coverage, rtol=1e-5)


def test_update_accepts_an_optimizer_and_keeps_the_scene_in_sync():
    scene = instancing.load_scene(SCENE)
    params = instancing.traverse(scene)
    opt = dr.opt.Adam(lr=0.1)
    opt["ball.translation"] = params["ball.translation"]
    dr.backward(dr.sum(opt["ball.translation"]))
    opt.step()
    params.update(opt)
    moved = np.array(params["ball.translation"]).ravel()
    np.testing.assert_allclose(moved, [0.1, -0.2, 0.2], atol=1e-6)  # Adam's first step: lr * sign
    np.testing.assert_allclose(scene.to_world[0][:3, 3], moved, atol=1e-6)


def _stored_rows(scene):
    return (np.array(scene.instances.inverse_rows), np.array(scene.instances.forward_linear))


def test_update_keeps_untouched_instances_bit_for_bit():
    """Only changed and grad-enabled instances are re-installed; the others keep the rows
    rounded at load time (inverse from the float64 input), with or without derivatives.
    Grad-enabled instances hold their float64 state rounded once too: the moved ball's
    linear part (only its translation changed) is the loaded one bit for bit."""
    scene = instancing.load_scene(SCENE)
    inverse, forward = _stored_rows(scene)
    params = instancing.traverse(scene)
    params["ball.translation"] = Array3f(0.5, 0.0, 0.3)
    params.update()
    dr.enable_grad(params["ball.scale"])
    params.update()
    for rows, loaded, width in zip(_stored_rows(scene), (inverse, forward), (12, 9)):
        np.testing.assert_array_equal(rows[width:], loaded[width:])  # the mirror, untouched
    rows, _ = _stored_rows(scene)
    assert not np.array_equal(rows[3:12:4], inverse[3:12:4])          # the ball moved
    np.testing.assert_array_equal(_stored_rows(scene)[1][:9], forward[:9])  # its linear part


def test_writing_back_what_was_read_moves_nothing_far_from_the_origin():
    """1e6 from the origin, where float32 values lie 0.0625 apart: the ball's (parts), the
    floor's (whole to_world) and the lamp's places read and assigned back, as read or
    through float32, stay where they were loaded, bit for bit; a translation step of 0.01
    moves the ball by 0.01 (the float64 parameter keeps it), the other components stay."""
    keys = ("ball.translation", "ball.rotation", "ball.scale", "floor.to_world", "lights[0].position")

    def as_read(v):
        return type(v)(v)

    def through_float32(v):
        return Matrix4f(v) if isinstance(v, Matrix4f64) else Array3f(v) if isinstance(v, Array3f64) else v

    for cast in (as_read, through_float32):
        scene = instancing.load_scene(stress.ball_on_floor(stress.placement(1e6)))
        loaded, lamp = scene.to_world_of(np.arange(2)), scene.lights[0].position
        assert not np.array_equal(loaded[:, :3, 3].astype(np.float32), loaded[:, :3, 3])
        params = instancing.traverse(scene)
        assert isinstance(params["ball.translation"], Array3f64)
        assert isinstance(params["floor.to_world"], Matrix4f64)
        for key in keys:
            params[key] = cast(params[key])
        params.update()
        np.testing.assert_array_equal(scene.to_world_of(np.arange(2)), loaded)
        assert scene.lights[0].position == lamp
    params = instancing.traverse(scene)
    params["ball.translation"] = params["ball.translation"] + Array3f64(0.01, 0, 0)
    params.update()
    moved = scene.to_world_of(1)[:3, 3]
    assert abs(moved[0] - (loaded[1, 0, 3] + 0.01)) < 1e-6
    np.testing.assert_array_equal(moved[1:], loaded[1, 1:3, 3])


def test_moving_a_few_of_many_instances_updates_the_grid_in_place(monkeypatch):
    """An update that moves 3 of 60 instances re-files their grid references instead of
    building the grid anew; hits (and the remap bounds) equal those of the same transforms
    loaded afresh, and a move out of the grid's box falls back to a full build."""
    import instancing.scene.scene as scene_module
    rng = np.random.default_rng(4)
    centres = rng.uniform(-6, 6, (60, 3))
    spheres = [{"id": f"s{k}", "model": "sphere",
                "to_world": [{"translate": c.tolist()}, {"scale": 0.6}]} for k, c in enumerate(centres)]
    scene = instancing.load_scene({"instances": spheres}, accel="grid")  # (auto: the BVH on CUDA)
    assert scene.accel == "grid"
    builds = []
    original = scene_module.build_grid
    monkeypatch.setattr(scene_module, "build_grid", lambda lo, hi: builds.append(1) or original(lo, hi))
    params = instancing.traverse(scene)
    for k, step in ((3, [0.4, 0.0, -0.3]), (17, [0.0, 0.7, 0.1]), (42, [-0.5, 0.2, 0.0])):
        params[f"s{k}.translation"] = params[f"s{k}.translation"] + Array3f(*step)
    dr.enable_grad(params["s17.translation"])
    params.update()
    assert builds == []
    fresh = instancing.load_scene({"instances": [{"id": f"s{k}", "model": "sphere",
                                                  "to_world": [{"matrix": m.tolist()}]}
                                                 for k, m in enumerate(scene.instances.to_world)]})
    # Rays from random points towards the moved instances and others, near their silhouettes.
    targets = scene.instances.to_world[rng.choice([3, 17, 42, 0, 9, 30], 4000)][:, :3, 3]
    o = rng.uniform(-8, 8, (4000, 3)).astype(np.float32)
    d = (targets + rng.uniform(-0.7, 0.7, (4000, 3)) - o).astype(np.float32)
    with dr.suspend_grad():
        ours, ref = scene.intersect(o, d), fresh.intersect(o, d)
    assert np.array_equal(ours.instance, ref.instance) and np.array_equal(ours.t, ref.t)
    assert {3, 17, 42} <= set(ours.instance.tolist()) and (ours.instance >= 0).mean() > 0.5
    np.testing.assert_array_equal(np.asarray(scene.instances.remap_error),
                                  np.asarray(fresh.instances.remap_error))
    before = len(builds)  # (the fresh scene's build counted too)
    params["s5.translation"] = Array3f(40.0, 0.0, 0.0)  # out of the grid's box
    params.update()
    assert len(builds) == before + 1


def test_optimisation_steps_reuse_compiled_kernels():
    """Steps after the first two launch only kernels already compiled in this process: the
    per-step arrays never take their code from the alignment of NumPy buffers."""
    scene = instancing.load_scene({**SCENE, "camera": {
        "type": "perspective", "fov": 30, "width": 16, "height": 16,
        "to_world": [{"look_at": {"origin": [0, 0, -8], "target": [0, 0, 0], "up": [0, 1, 0]}}]},
        "lights": [{"type": "directional", "direction": [0, 0, 1], "irradiance": 2}]})
    target = np.array(instancing.render(scene, "direct", spp=2, seed=0))
    params = instancing.traverse(scene)
    opt = dr.opt.Adam(lr=0.01)
    for key in ("ball.translation", "mirror.rotation", "red.reflectance"):
        opt[key] = params[key]
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        new = []
        for step in range(5):
            dr.kernel_history()
            params.update(opt)
            image = instancing.render(scene, "direct", spp=2, seed=step + 1)
            dr.backward(dr.mean(dr.square(image.array - instancing.core.backend.TensorXf(target).array)))
            opt.step()
            dr.eval(opt)
            new.append(sum(1 for k in dr.kernel_history()
                           if k["type"] == dr.KernelType.JIT and not k.get("cache_hit", True)))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert new[2:] == [0, 0, 0], new


def _lit(lights: list) -> dict:
    return {"instances": [{"id": "ball", "model": "sphere"}], "lights": lights,
            "camera": {"type": "perspective", "width": 12, "height": 8,
                       "to_world": [{"look_at": {"origin": [0, 0, -6], "target": [0, 0, 0],
                                                 "up": [0, 1, 0]}}]}}


def test_light_parameters_are_keys_named_by_their_ids():
    params = instancing.traverse(instancing.load_scene(_lit([
        {"type": "point", "id": "lamp", "position": [1, 2, -3], "intensity": 5},
        {"type": "directional", "direction": [0, 0, 2], "irradiance": [1, 2, 3]},
        {"type": "constant", "radiance": 0.1}])))
    keys = set(params)
    assert {"lamp.position", "lamp.intensity", "lights[1].direction", "lights[1].irradiance"} <= keys
    assert len(params) == len(keys)
    np.testing.assert_array_equal(np.array(params["lamp.position"]).ravel(), [1, 2, -3])
    np.testing.assert_array_equal(np.array(params["lights[1].direction"]).ravel(), [0, 0, 1])
    with pytest.raises(KeyError):
        params["lamp.direction"]  # a point light has a position, not a direction


def test_a_moved_light_renders_as_a_scene_loaded_with_it():
    params = instancing.traverse(instancing.load_scene(_lit([
        {"type": "point", "id": "lamp", "position": [1, 2, -3], "intensity": 5}])))
    params["lamp.position"] = [-2.0, 1.0, -4.0]
    params["lamp.intensity"] = [3.0, 4.0, 5.0]
    params.update()
    moved = instancing.load_scene(_lit([{"type": "point", "id": "lamp", "position": [-2, 1, -4],
                                         "intensity": [3, 4, 5]}]))
    np.testing.assert_array_equal(np.array(instancing.render(params.scene, "direct", spp=2)),
                                  np.array(instancing.render(moved, "direct", spp=2)))


@pytest.mark.parametrize("key, value, message", [
    ("lamp.intensity", [-1.0, 0.0, 0.0], "must not be negative"),
    ("sun.direction", [0.0, 0.0, 0.0], "zero vector is not a direction"),
    ("lamp.position", [float("nan"), 0.0, 0.0], "non-finite"),
])
def test_bad_light_values_name_the_parameter(key, value, message):
    params = instancing.traverse(instancing.load_scene(_lit([
        {"type": "point", "id": "lamp", "position": [1, 2, -3], "intensity": 5},
        {"type": "directional", "id": "sun", "direction": [0, 0, 1], "irradiance": 1}])))
    params[key] = value
    with pytest.raises(SceneError, match=message) as info:
        params.update()
    assert key.split(".")[0] in str(info.value)


SKY = str(Path(__file__).resolve().parents[1] / "scenes" / "textures" / "sky.exr")


def _emitting(environment: dict) -> dict:
    """A ball lit by a rectangle lamp of a constant radiance, a textured one and ``environment``."""
    lamp = {"model": "rectangle", "to_world": [{"look_at": {"origin": [1.5, 2, -2], "target": [0, 0, 0],
                                                            "up": [0, 1, 0]}}]}
    scene = _lit([environment])
    scene["instances"] += [
        {"id": "lamp", **lamp, "emitter": {"type": "area", "radiance": [3, 2, 1]}},
        {"id": "tiles", **lamp, "to_world": [{"look_at": {"origin": [-1.5, 2, -2], "target": [0, 0, 0],
                                                          "up": [0, 1, 0]}}],
         "emitter": {"type": "area", "radiance": {"type": "checkerboard", "color0": 2, "color1": 0.5}}}]
    return scene


def test_emitted_light_is_a_key_and_renders_as_loaded(tmp_path):
    """An area lamp's constant radiance, a checkerboard lamp's colours, a constant
    environment's radiance and an environment map's texels and scale are keys (a textured
    lamp's radiance itself is not); set, the scene renders as one loaded with the new values,
    the map sampled by the density of its new texels."""
    params = instancing.traverse(instancing.load_scene(_emitting(
        {"type": "constant", "id": "sky", "radiance": 0.2})))
    assert {"lamp.emitter.radiance", "sky.radiance", "tiles.emitter.radiance.color0",
            "tiles.emitter.radiance.color1"} <= set(params)
    assert "tiles.emitter.radiance" not in params and len(params) == len(list(params))
    assert params.kind("lamp.emitter.radiance") == "emitter" and params.kind("sky.radiance") == "environment"
    params["lamp.emitter.radiance"] = [4.0, 1.0, 2.0]
    params["sky.radiance"] = [0.1, 0.3, 0.2]
    params["tiles.emitter.radiance.color1"] = [3.0, 0.2, 0.1]
    params.update()
    expected = _emitting({"type": "constant", "id": "sky", "radiance": [0.1, 0.3, 0.2]})
    expected["instances"][1]["emitter"]["radiance"] = [4, 1, 2]
    expected["instances"][2]["emitter"]["radiance"]["color1"] = [3, 0.2, 0.1]
    for integrator in ("direct", "path"):
        np.testing.assert_allclose(np.array(instancing.render(params.scene, integrator, spp=4, seed=1)),
                                   np.array(instancing.render(instancing.load_scene(expected), integrator,
                                                              spp=4, seed=1)), rtol=1e-6, atol=1e-7)

    params = instancing.traverse(instancing.load_scene(_emitting(
        {"type": "envmap", "id": "sky", "filename": SKY, "scale": 0.8})))
    texels = np.array(params["sky.data"])
    assert texels.shape == read_texture(SKY).shape and float(params["sky.scale"][0]) == pytest.approx(0.8)
    assert params.bounds("sky.data") == (0.0, np.inf) and params.bounds("lamp.emitter.radiance")[0] == 0.0
    turned = np.ascontiguousarray(texels[:, ::-1] * [0.5, 1.0, 2.0]).astype(np.float32)
    write_exr(tmp_path / "turned.exr", turned)
    params["sky.data"] = turned
    params["sky.scale"] = 1.3
    params.update()
    expected = instancing.load_scene(_emitting({"type": "envmap", "id": "sky", "scale": 1.3,
                                                "filename": str(tmp_path / "turned.exr")}))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "direct", spp=4, seed=1)),
                               np.array(instancing.render(expected, "direct", spp=4, seed=1)),
                               rtol=1e-5, atol=1e-6)


def test_recorded_optimisation_steps_recover_emitted_light():
    """Recorded optimisation steps (instancing.OptimisationStep) on an area lamp's radiance
    and an environment map's scale and texels: the loss falls, the values stay in their
    ranges, and steps after the third launch no new kernel."""
    target = instancing.render(instancing.load_scene(_emitting(
        {"type": "envmap", "id": "sky", "filename": SKY, "scale": 1.5})), "direct", spp=64, seed=0)
    start = _emitting({"type": "envmap", "id": "sky", "filename": SKY, "scale": 0.5})
    start["instances"][1]["emitter"]["radiance"] = [1, 1, 1]
    params = instancing.traverse(instancing.load_scene(start))
    opt = dr.opt.Adam(lr=0.05)
    for key in ("lamp.emitter.radiance", "sky.scale", "sky.data"):
        opt[key] = params[key]
    step = instancing.OptimisationStep(params, opt, lambda image, t: dr.mean(dr.square(image.array - t.array)),
                                       spp=8)
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        losses, new = [], []
        for k in range(12):
            dr.kernel_history()
            losses.append(float(step(k, target)[0]))
            new.append(sum(1 for h in dr.kernel_history()
                           if h["type"] == dr.KernelType.JIT and not h.get("cache_hit", True)))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert losses[-1] < 0.2 * losses[0], losses
    assert new[3:] == [0] * 9, new
    assert np.array(params["sky.data"]).min() >= 0 and float(params["sky.scale"][0]) > 0.5


def test_a_lamp_bitmap_is_one_key_for_the_lamps_sharing_it(tmp_path):
    """A batch of lamps shares one emitter, so one bitmap: one key, under the first lamp,
    and setting it changes every lamp of the batch as a scene loaded with the new bitmap."""
    tiles = str(Path(__file__).resolve().parents[1] / "scenes" / "materials" / "textures" / "tiles.png")

    def scene(filename):
        description = _lit([{"type": "constant", "radiance": 0.1}])
        description["instances"].append({
            "id": "lamps", "model": "rectangle",
            "emitter": {"type": "area", "radiance": {"type": "bitmap", "filename": filename}},
            "to_world": np.stack([parse_transform([{"look_at": {"origin": [x, 2, -2], "target": [0, 0, 0],
                                                                "up": [0, 1, 0]}}], "lamp").to_numpy()[0]
                                  for x in (1.5, -1.5)])})
        return description

    params = instancing.traverse(instancing.load_scene(scene(tiles)))
    lamp_keys = [key for key in params if "emitter" in key]
    assert lamp_keys == ["lamps[0].emitter.radiance.data"] and params.kind(lamp_keys[0]) == "emitter"
    texels = np.array(params[lamp_keys[0]])
    np.testing.assert_array_equal(texels, read_texture(tiles))
    changed = np.ascontiguousarray(texels[::-1] * [2.0, 1.0, 0.5]).astype(np.float32)
    params[lamp_keys[0]] = changed
    params.update()
    write_exr(tmp_path / "changed.exr", changed)
    expected = instancing.load_scene(scene(str(tmp_path / "changed.exr")))
    for integrator in ("direct", "path"):
        np.testing.assert_allclose(np.array(instancing.render(params.scene, integrator, spp=4, seed=1)),
                                   np.array(instancing.render(expected, integrator, spp=4, seed=1)),
                                   rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("kind, field", [("spot", "texture"), ("projector", "irradiance")])
def test_a_spot_or_projector_bitmap_is_a_key_and_renders_as_loaded(kind, field, tmp_path):
    """A spot's texture and a projector's irradiance given by a bitmap: its texels are the
    key Mitsuba names (``"<light>.texture.data"``, ``"<light>.irradiance.data"``); set, the
    scene renders as one loaded with the new bitmap; negative texels are refused."""
    tiles = str(Path(__file__).resolve().parents[1] / "scenes" / "materials" / "textures" / "tiles.png")

    def scene(filename):
        return _lit([{"type": kind, "id": "lamp", field: {"type": "bitmap", "filename": filename},
                      "to_world": [{"look_at": {"origin": [0, 1, -4], "target": [0, 0, 0], "up": [0, 1, 0]}}]}])

    params = instancing.traverse(instancing.load_scene(scene(tiles)))
    key = f"lamp.{field}.data"
    assert key in set(params) and params.kind(key) == "light" and len(params) == len(list(params))
    texels = np.array(params[key])
    np.testing.assert_array_equal(texels, read_texture(tiles))
    changed = np.ascontiguousarray(texels[:, ::-1] * [0.5, 2.0, 1.0]).astype(np.float32)
    params[key] = changed
    params.update()
    write_exr(tmp_path / "changed.exr", changed)
    expected = instancing.load_scene(scene(str(tmp_path / "changed.exr")))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "direct", spp=4, seed=1)),
                               np.array(instancing.render(expected, "direct", spp=4, seed=1)),
                               rtol=1e-6, atol=1e-7)
    changed[0, 0, 0] = -1.0
    params[key] = changed
    with pytest.raises(SceneError, match=f"{key!r} must not be negative"):
        params.update()


@pytest.mark.parametrize("key, value, message", [
    ("lamp.emitter.radiance", [1.0, -0.5, 0.0], "must not be negative"),
    ("sky.scale", -1.0, "must not be negative"),
    ("sky.data", "negative", "1 negative entries of"),
    ("sky.data", "nan", "non-finite"),
    ("sky.data", "small", "expected texels of shape"),
])
def test_bad_emitted_light_values_name_the_parameter(key, value, message):
    params = instancing.traverse(instancing.load_scene(_emitting(
        {"type": "envmap", "id": "sky", "filename": SKY})))
    if key == "sky.data":
        texels = np.array(params[key])
        if value == "small":
            texels = texels[1:]
        else:
            texels[3, 5, 1] = -1.0 if value == "negative" else np.nan
        value = TensorXf(texels)
    with pytest.raises(SceneError, match=message) as info:
        params[key] = value
        params.update()
    assert repr(key) in str(info.value)


def test_light_ids_must_be_unique_and_not_name_an_instance():
    with pytest.raises(SceneError, match="also instance or material names"):
        instancing.load_scene(_lit([{"type": "point", "id": "ball", "position": [1, 2, -3],
                                     "intensity": 5}]))
    with pytest.raises(SceneError, match="naming one light"):
        instancing.load_scene(_lit([{"type": "point", "id": "a", "position": [1, 2, -3], "intensity": 5},
                                    {"type": "point", "id": "a", "position": [0, 2, -3], "intensity": 5}]))


TILES = str(Path(__file__).resolve().parents[1] / "scenes" / "materials" / "textures" / "tiles.png")
#: One material of each kind whose parameters traverse exposes differently.
MATERIALS = {
    "red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]},
    "gold": {"type": "roughconductor", "material": "Au", "alpha": 0.2},
    "mirror": {"type": "conductor", "specular_reflectance": 0.9},
    "coat": {"type": "roughplastic", "diffuse_reflectance": [0.2, 0.3, 0.6], "alpha": 0.15},
    "glass": {"type": "roughdielectric", "alpha": 0.3},
    "tiles": {"type": "plastic", "diffuse_reflectance": {"type": "bitmap", "filename": TILES}},
    "checks": {"type": "diffuse", "reflectance": {"type": "checkerboard"}},
    "sheet": {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.4}},
    "brushed": {"type": "roughconductor", "alpha_u": 0.05, "alpha_v": 0.3},
    "satin": {"type": "principled", "anisotropic": 0.6, "roughness": 0.3},
    "polar": {"type": "pplastic", "diffuse_reflectance": [0.3, 0.1, 0.4], "alpha": 0.2},
    "filter": {"type": "polarizer", "transmittance": [0.8, 0.6, 0.9]},
}


def _material_scene(materials: dict = MATERIALS) -> dict:
    names = list(materials)
    return {
        "materials": materials,
        "instances": [{"id": f"i{k}", "model": "sphere", "material": name,
                       "to_world": [{"translate": [2.2 * k - 2.2 * len(names) / 2, 0, 0]}]}
                      for k, name in enumerate(names)],
        "lights": [{"type": "point", "position": [0, 3, -6], "intensity": 40},
                   {"type": "constant", "radiance": 0.3}],
        "camera": {"type": "perspective", "fov": 90, "width": 64, "height": 24,
                   "to_world": [{"look_at": {"origin": [0, 0, -8], "target": [0, 0, 0],
                                             "up": [0, 1, 0]}}]}}


def test_material_parameters_are_the_differentiable_ones_of_each_type():
    """Keys: Mitsuba's differentiable parameters (colours, microfacet roughness, a
    conductor's eta and k, the relative index of refraction ``eta`` of rough glass and of a
    rough plastic's coating), a bitmap's texels, a checkerboard's colours; not the indices of
    refraction of smooth glass and plastics."""
    scene = instancing.load_scene(_material_scene())
    params = instancing.traverse(scene)
    keys = {key for key in params if key.split(".")[0] in MATERIALS}
    assert keys == {"red.reflectance", "gold.eta", "gold.k", "gold.specular_reflectance",
                    "gold.alpha", "mirror.eta", "mirror.k", "mirror.specular_reflectance",
                    "coat.diffuse_reflectance", "coat.specular_reflectance", "coat.alpha", "coat.eta",
                    "glass.specular_reflectance", "glass.specular_transmittance", "glass.alpha",
                    "glass.eta",
                    "tiles.diffuse_reflectance.data", "tiles.specular_reflectance",
                    "checks.reflectance.color0", "checks.reflectance.color1",
                    "sheet.eta", "sheet.k", "sheet.specular_reflectance", "sheet.alpha",
                    "brushed.eta", "brushed.k", "brushed.specular_reflectance", "brushed.alpha_u",
                    "brushed.alpha_v", "satin.base_color", "satin.roughness", "satin.anisotropic",
                    "satin.metallic", "satin.spec_trans", "satin.eta", "satin.spec_tint",
                    "satin.sheen", "satin.sheen_tint", "satin.flatness", "satin.clearcoat",
                    "satin.clearcoat_gloss", "polar.diffuse_reflectance", "polar.specular_reflectance",
                    "polar.alpha", "polar.eta", "filter.theta", "filter.transmittance"}
    assert len(params) == len(list(params))
    assert type(params["gold.alpha"]) is Float and np.array(params["gold.alpha"]).tolist() == [
        pytest.approx(0.2)]
    # Named metals give the eta and k Mitsuba's RGB variant computes.
    np.testing.assert_allclose(np.array(params["gold.eta"]).ravel(),
                               scene.materials["gold"]["eta"], rtol=1e-6)
    texels = params["tiles.diffuse_reflectance.data"]
    image = read_texture(TILES)
    assert tuple(texels.shape) == image.shape
    np.testing.assert_allclose(np.array(texels), image, atol=1e-6)


@pytest.mark.parametrize("key, value, loaded", [
    ("gold.alpha", 0.35, {"alpha": 0.35}),
    ("coat.diffuse_reflectance", [0.5, 0.1, 0.1], {"diffuse_reflectance": [0.5, 0.1, 0.1]}),
    ("gold.eta", [0.3, 0.4, 1.2], {"eta": [0.3, 0.4, 1.2], "k": None}),
    ("sheet.alpha", 0.1, {"alpha": 0.1}),
    ("glass.specular_transmittance", [0.7, 0.8, 0.9], {"specular_transmittance": [0.7, 0.8, 0.9]}),
    ("coat.alpha", 0.3, {"alpha": 0.3}),
    ("brushed.alpha_v", 0.1, {"alpha_v": 0.1}),
    ("satin.anisotropic", 0.2, {"anisotropic": 0.2}),
    ("polar.diffuse_reflectance", [0.05, 0.5, 0.1], {"diffuse_reflectance": [0.05, 0.5, 0.1]}),
    ("filter.transmittance", [0.3, 0.9, 0.5], {"transmittance": [0.3, 0.9, 0.5]}),
])
def test_a_changed_material_renders_as_a_scene_loaded_with_it(key, value, loaded):
    """Values derived from a parameter follow it (a plastic's sampling weight, a twosided
    material's back side); a conductor given a new eta keeps its k but not its name."""
    params = instancing.traverse(instancing.load_scene(_material_scene()))
    name = key.split(".")[0]
    spec = dict(MATERIALS[name]["bsdf"] if name == "sheet" else MATERIALS[name])
    if "k" in loaded:
        spec.pop("material")
        loaded = {"eta": loaded["eta"], "k": list(np.array(params["gold.k"]).ravel())}
    spec.update(loaded)
    params[key] = value
    params.update()
    assert params.scene.materials[name][key.split(".")[1]] == pytest.approx(value)
    materials = {**MATERIALS, name: {"type": "twosided", "bsdf": spec} if name == "sheet" else spec}
    expected = instancing.load_scene(_material_scene(materials))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "path", spp=4, max_depth=3)),
                               np.array(instancing.render(expected, "path", spp=4, max_depth=3)),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", ["glass", "coat", "polar"])
def test_eta_is_the_index_ratio_and_renders_as_loaded(name):
    """``eta`` (Mitsuba's traverse key of rough glass and a rough plastic's coating) is
    int_ior / ext_ior; setting it sets int_ior (the outer medium stays), which the scene
    file of a recovery writes; a coating's tables follow it."""
    params = instancing.traverse(instancing.load_scene(_material_scene()))
    material = params.scene.materials[name]
    assert float(np.array(params[f"{name}.eta"])[0]) == pytest.approx(
        material["int_ior"] / material["ext_ior"], rel=1e-6)
    params[f"{name}.eta"] = 1.3
    params.update()
    material = params.scene.materials[name]
    assert material["int_ior"] == pytest.approx(1.3 * material["ext_ior"])
    assert material.file_entries({"eta"}) == {"int_ior": pytest.approx(1.3 * material["ext_ior"])}
    materials = {**MATERIALS, name: {**MATERIALS[name], "int_ior": 1.3 * material["ext_ior"]}}
    expected = instancing.load_scene(_material_scene(materials))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "path", spp=4, max_depth=3)),
                               np.array(instancing.render(expected, "path", spp=4, max_depth=3)),
                               rtol=1e-5, atol=1e-6)
    with pytest.raises(SceneError, match=f"material '{name}': 'eta' must be positive and differ from 1"):
        params[f"{name}.eta"] = 1.0
        params.update()


def test_a_principled_eta_key_states_its_index_however_the_file_does():
    """``eta`` of a principled material given by ``specular`` (Mitsuba's default 0.5: eta
    1.5) is a key too; setting it replaces ``specular``, and renders as a scene loaded with
    that ``eta``."""
    disney = {"disney": {"type": "principled", "base_color": [0.7, 0.4, 0.2], "spec_trans": 0.4}}
    params = instancing.traverse(instancing.load_scene(_material_scene(disney)))
    assert float(np.array(params["disney.eta"])[0]) == pytest.approx(1.5, rel=1e-6)
    params["disney.eta"] = 1.3
    params.update()
    material = params.scene.materials["disney"]
    assert material.file_entries({"eta"}) == {"eta": pytest.approx(1.3), "specular": None}
    expected = instancing.load_scene(_material_scene({"disney": {**disney["disney"], "eta": 1.3}}))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "path", spp=4, max_depth=3)),
                               np.array(instancing.render(expected, "path", spp=4, max_depth=3)),
                               rtol=1e-5, atol=1e-6)


#: A leaf (a mask around a twosided diffuse) and a blend of a diffuse and a rough metal.
MIXES = {"leaf": {"type": "mask", "opacity": 0.6, "blade": {
             "type": "twosided", "bsdf": {"type": "diffuse", "reflectance": [0.2, 0.6, 0.2]}}},
         "mix": {"type": "blendbsdf", "weight": 0.3, "a": {"type": "diffuse", "reflectance": 0.4},
                 "b": {"type": "roughconductor", "alpha": 0.2}}}


def test_the_bsdfs_of_blends_and_masks_have_keys_of_their_own(tmp_path):
    """``<material>.<part>.<parameter>`` with Mitsuba's part names (``bsdf_0``, ``bsdf_1``,
    ``nested_bsdf``; a twosided part has its BSDF's keys): set, they render as a scene
    loaded with them, and a recovery's scene file writes them under the part's own key."""
    params = instancing.traverse(instancing.load_scene(_material_scene(MIXES)))
    assert {key for key in params if key.split(".")[0] in MIXES} == {
        "leaf.opacity", "leaf.nested_bsdf.reflectance", "mix.weight", "mix.bsdf_0.reflectance",
        "mix.bsdf_1.eta", "mix.bsdf_1.k", "mix.bsdf_1.specular_reflectance", "mix.bsdf_1.alpha"}
    np.testing.assert_allclose(np.array(params["leaf.nested_bsdf.reflectance"]).ravel(), [0.2, 0.6, 0.2],
                               rtol=1e-6)
    params["leaf.nested_bsdf.reflectance"] = [0.9, 0.1, 0.1]
    params["mix.bsdf_1.alpha"] = 0.5
    params.update()
    assert params.material_parameter("mix.bsdf_1.alpha") == ("mix", "alpha", 1, None)
    expected = json.loads(json.dumps(MIXES))
    expected["leaf"]["blade"]["bsdf"]["reflectance"] = [0.9, 0.1, 0.1]
    expected["mix"]["b"]["alpha"] = 0.5
    np.testing.assert_allclose(
        np.array(instancing.render(params.scene, "path", spp=4, max_depth=3)),
        np.array(instancing.render(instancing.load_scene(_material_scene(expected)), "path", spp=4,
                                   max_depth=3)), rtol=1e-5, atol=1e-6)
    entries = {"leaf": {"blade": params.scene.materials["leaf"].parts[1].file_entries({"reflectance"})},
               "mix": {"b": params.scene.materials["mix"].parts[1].file_entries({"alpha"})}}
    write_scene_with_transforms(_material_scene(MIXES), params.scene.to_world, tmp_path / "out.json",
                                materials=entries)
    written = json.loads((tmp_path / "out.json").read_text())["materials"]
    assert written["leaf"]["blade"]["bsdf"]["reflectance"] == pytest.approx([0.9, 0.1, 0.1])
    assert written["mix"]["b"]["alpha"] == pytest.approx(0.5)
    with pytest.raises(SceneError, match=r"'mix.bsdf_1.alpha': values must lie in \[0.0, inf\]"):
        params["mix.bsdf_1.alpha"] = -1.0
        params.update()


def test_checkerboard_colours_are_keys_and_render_as_loaded(tmp_path):
    """A checkerboard's ``color0`` and ``color1`` (Mitsuba's traverse has them): a colour
    parameter's as Array3f, a number parameter's (a roughness) as Float; set, they render as
    a scene loaded with them, and a recovery's scene file writes them into the texture."""
    checker = {"type": "checkerboard", "color0": [0.8, 0.2, 0.1], "color1": [0.1, 0.3, 0.7]}
    materials = {"checks": {"type": "diffuse", "reflectance": checker},
                 "bumpy": {"type": "roughconductor", "alpha": {"type": "checkerboard", "color0": 0.1,
                                                              "color1": 0.4}}}
    params = instancing.traverse(instancing.load_scene(_material_scene(materials)))
    np.testing.assert_allclose(np.array(params["checks.reflectance.color1"]).ravel(), [0.1, 0.3, 0.7],
                               rtol=1e-6)
    assert type(params["bumpy.alpha.color1"]) is Float
    params["checks.reflectance.color0"] = [0.3, 0.9, 0.3]
    params["bumpy.alpha.color1"] = 0.25
    params.update()
    expected = json.loads(json.dumps(materials))
    expected["checks"]["reflectance"]["color0"] = [0.3, 0.9, 0.3]
    expected["bumpy"]["alpha"]["color1"] = 0.25
    np.testing.assert_allclose(
        np.array(instancing.render(params.scene, "path", spp=4, max_depth=3)),
        np.array(instancing.render(instancing.load_scene(_material_scene(expected)), "path", spp=4,
                                   max_depth=3)), rtol=1e-5, atol=1e-6)
    entries = {"checks": {"reflectance": {"color0": [0.3, 0.9, 0.3]}}}
    write_scene_with_transforms(_material_scene(materials), params.scene.to_world, tmp_path / "out.json",
                                materials=entries)
    written = json.loads((tmp_path / "out.json").read_text())["materials"]["checks"]["reflectance"]
    assert written == {**checker, "color0": [0.3, 0.9, 0.3]}
    with pytest.raises(SceneError, match=r"'checks.reflectance.color1': values must lie in \[0.0, 1.0\]"):
        params["checks.reflectance.color1"] = [1.5, 0.0, 0.0]
        params.update()


def test_a_normal_mapped_bsdfs_parameters_are_its_bsdfs(tmp_path):
    """A normal-mapped BSDF (inside twosided too; and a bump-mapped one) exposes its BSDF's parameters under the
    material's name and its map's texels as ``<material>.normalmap.data`` (a bump map's as
    ``<material>.bumpmap.data``); set, they render
    as a scene loaded with them, and a recovery's scene file writes the BSDF's into the BSDF
    inside the ``normalmap`` and the map's image into its texture."""
    bumps = {"type": "bitmap", "raw": True, "filename": str(Path(__file__).resolve().parent.parent
                                                          / "scenes" / "materials" / "textures" / "bumps.png")}
    materials = {"bumpy": {"type": "normalmap", "normalmap": bumps,
                           "bsdf": {"type": "roughconductor", "alpha": 0.2}},
                 "both": {"type": "twosided", "bsdf": {"type": "normalmap", "normalmap": bumps,
                                                       "inner": {"type": "diffuse"}}},
                 "rippled": {"type": "bumpmap", "heights": bumps, "scale": 0.05,
                             "bsdf": {"type": "diffuse"}},
                 "around": {"type": "normalmap", "normalmap": bumps,
                            "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}}
    params = instancing.traverse(instancing.load_scene(_material_scene(materials)))
    assert {k for k in params if k.startswith(("bumpy.", "both.", "rippled.", "around."))} == {
        "bumpy.alpha", "bumpy.eta", "bumpy.k", "bumpy.specular_reflectance", "both.reflectance",
        "bumpy.normalmap.data", "both.normalmap.data", "rippled.reflectance", "rippled.bumpmap.data",
        "around.reflectance"}  # (a map around a twosided BSDF is no parameter)
    params["around.reflectance"] = [0.2, 0.2, 0.9]
    params["bumpy.alpha"] = 0.4
    params["both.reflectance"] = [0.9, 0.2, 0.1]
    params["rippled.reflectance"] = [0.3, 0.6, 0.2]
    # The first material's map made flat: (0.5, 0.5, 1) everywhere (the second keeps its own).
    flat = np.broadcast_to(np.float32([0.5, 0.5, 1.0]), params["bumpy.normalmap.data"].shape).copy()
    params["bumpy.normalmap.data"] = flat
    params["rippled.bumpmap.data"] = flat  # (a constant height: no slope)
    params.update()
    write_exr(tmp_path / "flat.exr", flat)
    entries = {"bumpy": {"alpha": 0.4, "normalmap": "flat.exr"}, "both": {"reflectance": [0.9, 0.2, 0.1]},
               "rippled": {"reflectance": [0.3, 0.6, 0.2], "bumpmap": "flat.exr"},
               "around": {"reflectance": [0.2, 0.2, 0.9]}}
    write_scene_with_transforms(_material_scene(materials), params.scene.to_world, tmp_path / "out.json",
                                materials=entries)
    written = json.loads((tmp_path / "out.json").read_text())["materials"]
    assert written["bumpy"]["bsdf"] == {"type": "roughconductor", "alpha": 0.4}
    assert written["bumpy"]["normalmap"] == {**bumps, "filename": "flat.exr"}
    assert written["both"]["bsdf"]["inner"] == {"type": "diffuse", "reflectance": [0.9, 0.2, 0.1]}
    assert written["rippled"]["bsdf"] == {"type": "diffuse", "reflectance": [0.3, 0.6, 0.2]}
    assert written["around"]["bsdf"]["bsdf"] == {"type": "diffuse", "reflectance": [0.2, 0.2, 0.9]}
    assert written["rippled"]["scale"] == 0.05 and written["rippled"]["heights"] == {**bumps, "filename": "flat.exr"}
    np.testing.assert_allclose(
        np.array(instancing.render(params.scene, "direct", spp=4)),
        np.array(instancing.render(instancing.load_scene(tmp_path / "out.json"), "direct", spp=4)),
        rtol=1e-5, atol=1e-6)


def test_changed_texels_render_as_a_scene_loaded_with_them(tmp_path):
    params = instancing.traverse(instancing.load_scene(_material_scene()))
    rng = np.random.default_rng(4)
    texels = rng.uniform(0, 1, params["tiles.diffuse_reflectance.data"].shape).astype(np.float32)
    params["tiles.diffuse_reflectance.data"] = texels
    params.update()
    write_exr(tmp_path / "noise.exr", texels)
    materials = {**MATERIALS, "tiles": {"type": "plastic", "diffuse_reflectance": {
        "type": "bitmap", "filename": str(tmp_path / "noise.exr")}}}
    expected = instancing.load_scene(_material_scene(materials))
    np.testing.assert_allclose(np.array(instancing.render(params.scene, "direct", spp=4)),
                               np.array(instancing.render(expected, "direct", spp=4)),
                               rtol=1e-5, atol=1e-6)


def test_a_material_refused_by_its_type_stores_no_other_material():
    """An ``eta`` of 1 for rough glass (refused by the dielectric itself) stops the update
    before another material's new roughness or the light's new position is stored."""
    params = instancing.traverse(instancing.load_scene(_material_scene()))
    params["coat.alpha"] = 0.3
    params["lights[0].position"] = [1.0, 3.0, -6.0]
    params["glass.eta"] = 1.0
    with pytest.raises(SceneError, match="material 'glass': 'eta' must be positive and differ from 1"):
        params.update()
    assert params.scene.materials["coat"]["alpha"] == pytest.approx(0.15)
    assert params.scene.lights[0].position == (0.0, 3.0, -6.0)
    params["glass.eta"] = 1.3
    params.update()
    assert params.scene.materials["coat"]["alpha"] == pytest.approx(0.3)
    assert params.scene.lights[0].position == (1.0, 3.0, -6.0)


@pytest.mark.parametrize("key, value, message", [
    ("red.reflectance", [1.2, 0.0, 0.0], r"'red.reflectance': values must lie in \[0.0, 1.0\]"),
    ("red.reflectance", [1.0000001, 0.0, 0.0], r"got 0 \.\. 1\.0000001"),  # not rounded to 1
    ("gold.alpha", -0.1, r"'gold.alpha': values must lie in \[0.0, inf\]"),
    ("gold.eta", [float("inf"), 0.0, 0.0], "'gold.eta' has non-finite"),
    ("tiles.diffuse_reflectance.data", np.full((2, 2, 3), 0.5), r"expected texels of shape"),
    # Texels: where the first bad one is, not the whole image.
    ("tiles.diffuse_reflectance.data", "nan at (1, 2, 0)",
     r"'tiles.diffuse_reflectance.data' has 1 non-finite entries of \d+, the first at index \(1, 2, 0\): nan$"),
])
def test_bad_material_values_name_the_parameter(key, value, message):
    params = instancing.traverse(instancing.load_scene(_material_scene()))
    if isinstance(value, str):
        value = np.array(params[key])
        value[1, 2, 0] = np.nan
    with pytest.raises(SceneError, match=message):
        params[key] = value
        params.update()
    assert params.bounds("red.reflectance") == (0.0, 1.0)
    assert params.bounds("i0.translation") == (-np.inf, np.inf)


# -- groups: the same parameters of many instances as one array each ----------------------------

def _row_scene(n: int = 6, batch: bool = False) -> dict:
    """n small spheres in a row (as a batch 'pebble' of the scene file, or one by one)."""
    xs = np.linspace(-2.5, 2.5, n)
    matrices = [(tf.translate([x, 0.1 * k, 0.0]) @ tf.rotate([0, 1, 1], 10.0 * k)
                 @ tf.scale([0.3, 0.35, 0.4])).to_numpy()[0] for k, x in enumerate(xs)]
    if batch:
        instances = [{"id": "pebble", "model": "sphere", "to_world": np.array(matrices)}]
    else:
        instances = [{"id": f"p{k}", "model": "sphere", "to_world": [{"matrix": m.tolist()}]}
                     for k, m in enumerate(matrices)]
    return {"instances": instances}


def _lanes(values: np.ndarray, kind=Array3f):
    return kind(*[Float(np.ascontiguousarray(values[:, k], np.float32)) for k in range(values.shape[1])])


def test_a_group_sets_its_members_as_their_own_keys_do():
    """One array per part for the group gives bit for bit the matrices that the members'
    own keys give (same float64 composition), and the members' keys then read the new
    values (and the group's the members' after they are set one by one)."""
    rng = np.random.default_rng(5)
    t, q, s = rng.normal(size=(6, 3)), rng.normal(size=(6, 4)), rng.uniform(0.2, 0.5, (6, 3))
    grouped = instancing.load_scene(_row_scene())
    params = instancing.traverse(grouped)
    keys = params.group("row", [f"p{k}" for k in (3, 1, 0, 2, 5, 4)])
    assert keys == ["row.translation", "row.rotation", "row.scale"]
    assert params.groups["row"][0] == "p3" and params.kind("row.rotation") == "group"
    order = [3, 1, 0, 2, 5, 4]
    np.testing.assert_allclose(np.array(params["row.translation"]).T,
                               grouped.to_world[order, :3, 3], atol=1e-6)
    params["row.translation"] = _lanes(t[order])
    params["row.rotation"] = _lanes(q[order], instancing.core.backend.Array4f)
    params["row.scale"] = _lanes(s[order])
    params.update()

    single = instancing.load_scene(_row_scene())
    own = instancing.traverse(single)
    for k in range(6):
        own[f"p{k}.translation"] = t[k].tolist()
        own[f"p{k}.rotation"] = instancing.core.backend.Array4f(*q[k].tolist())
        own[f"p{k}.scale"] = s[k].tolist()
    own.update()
    np.testing.assert_array_equal(grouped.to_world, single.to_world)
    np.testing.assert_allclose(np.array(params["p2.scale"]).ravel(), s[2], rtol=1e-6)

    params["p4.translation"] = [9.0, 0.0, 0.0]
    params.update()
    assert float(np.array(params["row.translation"])[0, 5]) == 9.0


def test_batches_of_the_scene_file_are_groups():
    scene = instancing.load_scene(_row_scene(batch=True))
    params = instancing.traverse(scene)
    assert params.groups == {"pebble": [f"pebble[{k}]" for k in range(6)]}
    assert dr.width(params["pebble.scale"]) == 6
    keys = list(params)
    assert [k for k in keys if k.startswith("pebble.")] == ["pebble.translation",
                                                          "pebble.rotation", "pebble.scale"]
    assert len(params) == len(keys)
    with pytest.raises(SceneError, match="not a group made by group"):
        params.ungroup("pebble")


def test_group_derivatives_equal_the_members_own():
    """d(hit distance)/d(translation, rotation, scale) through one group array equals the
    derivatives through the members' own keys, lane for lane."""
    o = np.column_stack([np.linspace(-2.5, 2.5, 48), np.full(48, 0.05), np.full(48, -8.0)])
    d = np.tile([0.0, 0.0, 1.0], (48, 1))
    o = o.astype(np.float32).astype(np.float64)
    grads = []
    for grouped in (True, False):
        scene = instancing.load_scene(_row_scene())
        params = instancing.traverse(scene)
        if grouped:
            params.group("row")
            values = [params[f"row.{p}"] for p in ("translation", "rotation", "scale")]
        else:
            values = [params[f"p{k}.{p}"] for p in ("translation", "rotation", "scale")
                      for k in range(6)]
        for v in values:
            dr.enable_grad(v)
        params.update()
        hit = scene.intersect(_jit(o), _jit(d))
        dr.backward(dr.sum(dr.select(hit.valid, hit.t, 0.0)))
        if grouped:
            grads.append(np.concatenate([np.array(dr.grad(v)).T for v in values], axis=1))
        else:
            per = [np.array(dr.grad(v)).reshape(-1) for v in values]
            grads.append(np.concatenate([np.stack(per[6 * p:6 * p + 6]) for p in range(3)], axis=1))
    assert np.abs(grads[1]).max() > 0.1
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-5, atol=1e-5 * np.abs(grads[1]).max())


def test_a_parameter_driven_by_two_keys_is_refused_naming_them():
    params = instancing.traverse(instancing.load_scene(_row_scene()))
    params.group("row", ["p0", "p1"])
    params["row.translation"] = _lanes(np.zeros((2, 3)))
    params["p1.translation"] = [0.0, 1.0, 0.0]
    with pytest.raises(SceneError, match=r"'p1'.*translation.*\['p1.translation', 'row.translation'\]"):
        params.update()

    params = instancing.traverse(instancing.load_scene(_row_scene()))
    dr.enable_grad(params["p1.rotation"])
    with pytest.raises(SceneError, match=r"p1.rotation.*carry derivatives"):
        params.group("row", ["p0", "p1"])
    params.group("other", ["p2", "p3"])
    dr.enable_grad(params["p3.to_world"])
    dr.enable_grad(params["other.scale"])
    with pytest.raises(SceneError, match=r"'p3'.*scale.*\['other.scale', 'p3.to_world'\]"):
        params.update()


@pytest.mark.parametrize("call, message", [
    (lambda p: p.group("p0", ["p1"]), "expected a new name"),
    (lambda p: p.group("a.b", ["p1"]), "expected a new name"),
    (lambda p: p.group("g", ["p1", "nope"]), "'nope'.*not in the scene"),
    (lambda p: p.group("g", []), "no.*instance ids given"),
    (lambda p: p.group("g", ["p1", "p1"]), "given twice"),
    (lambda p: p.ungroup("g"), "not a group made by group"),
])
def test_bad_groups_are_refused(call, message):
    params = instancing.traverse(instancing.load_scene(_row_scene()))
    with pytest.raises(SceneError, match=message):
        call(params)


def test_bad_group_values_name_the_member():
    params = instancing.traverse(instancing.load_scene(_row_scene()))
    params.group("row")
    with pytest.raises(SceneError, match="expected 6 value"):
        params["row.scale"] = [1.0, 1.0, 1.0]
    bad = np.ones((6, 3))
    bad[4, 1] = np.nan
    params["row.translation"] = _lanes(bad)
    with pytest.raises(SceneError, match=r"'row.translation' \(member 'p4'\).*non-finite"):
        params.update()
    params = instancing.traverse(instancing.load_scene(_row_scene()))
    params.group("row")
    q = np.ones((6, 4))
    q[2] = 0.0
    params["row.rotation"] = _lanes(q, instancing.core.backend.Array4f)
    with pytest.raises(SceneError, match="'p2'.rotation: the zero quaternion"):
        params.update()


def test_a_group_discarded_after_a_refused_update_leaves_its_members_as_installed():
    """Values of a group refused at update() (one member's zero quaternion) and then
    discarded by ungroup() are not stored for any member: their own keys read, and a later
    update of one of them keeps, the installed transforms."""
    scene = instancing.load_scene(_row_scene(3))
    loaded = scene.to_world.copy()
    params = instancing.traverse(scene)
    params.group("row")
    params["row.translation"] = _lanes(np.full((3, 3), 9.0))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    q[1] = 0.0
    params["row.rotation"] = _lanes(q, instancing.core.backend.Array4f)
    with pytest.raises(SceneError, match="'p1'.rotation: the zero quaternion"):
        params.update()
    params.ungroup("row", discard=True)
    np.testing.assert_allclose(np.array(params["p0.translation"]).ravel(), loaded[0, :3, 3], atol=1e-6)
    params["p0.scale"] = [0.2, 0.2, 0.2]
    params.update()
    np.testing.assert_array_equal(scene.to_world[1:], loaded[1:])
    np.testing.assert_allclose(scene.to_world[0, :3, 3], loaded[0, :3, 3], atol=1e-6)


def test_group_ids_given_as_one_string_are_refused():
    """``group("g", "ab")`` is not the group of instances "a" and "b"."""
    params = instancing.traverse(instancing.load_scene(
        {"instances": [{"id": x, "model": "sphere"} for x in ("a", "b", "ab")]}))
    with pytest.raises(SceneError, match="not the string 'ab'"):
        params.group("g", "ab")
    assert params.groups == {}


def test_a_square_host_array_for_a_group_of_its_size_is_refused():
    """A (3, 3) NumPy array for a 3-member group's translation reads both ways (members by
    components, Dr.Jit's components by members) and is refused rather than transposed; a
    non-square one in Dr.Jit's (3, N) layout is taken as it reads."""
    scene = instancing.load_scene(_row_scene(3))
    loaded = scene.to_world.copy()
    params = instancing.traverse(scene)
    params.group("row")
    rows = np.arange(9.0).reshape(3, 3)  # one row per member
    for value in (rows, rows.tolist()):
        with pytest.raises(SceneError, match=r"'row.translation': a \(3, 3\) array reads"):
            params["row.translation"] = value
    params.update()
    np.testing.assert_array_equal(scene.to_world, loaded)
    params.group("pair", ["p0", "p1"])
    params["pair.translation"] = rows[:2].T
    params.update()
    np.testing.assert_allclose(scene.to_world[:2, :3, 3], rows[:2])


def test_update_refuses_values_that_are_not_a_mapping():
    params = instancing.traverse(instancing.load_scene(SCENE))
    with pytest.raises(TypeError, match="values must be a mapping.*got list"):
        params.update([("ball.translation", [1.0, 2.0, 3.0])])


def test_ungroup_hands_the_members_back():
    params = instancing.traverse(instancing.load_scene(_row_scene()))
    params.group("row", ["p0", "p1"])
    params["row.translation"] = _lanes(np.array([[1.0, 2, 3], [4, 5, 6]]))
    with pytest.raises(SceneError, match="set but not updated"):
        params.ungroup("row")
    params.update()
    params.ungroup("row")
    assert "row.translation" not in params
    np.testing.assert_allclose(np.array(params["p1.translation"]).ravel(), [4, 5, 6])


def test_a_mesh_attribute_gives_its_parameter_no_key():
    """A parameter read from a mesh attribute has no material key (the attribute is a key of
    its mesh model), where a constant one of the same material has its own."""
    from pathlib import Path
    torus = Path(__file__).resolve().parent.parent / "scenes" / "meshes" / "torus_colors.ply"
    scene = instancing.load_scene({
        "models": {"t": {"type": "ply", "filename": str(torus)}},
        "materials": {"metal": {"type": "roughconductor", "specular_reflectance": [0.9, 0.8, 0.7],
                                "alpha": {"type": "mesh_attribute", "name": "vertex_roughness"}}},
        "instances": [{"model": "t", "material": "metal"}]})
    params = instancing.traverse(scene)
    keys = [key for key in params.keys() if key.startswith("metal.")]
    assert "metal.specular_reflectance" in keys
    assert not [key for key in keys if key.startswith("metal.alpha")], keys
    assert [key for key in params.keys() if key.startswith("t.")] == ["t.vertex_roughness"]
    assert params.kind("t.vertex_roughness") == "mesh"


def test_mesh_attributes_are_keys_of_their_model_and_render_as_loaded(tmp_path):
    """The attributes that materials read are keys of their mesh model, ``"<model>.<name>"``
    (per vertex or per face, (N, dim)); set, the scene renders as one loaded from a PLY file
    holding the new values, with every instance of the model showing them."""
    import plyfile
    torus = Path(__file__).resolve().parents[1] / "scenes" / "meshes" / "torus_colors.ply"

    def scene(path):
        return instancing.load_scene({
            "models": {"t": {"type": "ply", "filename": str(path)}},
            "materials": {
                "paint": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}},
                "metal": {"type": "roughconductor",
                          "specular_reflectance": {"type": "mesh_attribute", "name": "face_tint_color"},
                          "alpha": {"type": "mesh_attribute", "name": "vertex_roughness"}}},
            "instances": [{"model": "t", "material": "paint", "to_world": [{"translate": [-1.2, 0, 0]}]},
                          {"model": "t", "material": "metal", "to_world": [{"translate": [1.2, 0, 0]},
                                                                           {"rotate": {"axis": [1, 0, 0], "angle": 60}}]}],
            "lights": [{"type": "point", "position": [0, 3, -4], "intensity": 30}],
            "camera": {"type": "perspective", "fov": 50, "width": 32, "height": 16, "to_world": [
                {"look_at": {"origin": [0, 1, -5], "target": [0, 0, 0], "up": [0, 1, 0]}}]}})

    params = instancing.traverse(scene(torus))
    assert {"t.vertex_color", "t.face_tint_color", "t.vertex_roughness"} == {
        key for key in params if key.startswith("t.")}
    data = plyfile.PlyData.read(str(torus))
    vertex, face = data["vertex"].data, data["face"].data
    colour = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
    np.testing.assert_array_equal(np.array(params["t.vertex_color"]), colour)
    assert np.array(params["t.vertex_roughness"]).shape == (len(vertex), 1)
    assert np.array(params["t.face_tint_color"]).shape == (len(face), 3)
    rng = np.random.default_rng(3)
    new = {"t.vertex_color": rng.random(colour.shape).astype(np.float32),
           "t.face_tint_color": rng.random((len(face), 3)).astype(np.float32),
           "t.vertex_roughness": (0.05 + 0.4 * rng.random((len(vertex), 1))).astype(np.float32)}
    for key, value in new.items():
        params[key] = value
    params.update()
    for c, name in enumerate(("red", "green", "blue")):
        vertex[name] = new["t.vertex_color"][:, c]
    vertex["roughness_0"] = new["t.vertex_roughness"][:, 0]
    for c, name in enumerate(("tint_r", "tint_g", "tint_b")):
        face[name] = new["t.face_tint_color"][:, c]
    data.write(str(tmp_path / "changed.ply"))
    expected = scene(tmp_path / "changed.ply")
    for integrator in ("direct", "path"):
        np.testing.assert_allclose(np.array(instancing.render(params.scene, integrator, spp=4, seed=1)),
                                   np.array(instancing.render(expected, integrator, spp=4, seed=1)),
                                   rtol=1e-6, atol=1e-7)
    with pytest.raises(SceneError, match=r"'t.vertex_color': expected values of shape \(288, 3\)"):
        params["t.vertex_color"] = new["t.vertex_color"][:5]
    # The scene's own method names the attribute and the problem.
    model = [spec.name for spec in params.scene.description.models].index("t")
    for name, values, words in (("vertex_color", np.zeros((2, 3)), "shape (288, 3)"),
                                ("vertex_color", np.full((288, 3), np.nan), "864 non-finite"),
                                ("vertex_normal", np.zeros((288, 3)), "no attribute 'vertex_normal'")):
        with pytest.raises(SceneError, match=re.escape(words)):
            params.scene.set_mesh_attribute(model, name, values)
