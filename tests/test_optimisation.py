"""Optimisation steps replayed from a ``dr.freeze`` recording (instancing.ad.optimisation): the
same losses and parameters as steps traced afresh, across grid updates, grid and BVH
rebuilds and learning-rate schedules, without tracing the render again."""

import re

import drjit as dr
import drjit.opt
import numpy as np
import pytest

import instancing
import instancing.rendering.film
from instancing.core.backend import Float, TensorXf
from instancing.core.errors import SceneError
from instancing.ad.optimisation import OptimisationStep
from instancing.ad.recovery import image_loss

SIZE = 32


def _scene(count: int, accel: str = "auto", more_cameras: tuple = ()) -> instancing.Scene:
    """``count`` spheres in a row in front of a wall (two materials), a point light; one
    camera, and ``more_cameras``."""
    xs = np.linspace(-1.6, 1.6, count)
    instances = [{"id": f"s{i}", "model": "sphere", "material": "paint" if i % 2 else "clay",
                  "to_world": [{"translate": [float(x), 0.3 * (i % 3) - 0.3, 0]}, {"scale": 0.3}]}
                 for i, x in enumerate(xs)]
    instances.append({"id": "wall", "model": "rectangle", "material": "clay",
                      "to_world": [{"translate": [0, 0, 2]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}},
                                   {"scale": 4}]})
    return instancing.load_scene({
        "cameras": [{"type": "perspective", "fov": 50, "width": SIZE, "height": SIZE,
                     "to_world": [{"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0],
                                               "up": [0, 1, 0]}}]}, *more_cameras],
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]},
                      "clay": {"type": "diffuse", "reflectance": [0.4, 0.4, 0.4]}},
        "lights": [{"type": "point", "position": [1, 2, -5], "intensity": [30, 30, 30]}],
        "instances": instances}, accel=accel)


def _run(count, accel, frozen, steps, moved=(0, 3), lr=0.05, jump=None, grouped=False):
    """Losses and final parameters of ``steps`` steps; ``jump``: (step, instance, offset) moves
    an instance by hand before that step (out of the grid's box: a full rebuild);
    ``grouped``: the moved instances' translations as one group array."""
    scene = _scene(count, accel)
    target = TensorXf(np.asarray(instancing.render(scene, "direct", spp=4, seed=9), np.float32))
    params = instancing.traverse(scene)
    opt = drjit.opt.Adam(lr=lr)
    if grouped:
        params.group("moved", [f"s{i}" for i in moved])
        opt["moved.translation"] = params["moved.translation"] + Float(0.15)
    for i in moved if not grouped else ():
        opt[f"s{i}.translation"] = params[f"s{i}.translation"] + Float(0.15)
    opt["paint.reflectance"] = params["paint.reflectance"]
    step = OptimisationStep(params, opt, image_loss, spp=2, frozen=frozen)
    losses = []
    for it in range(steps):
        opt.set_learning_rate(dr.opaque(Float, lr * 0.9 ** it))
        if jump is not None and it == jump[0]:
            key = f"s{jump[1]}.translation"
            opt[key] = opt[key] + Float(jump[2])
        losses.append(float(step(it, target)[0]))
    values = {key: np.array(opt[key]).ravel() for key in opt.keys()}
    return losses, values, step, scene


@pytest.mark.parametrize("count, accel, jump", [
    (6, "auto", None),             # unrolled: the world boxes are opaque inputs
    (30, "auto", None),            # grid: the moved instances re-filed in place
    (30, "auto", (3, 0, 9.0)),     # grid: a sphere leaves the grid's box, full rebuild
    (30, "bvh", None),             # BVH rebuilt every step
])
def test_replayed_steps_equal_traced_steps(count, accel, jump, one_thread):
    traced = _run(count, accel, False, 6, jump=jump)
    replayed = _run(count, accel, True, 6, jump=jump)
    np.testing.assert_allclose(replayed[0], traced[0], rtol=1e-4)
    for key, value in traced[1].items():
        np.testing.assert_allclose(replayed[1][key], value, rtol=0, atol=1e-5, err_msg=key)
    # The optimisation did something: the parameters left their start.
    assert abs(traced[0][-1] - traced[0][0]) > 1e-3 * traced[0][0]
    assert replayed[3].accel == traced[3].accel


def test_a_group_steps_as_its_members_own_keys_do(one_thread):
    """Optimising translations through one group array: the losses and values of the
    members' own keys (Adam is elementwise), replayed. (On one thread: with several, the
    atomic sums of the gradients vary by a few ulps from run to run, and 30 steps made that
    1.3e-5 in a translation.)"""
    own = _run(30, "auto", True, 5, moved=(0, 3, 7))
    grouped = _run(30, "auto", True, 5, moved=(0, 3, 7), grouped=True)
    np.testing.assert_allclose(grouped[0], own[0], rtol=1e-4)
    lanes = grouped[1]["moved.translation"].reshape(3, -1)
    for k, i in enumerate((0, 3, 7)):
        np.testing.assert_allclose(lanes[:, k], own[1][f"s{i}.translation"], atol=1e-5)
    assert grouped[2].recordings <= 2 and abs(own[0][-1] - own[0][0]) > 1e-3 * own[0][0]


