"""Optimisation steps replayed from a ``dr.freeze`` recording instead of traced again.

One step of gradient descent on instance transforms and material parameters is::

    params.update(opt)                  # host: check values, move instances, re-file grid
    image = render(scene, ...)          # Dr.Jit: interior and boundary derivative terms
    loss = loss_fn(image, *inputs)
    dr.backward(loss)
    _separate_rates(opt)
    opt.step()

Traced afresh, its Python code costs as much as its kernels in small scenes
(measured 10 spheres, 128x128, 4 spp: 85 ms per step, 41 ms of it kernels).
:class:`OptimisationStep` splits the step into the host work, which runs every
step (:meth:`SceneParameters.install`: checks, world boxes, grid references; the
moving instances' silhouette and shadow curves, :func:`instancing.rendering.film.boundary_samplers`;
the light set), and the Dr.Jit work, recorded once with ``dr.freeze`` and
replayed for later steps: attaching the optimiser's values to the installed
transforms (:meth:`SceneParameters.attach`), the render, the loss,
``dr.backward`` and ``opt.step()``. Gradients never cross the recording's
boundary (Dr.Jit 1.5 gives zero gradients there): the parameters are leaves
inside it and the optimiser consumes their gradients inside it.

What a replay relies on, and how it is kept true:

- Python values the recorded code reads form the recording's key: the render
  settings, the cameras, which parameters of which instances are optimised
  (:meth:`Attachment.key`), the scene's acceleration structure kind, the
  capacity of the curve table, the light set's layout and the shapes of the
  loss inputs. The grid's box and resolution and the BVH's root are opaque
  arrays (inputs), so an in-place grid update or a rebuild replays the same
  recording.
- Every Dr.Jit array the step reads is an input: the optimiser's state (values,
  moments, step counts and learning rates), the loss inputs, and every array
  reachable from the scene, camera, lights, curves and attachment
  (:func:`instancing.core.kernel_recording.jit_state`).
- A learning rate is part of the optimiser's state: a Python float becomes part
  of the key (a schedule that changes it every step would record every step);
  give schedules as opaque ``Float`` values (``dr.opaque(Float, rate)``), as
  :func:`instancing.ad.recovery.recover` does.
- ``path`` derivatives come from path replay, a custom operation whose derivative
  pass runs inside the AD traversal (:mod:`instancing.rendering.integrators.path`);
  its steps are traced every time, as are steps whose recording fails.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import drjit.opt
import numpy as np

from ..core.arguments import integer
from ..core.backend import Float, TensorXf, UInt32, dr
from ..core.errors import SceneError
from ..core.kernel_recording import RecordingTable, call_recorded, jit_state, python_state
from ..rendering.film import (MAX_LANES, VIEW_SEED_STRIDE, RenderSettings, _check_aovs,
                              _check_integrator, boundary_samplers, images, seed_value,
                              warn_omitted_terms)
from ..rendering.integrators.path import RR_DEPTH
from ..scene.camera import CameraBatch
from .parameters import SceneParameters


class OptimisationStep:
    """One optimisation step of ``opt`` on ``params``, recorded on first use and replayed.

    Args:
        params: the scene's parameters (:func:`instancing.traverse`).
        opt: a ``drjit.opt`` optimiser whose keys are parameters of ``params``; every
            grad-enabled parameter must be one of them.
        loss: ``loss(image, *inputs) -> Float`` (one entry), Dr.Jit code only; ``inputs``
            are the extra arguments of each call (e.g. the target image). With
            ``cameras``, ``loss(images, *inputs)``: the list of the views' images.
        integrator, spp, sppc, sppp, sppi: as :func:`instancing.render`.
        cameras: the views each step renders (indices into ``scene.cameras`` or camera
            ids); None: the first camera alone, its image passed as one tensor.
        frozen: False traces every step (the same code, for comparison).

    Calling the step with ``(seed, *inputs)`` runs update, render, loss, backward and
    the optimiser's step (material and light parameters then clipped to their valid ranges,
    :meth:`SceneParameters.bounds`), and returns the loss (a detached Float). Afterwards the
    scene holds the parameters' values before the optimiser's step, detached.
    """

    def __init__(self, params: SceneParameters, opt: Any, loss: Callable[..., Float], *,
                 integrator: str = "direct", spp: int = 16, sppc: int | None = None,
                 sppp: int | None = None, sppi: int | None = None,
                 cameras: list[int | str] | tuple | None = None, frozen: bool = True):
        if not isinstance(params, SceneParameters):
            raise TypeError(f"OptimisationStep: params must come from instancing.traverse(scene), "
                            f"got {type(params).__name__}")
        if not isinstance(opt, drjit.opt.Optimizer):
            raise TypeError(f"OptimisationStep: opt must be a drjit.opt optimiser (e.g. "
                            f"drjit.opt.Adam(lr=0.01)) holding parameters of params, got "
                            f"{type(opt).__name__}")
        if not callable(loss):
            raise TypeError(f"OptimisationStep: loss must be a function loss(image, *inputs), "
                            f"got {type(loss).__name__}")
        _check_integrator(integrator)
        spp, sppc, sppp, sppi = (
            None if value is None and name != "spp" else integer(name, value, least)
            for name, value, least in (("spp", spp, 1), ("sppc", sppc, 0), ("sppp", sppp, 0),
                                       ("sppi", sppi, 0)))
        if not isinstance(frozen, bool):
            raise TypeError(f"OptimisationStep: frozen must be True or False, got {frozen!r}")
        if not list(opt.keys()):
            raise SceneError("OptimisationStep: the optimiser holds no parameters; assign the "
                             "ones to optimise first (opt['box.translation'] = "
                             "params['box.translation'])")
        if params.scene.camera is None:
            raise SceneError("the scene has no 'camera'; add one to optimise against images")
        if cameras is not None and (isinstance(cameras, (str, int)) or not len(cameras)):
            raise SceneError(f"cameras must be a non-empty list of camera indices or ids, "
                             f"got {cameras!r}")
        #: The rendered views (indices into the scene's cameras; None: the first alone).
        self.cameras = None if cameras is None else [params.scene.camera_index(c) for c in cameras]
        if self.cameras is not None and len(set(self.cameras)) != len(self.cameras):
            raise SceneError(f"cameras names a view twice: {list(cameras)!r}")
        unknown = [key for key in opt.keys() if key not in params]
        if unknown:
            raise SceneError(f"optimiser keys {unknown} are not parameters of the scene")
        self.params, self.opt, self.loss = params, opt, loss
        sppc = spp if sppc is None else sppc
        sppp = spp if sppp is None else sppp
        sppi = spp if sppi is None else sppi
        aovs = tuple(_check_aovs(None)) if integrator == "aov" else None
        self.settings = RenderSettings(integrator, aovs, -1, RR_DEPTH, False, spp, sppc, sppp, sppi)
        self.frozen = frozen and integrator != "path"
        self._recordings = RecordingTable()
        self._frame: tuple = ()

    @property
    def recordings(self) -> int:
        """Recordings made so far (one per key; see the module docstring)."""
        return sum(f.n_recordings for f in self._recordings.functions())

    def __call__(self, seed: int = 0, *inputs: Any) -> Float:
        params, opt = self.params, self.opt
        seed = seed_value(seed)
        # Host arrays become Dr.Jit tensors here: a recording may not upload host data.
        inputs = tuple(TensorXf(np.asarray(x, np.float32)) if isinstance(x, np.ndarray) else x
                       for x in inputs)
        scene = params.scene
        loose = [key for key in params.grad_enabled_keys() if key not in opt.keys()]
        if loose:
            raise SceneError(f"parameters {loose} carry derivatives but are not in the optimiser")
        # Host work: the optimiser's values checked and installed (detached), the
        # moving instances' curves, the lights.
        attachment = params.install(opt)
        views = [scene.view(k) for k in (self.cameras or [0])]
        integrator = self.settings.integrator
        lights = scene.light_set() if integrator != "aov" else None
        for view in views:
            warn_omitted_terms(scene, view, self.settings, stacklevel=2)
        # Views of one camera type, film size and filter trace as one wavefront.
        batches = CameraBatch.group(views, MAX_LANES)
        curves = boundary_samplers(scene, [batch for batch, _ in batches], self.settings)
        # The inputs' shapes too: a loss may derive Python values from them (blur taps).
        key = (tuple(view.key() for view in views), attachment.key(), scene.accel,
               scene.instances.wide_scales, python_state(curves), python_state(lights),
               _shapes(inputs))
        self._frame = (scene, batches, lights, curves, attachment)
        table = scene.instances
        detached = table.rows(), scene.bsdfs.state()
        lr = opt.lr
        rates = {k: entry[2] for k, entry in opt.state.items()}
        try:
            loss, state = self._run(key, seed, inputs)
        finally:
            # The scene keeps the installed (detached) values, whatever the step attached,
            # and the optimiser its own learning rates (the step read copies).
            table.restore_rows(detached[0])
            scene.bsdfs.restore(detached[1])
            opt.lr = lr
        opt.state = {k: (value, promoted, rates.get(k), extra)
                     for k, (value, promoted, _, extra) in state.items()}
        return loss

    def _run(self, key: tuple, seed: UInt32, inputs: tuple) -> tuple[Float, dict]:
        opt = self.opt
        # The optimiser's arrays are arguments: its state and its default learning rate.
        state, lr = opt.state, opt.lr
        if not self.frozen:
            return _step(self, state, lr, seed, *inputs)
        def restore():
            # The recording failed: this key's steps are traced from now on, starting
            # again from the optimiser's state before the attempt.
            opt.state, opt.lr = state, lr
        return call_recorded(self._recordings, key, _step, (self, state, lr, seed, *inputs),
                             _frame_state, on_failure=restore)


def _shapes(inputs: Any) -> Any:
    """The shapes of the Dr.Jit arrays in ``inputs`` (lists and tuples entered)."""
    if isinstance(inputs, (list, tuple)):
        return tuple(_shapes(x) for x in inputs)
    return tuple(inputs.shape) if dr.is_array_v(inputs) else None


def _frame_state(step: OptimisationStep, state: dict, lr: Any, seed: UInt32, *inputs: Any) -> list:
    """The Dr.Jit arrays of the step's current frame, as extra inputs of its recording."""
    return jit_state(*step._frame)


