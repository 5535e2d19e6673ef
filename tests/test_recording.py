"""Repeated renders replayed from a ``dr.freeze`` recording (instancing.rendering.recording): equal, bit for
bit, to renders traced afresh, across seeds, scene changes and settings."""

from pathlib import Path

import drjit as dr
import numpy as np
import pytest

import instancing
from instancing.core import kernel_recording
from instancing.rendering import recording as frozen
from instancing.core.backend import Array3f

SCENES = Path(__file__).resolve().parent.parent / "scenes"
SIZE = {"width": 24, "height": 18}


def _plain(scene, integrator, **kwargs):
    """A render traced afresh."""
    return np.asarray(instancing.render(scene, integrator, frozen=False, **SIZE, **kwargs))


def _replayed(scene, integrator, **kwargs):
    """A render as by default: recorded at the first call per setting, replayed later."""
    return np.asarray(instancing.render(scene, integrator, **SIZE, **kwargs))


def _recordings(scene):
    """Frozen functions held for the scene's current revision."""
    return kernel_recording.recordings_of(scene, "render").functions()


@pytest.mark.parametrize("name, integrators", [
    ("cornell_box", ("aov", "direct", "path")),
    ("light_area", ("direct", "path")),
    ("light_constant", ("direct",)),
    ("light_directional", ("direct",)),
    ("light_point", ("direct",)),
    ("affine_shapes", ("path",)),
])
def test_replays_equal_fresh_renders_for_every_seed(name, integrators):
    scene = instancing.load_scene(SCENES / f"{name}.json")
    for integrator in integrators:
        for seed in (0, 1, 2):
            assert np.array_equal(_replayed(scene, integrator, spp=2, seed=seed),
                                  _plain(scene, integrator, spp=2, seed=seed)), (integrator, seed)
    # One recording per integrator, replayed for every later seed.
    assert sorted(f.n_recordings for f in _recordings(scene)) == [1] * len(integrators)


def test_replays_launch_only_cached_kernels_and_record_once():
    scene = instancing.load_scene(SCENES / "light_area.json")
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):  # (JIT flags are part of a recording's key)
        _replayed(scene, "direct", spp=1, seed=0)
        dr.kernel_history()
        _replayed(scene, "direct", spp=1, seed=5)
        history = dr.kernel_history()
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    assert jit and all(k["cache_hit"] for k in jit)
    (function,) = _recordings(scene)
    assert function.n_recordings == 1


@pytest.mark.parametrize("name, change", [
    # A structural change (set_transforms: a new revision) and an array replaced in place.
    ("translation", lambda value: value + Array3f(0.3, -0.2, 0.1)),
    ("reflectance", lambda value: Array3f(0.1, 0.9, 0.3)),
])
def test_replays_render_the_scene_as_changed_through_its_parameters(name, change):
    scene = instancing.load_scene(SCENES / "light_point.json")
    before = _replayed(scene, "direct", spp=2, seed=3)
    params = instancing.traverse(scene)
    key = next(k for k in params if k.endswith("." + name))
    params[key] = change(params[key])
    params.update()
    after = _replayed(scene, "direct", spp=2, seed=3)
    assert not np.array_equal(after, before)
    assert np.array_equal(after, _plain(scene, "direct", spp=2, seed=3))


def test_other_settings_get_their_own_recording():
    scene = instancing.load_scene(SCENES / "cornell_box.json")
    for spp, width in ((1, 24), (2, 24), (1, 20)):
        image = np.asarray(instancing.render(scene, "direct", spp=spp, width=width, height=18, seed=1))
        reference = np.asarray(instancing.render(scene, "direct", spp=spp, width=width, height=18,
                                                 seed=1, frozen=False))
        assert np.array_equal(image, reference), (spp, width)
    scene.set_accel("grid")  # a structural change: recordings of the old revision go
    assert _recordings(scene) == []
    assert np.array_equal(_replayed(scene, "direct", spp=1, seed=1), _plain(scene, "direct", spp=1, seed=1))


def test_a_failed_recording_falls_back_to_fresh_renders(monkeypatch):
    scene = instancing.load_scene(SCENES / "light_point.json")
    # Without the scene's arrays as inputs, recording fails (they predate it).
    monkeypatch.setattr(frozen, "jit_state", lambda *roots: [])
    image = _replayed(scene, "direct", spp=2, seed=4)
    assert np.array_equal(image, _plain(scene, "direct", spp=2, seed=4))
    assert np.array_equal(_replayed(scene, "direct", spp=2, seed=5), _plain(scene, "direct", spp=2, seed=5))
    assert _recordings(scene) == []


def test_ctrl_c_while_recording_stops_the_render_instead_of_counting_as_a_failure(monkeypatch):
    """dr.freeze reports a KeyboardInterrupt raised while it records as a RuntimeError caused
    by it; the render re-raises the interrupt (it once fell back to a plain render)."""
    scene = instancing.load_scene(SCENES / "light_point.json")

    def interrupted(*roots):
        raise KeyboardInterrupt

    monkeypatch.setattr(frozen, "jit_state", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _replayed(scene, "direct", spp=2, seed=4)


def test_renders_are_recorded_unless_asked_not_to_or_reporting_progress():
    scene = instancing.load_scene(SCENES / "light_point.json")
    _plain(scene, "direct", spp=1, seed=0)
    instancing.render(scene, "direct", spp=1, progress=lambda done: None, **SIZE)
    assert _recordings(scene) == []
    _replayed(scene, "direct", spp=1, seed=0)
    assert len(_recordings(scene)) == 1


@pytest.mark.skipif(instancing.core.backend.BACKEND_NAME != "llvm", reason="reads LLVM IR")
@pytest.mark.parametrize("integrator", ["direct", "path"])
def test_a_recorded_kernel_reads_no_more_by_gather_than_the_plain_one(integrator):
    """Reads from a jit array at trace-time indices are scalar loads in a plain kernel but
    16-lane gathers in a recording; the unrolled instances' and the emitters' world boxes
    are opaque scalars instead, so the recorded render kernel has no more gathers than the
    plain one (read from one flat array: 130 against 34 for light_area's 'direct')."""
    scene = instancing.load_scene(SCENES / "light_area.json")

    def gathers(render):
        render(scene, integrator, spp=1, seed=0)
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            render(scene, integrator, spp=1, seed=1)
            history = dr.kernel_history()
        kernel = max((k for k in history if k["type"] == dr.KernelType.JIT),
                     key=lambda k: k["operation_count"])
        ir = kernel["ir"]
        return (ir.getvalue() if hasattr(ir, "getvalue") else str(ir)).count("@llvm.masked.gather")

    plain, replayed = gathers(_plain), gathers(_replayed)
    assert plain > 0 and replayed <= plain


def test_a_rendered_and_queried_scene_is_freed_with_its_recordings():
    """A frozen function keeps the arguments of its calls, the scene among them; the scene
    holds its recordings, so the collector frees both (a table keyed by the scene in a weak
    dictionary kept every rendered scene alive)."""
    import gc
    import weakref

    scene = instancing.load_scene(SCENES / "light_point.json")
    _replayed(scene, "direct", spp=1, seed=0)
    for _ in range(2):  # (a query's width is recorded at its second call)
        scene.intersect(np.zeros((4, 3)), np.tile([0.0, 0.0, 1.0], (4, 1)))
    assert _recordings(scene) and kernel_recording.recordings_of(scene, "intersect").functions()
    alive = weakref.ref(scene)
    del scene
    gc.collect()
    assert alive() is None