def test_a_learning_rate_shared_by_several_keys_steps_each_key_by_it():
    """Adam's first step moves every component with a gradient by the learning rate (the
    debiased moments are g and g^2), for each key alike, when one opaque rate is the default
    of all keys (Dr.Jit 1.5's optimisers multiply a rate array in place per key; the step
    gives each key its own)."""
    scene = _scene(6)
    target = TensorXf(np.asarray(instancing.render(scene, "direct", spp=4, seed=9), np.float32))
    params = instancing.traverse(scene)
    opt = drjit.opt.Adam(lr=0.05)
    keys = ("s0.translation", "s3.translation", "paint.reflectance")
    for key in keys:
        opt[key] = params[key] + Float(0.1)
    before = {key: np.array(opt[key]).ravel() for key in keys}
    opt.set_learning_rate(dr.opaque(Float, 0.02))
    step = OptimisationStep(params, opt, image_loss, spp=2)
    step(0, target)
    expected = 0.02
    for key in keys:
        moved = np.abs(np.array(opt[key]).ravel() - before[key])
        np.testing.assert_allclose(moved[moved > 0], expected, rtol=1e-3, err_msg=key)
        assert (moved > 0).sum() >= 2, key
    assert float(opt.lr[0]) == pytest.approx(0.02)


def _one_instance_run(frozen, integrator, extra_inputs):
    """Steps moving one sphere of a small scene toward its start (target rendered there);
    ``extra_inputs``: per step, the loss inputs after the target. Returns the losses, the
    final translation and the recordings made."""
    scene = _scene(6)
    params = instancing.traverse(scene)
    target = TensorXf(np.asarray(instancing.render(scene, integrator, spp=2), np.float32))
    opt = drjit.opt.Adam(lr=0.05)
    opt["s2.translation"] = params["s2.translation"] + Float(0.2)
    step = OptimisationStep(params, opt, image_loss, integrator=integrator, spp=2, frozen=frozen)
    losses = [float(step(seed, target, *extra)[0]) for seed, extra in enumerate(extra_inputs)]
    return losses, np.array(opt["s2.translation"]).ravel(), step.recordings


def test_aov_steps_replay():
    """The 'aov' integrator (default AOVs) records too: a loss on its channels steps the
    parameters like the traced step does, and the steps move the sphere's sideways offset
    (0.2, 0.2), which the image sees most, back by more than half (measured: to 0.006 and
    0.011). (Its offset along the line of sight the loss barely sees: finite differences
    show the loss falling as the sideways-offset sphere recedes, and so do the steps.)"""
    traced, replayed = (_one_instance_run(frozen, "aov", [()] * 4) for frozen in (False, True))
    np.testing.assert_allclose(replayed[0], traced[0], rtol=1e-4)
    np.testing.assert_allclose(replayed[1], traced[1], atol=1e-5)
    start = np.array(instancing.traverse(_scene(6))["s2.translation"]).ravel()
    assert 1 <= replayed[2] <= 2 and np.all(np.abs(replayed[1] - start)[:2] < 0.1)


def test_replayed_steps_do_not_trace_the_render(monkeypatch):
    """After at most two recordings (the optimiser's first step changes its state's layout),
    steps replay: the integrator's Python code is not run again."""
    calls = []
    radiance = instancing.rendering.film._radiance
    monkeypatch.setattr(instancing.rendering.film, "_radiance",
                        lambda *a, **k: calls.append(1) or radiance(*a, **k))
    losses, _, step, _ = _run(30, "auto", True, 3)
    traced_calls = len(calls)
    assert traced_calls > 0 and step.recordings <= 2
    calls.clear()
    scene = _scene(30)
    target = TensorXf(np.zeros((SIZE, SIZE, 3), np.float32))
    params = instancing.traverse(scene)
    opt = drjit.opt.Adam(lr=0.01)
    opt["s1.translation"] = params["s1.translation"]
    step = OptimisationStep(params, opt, image_loss, spp=2)
    for seed in range(6):
        step(seed, target)
        if seed == 2:
            recorded, calls[:] = step.recordings, []
    assert calls == [] and step.recordings == recorded <= 2