def _step(step: OptimisationStep, state: dict, lr: Any, seed: UInt32,
          *inputs: Any) -> tuple[Float, dict]:
    """The Dr.Jit half of a step: attach, render, loss, backward, optimiser step."""
    scene, batches, lights, curves, attachment = step._frame
    opt = step.opt
    opt.state, opt.lr = state, lr
    step.params.attach(attachment, {key: opt[key] for key in opt.keys()})
    # Each batch its own random numbers: VIEW_SEED_STRIDE apart per view before its first.
    views: list = [None] * sum(len(indices) for _, indices in batches)
    for (batch, indices), batch_curves in zip(batches, curves):
        rendered = images(scene, batch, lights, step.settings,
                          seed + (VIEW_SEED_STRIDE * indices[0] & 0xFFFFFFFF), None, batch_curves)
        for k, image in zip(indices, rendered):
            views[k] = image
    loss = step.loss(views[0] if step.cameras is None else views, *inputs)
    if not isinstance(loss, Float) or dr.width(loss) != 1:
        raise SceneError(f"the loss must return one Float, got {type(loss).__name__} "
                         f"of width {dr.width(loss)}")
    dr.backward(loss)
    _separate_rates(opt)
    opt.step()
    # Material and light parameters projected back onto their valid ranges.
    for key in opt.keys():
        low, high = step.params.bounds(key)
        if math.isfinite(low) or math.isfinite(high):
            opt[key] = dr.clip(opt[key], low, high)
    return dr.detach(loss), opt.state


def _separate_rates(opt: Any) -> None:
    """Give every key of ``opt`` its own reference to its learning rate when the rate is a
    Dr.Jit array: Dr.Jit 1.5's optimisers multiply that array in place by each key's
    debiasing factor, so one rate shared by several keys (the default rate set with
    ``dr.opaque``) would compound from key to key within a step. The keys' own rates are
    put back after the step (:meth:`OptimisationStep.__call__`)."""
    def own(rate: Any) -> Any:
        rate = opt.lr if rate is None else rate
        return type(rate)(rate) if dr.is_array_v(rate) else rate

    # (A new dict: the caller's state, an input of the recording, stays as it was.)
    opt.state = {key: (value, promoted, own(rate), extra)
                 for key, (value, promoted, rate, extra) in opt.state.items()}