def test_optimisation_step_rejects_bad_input():
    scene = _scene(4)
    params = instancing.traverse(scene)
    target = TensorXf(np.zeros((SIZE, SIZE, 3), np.float32))
    opt = drjit.opt.Adam(lr=0.01)
    opt["nobody.translation"] = Float(0.0, 0.0, 0.0)
    with pytest.raises(SceneError, match="nobody.translation"):
        OptimisationStep(params, opt, image_loss)
    opt = drjit.opt.Adam(lr=0.01)
    opt["s0.translation"] = params["s0.translation"]
    with pytest.raises(SceneError, match="integrator"):
        OptimisationStep(params, opt, image_loss, integrator="photon")
    with pytest.raises(SceneError, match="spp"):
        OptimisationStep(params, opt, image_loss, spp=0)
    dr.enable_grad(params["s1.scale"])
    with pytest.raises(SceneError, match="s1.scale"):
        OptimisationStep(params, opt, image_loss, spp=1)(0, target)
    dr.disable_grad(params["s1.scale"])
    with pytest.raises(SceneError, match="one Float"):
        OptimisationStep(params, opt, lambda image, t: image.array, spp=1)(0, target)


@pytest.mark.parametrize("make_opt, loss, words", [
    (lambda: None, image_loss, "opt must be a drjit.opt optimiser"),
    (lambda: {"s0.translation": Float(0.0, 0.0, 0.0)}, image_loss, "got dict"),
    (lambda: drjit.opt.Adam(lr=0.01), None, "loss must be a function loss(image, *inputs), got NoneType")])
def test_optimisation_step_names_an_optimiser_or_loss_of_the_wrong_type(make_opt, loss, words):
    params = instancing.traverse(_scene(4))
    with pytest.raises(TypeError) as info:
        OptimisationStep(params, make_opt(), loss, spp=1)
    assert words in str(info.value), str(info.value)


def test_optimisation_step_refuses_settings_of_the_wrong_kind_by_name():
    params = instancing.traverse(_scene(4))
    opt = drjit.opt.Adam(lr=0.01)
    opt["s0.translation"] = params["s0.translation"]
    for kwargs, error, words in [
            (dict(frozen=1), TypeError, "frozen must be True or False, got 1"),
            (dict(frozen="no"), TypeError, "frozen must be True or False, got 'no'"),
            (dict(spp=None), SceneError, "spp must be an integer >= 1, got None"),
            (dict(cameras=[0, 0]), SceneError, "cameras names a view twice: [0, 0]")]:
        with pytest.raises(error) as info:
            OptimisationStep(params, opt, image_loss, **kwargs)
        assert words in str(info.value), str(info.value)
    with pytest.raises(TypeError, match="params must come from instancing.traverse"):
        OptimisationStep(params.scene, opt, image_loss)
    with pytest.raises(SceneError, match="the optimiser holds no parameters"):
        OptimisationStep(params, drjit.opt.Adam(lr=0.01), image_loss)


def test_a_numpy_input_is_passed_to_the_recorded_step_as_a_tensor():
    """A NumPy target given to a recorded step (it once aborted the process: a recording
    may not upload host data) is the same step as with the tensor."""
    scene = _scene(4)
    target = np.asarray(instancing.render(scene, "direct", spp=4, seed=9), np.float32)
    losses = []
    for given in (target, TensorXf(target)):
        params = instancing.traverse(_scene(4))
        opt = drjit.opt.Adam(lr=0.01)
        opt["s0.translation"] = params["s0.translation"] + Float(0.1)
        step = OptimisationStep(params, opt, image_loss, spp=1)
        losses.append([float(step(k, given)[0]) for k in range(3)])
        assert step.recordings >= 1
    np.testing.assert_allclose(losses[0], losses[1], rtol=1e-5)


@pytest.mark.parametrize("seed", ["1", 1.5, None, True])
def test_optimisation_step_refuses_a_seed_that_is_no_integer_before_any_work(seed):
    params = instancing.traverse(_scene(4))
    opt = drjit.opt.Adam(lr=0.01)
    opt["s0.translation"] = params["s0.translation"]
    step = OptimisationStep(params, opt, image_loss, spp=1)
    before = np.array(params["s0.translation"])
    with pytest.raises(SceneError, match=f"seed must be an integer, got {re.escape(repr(seed))}"):
        step(seed, TensorXf(np.zeros((SIZE, SIZE, 3), np.float32)))
    assert step.recordings == 0 and np.array_equal(np.array(params["s0.translation"]), before)


def test_a_loss_input_of_another_shape_records_anew():
    """The blur's width comes from its taps' length: taps of another length are a new
    recording, not a replay of the old blur (the loss equals the traced step's)."""
    from instancing.ad.recovery import blur_taps
    taps = [(blur_taps(sigma),) for sigma in (2.0, 2.0, 2.0, 0.5, 0.5)]
    traced, replayed = (_one_instance_run(frozen, "direct", taps) for frozen in (False, True))
    np.testing.assert_allclose(replayed[0], traced[0], rtol=1e-4)
    assert replayed[2] == 3  # two for the wide blur (see above), one for the narrow one


def test_a_render_between_steps_replays_without_the_boundary_term(monkeypatch):
    """Between steps the scene holds detached transforms: a preview render has no derivatives,
    so it samples no silhouettes and replays its recording, equal to a render traced afresh."""
    import instancing.rendering.film as rendering
    _, _, _, scene = _run(30, "auto", True, 2)
    assert len(scene.moving_instances) and not scene.differentiable
    sampled = []
    sampler = rendering.boundary_sampler
    monkeypatch.setattr(rendering, "boundary_sampler", lambda *a: sampled.append(1) or sampler(*a))
    replayed = [np.asarray(instancing.render(scene, "direct", spp=2, seed=s)) for s in (1, 1)]
    traced = np.asarray(instancing.render(scene, "direct", spp=2, seed=1, frozen=False))
    assert sampled == []
    np.testing.assert_array_equal(replayed[0], traced)
    np.testing.assert_array_equal(replayed[1], traced)


#: A second camera, named 'top', looking down on the row of spheres.
TOP = {"type": "perspective", "fov": 60, "width": SIZE, "height": SIZE // 2, "id": "top",
       "to_world": [{"look_at": {"origin": [0, 5, -1], "target": [0, 0, 0], "up": [0, 0, 1]}}]}


def _multi_view_run(frozen: bool, steps: int = 5, traced: list | None = None):
    """Steps over two views moving one sphere toward its start; ``traced`` (when given) is
    cleared after the second step, so that it collects what later steps trace."""
    from instancing.ad.recovery import views_loss
    scene = _scene(6, more_cameras=(TOP,))
    targets = [TensorXf(np.asarray(instancing.render(scene, "aov", spp=4, seed=9, camera=k),
                                   np.float32)) for k in (0, 1)]
    params = instancing.traverse(scene)
    opt = drjit.opt.Adam(lr=0.05)
    opt["s2.translation"] = params["s2.translation"] + Float(0.2)
    # (AOVs without the silhouette term: the views' logic at a small compile cost.)
    step = OptimisationStep(params, opt, views_loss, integrator="aov", spp=2, sppp=0,
                            cameras=[0, "top"], frozen=frozen)
    losses = []
    for seed in range(steps):
        losses.append(float(step(seed, targets)[0]))
        if seed == 1 and traced is not None:
            traced.clear()
    return losses, np.array(opt["s2.translation"]).ravel(), step.recordings


@pytest.mark.filterwarnings("ignore:the gradients leave out")
def test_multi_view_steps_replay_and_equal_traced_steps(monkeypatch):
    """A step over two views replays its recording (after the first two steps, the
    integrator's Python code is not run again) with the losses and parameters of traced
    steps."""
    traced = _multi_view_run(False)
    calls = []
    radiance = instancing.rendering.film._radiance
    monkeypatch.setattr(instancing.rendering.film, "_radiance",
                        lambda *a, **k: calls.append(1) or radiance(*a, **k))
    replayed = _multi_view_run(True, traced=calls)
    np.testing.assert_allclose(replayed[0], traced[0], rtol=1e-4)
    np.testing.assert_allclose(replayed[1], traced[1], atol=1e-5)
    assert traced[0][-1] < traced[0][0]
    assert 1 <= replayed[2] <= 2 and calls == []


def test_multi_view_step_rejects_unknown_cameras():
    params = instancing.traverse(_scene(4, more_cameras=(TOP,)))
    opt = drjit.opt.Adam(lr=0.01)
    opt["s0.translation"] = params["s0.translation"]
    for cameras, message in (("top", "non-empty list"), ([], "non-empty list"),
                             ([0, "side"], "camera 'side': no such camera"),
                             ([2], "camera 2: no such camera")):
        with pytest.raises(SceneError, match=message):
            OptimisationStep(params, opt, image_loss, cameras=cameras)


def test_ctrl_c_while_a_step_is_recorded_stops_the_step():
    """A KeyboardInterrupt raised inside the recorded step (here by the loss) reaches the
    caller as itself, not as a failed recording that the step would trace around."""
    scene = _scene(2)
    target = TensorXf(np.asarray(instancing.render(scene, "direct", spp=2, seed=9), np.float32))
    params = instancing.traverse(scene)
    opt = drjit.opt.Adam(lr=0.05)
    opt["s0.translation"] = params["s0.translation"]

    def interrupted_loss(image, target):
        raise KeyboardInterrupt

    step = OptimisationStep(params, opt, interrupted_loss, spp=2)
    with pytest.raises(KeyboardInterrupt):
        step(0, target)

