"""Gradient-based recovery of instance transforms and material parameters from a target
image.

Starting from a scene whose instances are misplaced (and whose materials may be off),
Adam (``drjit.opt.Adam``) moves the chosen parameters of :func:`instancing.traverse`
(translation, rotation quaternion, scale; material colours, roughness, texels) so that
the rendered image matches the target in the mean squared error; material parameters
are clipped to their valid ranges after every step. Each iteration renders with fresh random numbers,
with the interior and boundary derivative terms (:mod:`instancing.rendering.boundary_term`).
The interior derivative comes from samples of its own (``sppc``), apart from the image's:
the gradient of ``mean((I - T)^2)`` is ``2 (I - T) dI``, and with I and dI from the same
samples its expectation adds their covariance, a bias that does not average out over the
steps. It pulls the optimum off the target wherever the loss is shallow: a reflectance
recovered at 2 spp ends low by the factor E[X]^2 / E[X^2] of its samples X, and an
ellipsoid whose two closest axes differ by 4.8 % (the benchmark's problem 40, two views,
8 spp) ended 2.2 degrees off with the image's samples and 0.88 - 1.0 degrees with
separate ones, which also cost less (the 8-spp image needs no derivative).
Each iteration is an :class:`~instancing.ad.optimisation.OptimisationStep`: recorded
once and replayed (the learning-rate schedule and the blur are its inputs).

Coarse to fine: with ``blur_start > 0`` both images are blurred by a Gaussian
whose standard deviation shrinks linearly from ``blur_start`` pixels to 0 over
the first ``blur_fraction`` of the iterations. A blurred loss is smooth over
larger displacements, so instances that start far from their target (no
overlap with it) still feel a pull; the late sharp loss fixes the details.
The learning rate stays at ``lr`` unless ``lr_final_ratio`` asks for a geometric decay,
and the parameters returned are the mean of the iterates over the last ``average_fraction``
of the run (Polyak-Ruppert averaging; quaternions sign-aligned to the first of them before
the mean): at a constant-size noisy step the last iterate wanders around the optimum
(on the shadowed target scene at 8 spp, between 0.2 and 0.95 degrees from step to
step after 150 steps), the mean sits near its centre. Averaging wants a step that does
not shrink: with the rate decaying to 30 % over 300 steps, the slow
directions (the turn of a near-symmetric ellipsoid about its near-axis of revolution) were
still drifting towards the target when the averaged quarter began, so the mean lagged
behind it: problem 40 of the benchmark ended 0.9 - 1.4 degrees off, 0.04 - 0.18 at a
constant rate, and the twenty ellipsoid and elliptic-cylinder problems from two views
0.02 - 0.18 degrees off (the bundled recovery scenes' card: 0.89 degrees decaying,
0.10 constant).
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import drjit.opt
import numpy as np

from ..core.arguments import integer, is_real
from ..core.backend import Bool, Float, Int32, TensorXf, UInt32, device_array, dr
from ..core.errors import SceneError, TransformError
from ..core.transform import check_affine_matrix, decompose, quaternion_product
from ..materials.normal_map import NORMAL_MAP
from ..materials.parameter import COLOR
from ..io.image import read_exr, write_exr, write_png
from ..io.scene_file import write_scene_with_transforms
from ..io.output_file import remove_partials, replaced
from ..io.scene_file import load_scene
from ..rendering.film import channel_names, render
from .checkpoint import RecoveryCheckpoint
from .optimisation import OptimisationStep
from .parameters import SceneParameters, traverse

#: Instance parameters recovery may optimise, and their Adam learning rates relative to the
#: base rate (translations in units of the instance's size, rotations as quaternion
#: components). Material parameters take the base rate (colours and roughness live in
#: [0, 1]).
RECOVERABLE = {"translation": 1.0, "rotation": 0.5, "scale": 0.5}
#: The default schedule of :func:`recover`: the base learning rate, the fraction of it the
#: rate decays to (geometrically) by the last step (1: constant), and the last fraction of
#: the run whose iterates are averaged.
LR, LR_FINAL_RATIO, AVERAGE_FRACTION = 0.03, 1.0, 0.25


@dataclass
class RecoveryHistory:
    """What happened during :func:`recover`: per-iteration loss and time, and (when the
    target transforms are known) per-instance errors."""

    loss: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    errors: list[dict[str, tuple[float, float, float]]] = field(default_factory=list)
    #: With restarts: each start's probe losses, and the start the run went on from.
    restarts: list[list[float]] = field(default_factory=list)
    chosen: int = 0


def blur_taps(sigma: float, radius: int | None = None) -> Float:
    """Weights of a separable Gaussian blur of standard deviation ``sigma`` pixels over
    2 radius + 1 taps (default radius: ceil(3 sigma)), normalised; sigma 0: the identity.
    A Dr.Jit array, so that a recorded step reads a changing blur as an input."""
    radius = max(1, int(math.ceil(3 * sigma))) if radius is None else radius
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (offsets / sigma) ** 2) if sigma > 0 else (offsets == 0).astype(np.float64)
    return device_array(Float, (taps / taps.sum()).astype(np.float32))


def blur_sigma(iteration: int, iterations: int, blur_start: float, blur_fraction: float) -> float:
    """The coarse-to-fine blur's standard deviation at ``iteration``: ``blur_start`` pixels,
    shrinking linearly to 0 over the first ``blur_fraction`` of ``iterations``."""
    return blur_start * max(0.0, 1.0 - iteration / max(1.0, blur_fraction * iterations))


def blur(image: TensorXf, taps: Float) -> TensorXf:
    """Separable blur with the weights ``taps`` (:func:`blur_taps`), edges clamped;
    differentiable."""
    h, w, c = image.shape
    radius = (dr.width(taps) - 1) // 2
    flat = image.array
    index = dr.arange(UInt32, h * w * c)
    channel, pixel = index % c, index // c
    x, y = pixel % w, pixel // w
    for axis in ("x", "y"):
        out = dr.zeros(Float, h * w * c)
        for k in range(2 * radius + 1):
            offset = k - radius
            if axis == "x":
                xs = dr.clip(Int32(x) + offset, 0, w - 1)
                src = (y * w + UInt32(xs)) * c + channel
            else:
                ys = dr.clip(Int32(y) + offset, 0, h - 1)
                src = (UInt32(ys) * w + x) * c + channel
            out += dr.gather(Float, taps, UInt32(k)) * dr.gather(Float, flat, src)
        flat = out
    return TensorXf(flat, shape=(h, w, c))


def image_loss(image: TensorXf, target: TensorXf, taps: Float | None = None) -> Float:
    """Mean squared difference of the two images, after a blur with ``taps`` if given."""
    if taps is not None:
        image, target = blur(image, taps), blur(target, taps)
    return dr.mean(dr.square(image.array - target.array))


def views_loss(images: list[TensorXf], targets: list[TensorXf], taps: Float | None = None) -> Float:
    """:func:`image_loss` averaged over the views (each image against its target)."""
    total = image_loss(images[0], targets[0], taps)
    for image, target in zip(images[1:], targets[1:]):
        total += image_loss(image, target, taps)
    return total / len(images)


def _numbers(value: Any, name: str) -> np.ndarray:
    """``value`` as a float64 array, or a SceneError naming the setting."""
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"recover: {name} must hold numbers, got {value!r:.60}") from None


def _check_real(name: str, value: Any, low: float, high: float, low_open: bool = False) -> None:
    """Refuse a recover setting that is not a finite number in [low, high] ((low, high]
    with ``low_open``), naming it."""
    if (not is_real(value) or not math.isfinite(value)
            or value < low or value > high or (low_open and value == low)):
        interval = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise SceneError(f"recover: {name} must be a number in {interval}, got {value!r}")


def _nested_image(target: list | tuple) -> bool:
    """Whether a list is one (H, W, C) image written as nested lists (its first entry a row
    of pixels) rather than a list of images."""
    first = target[0] if len(target) else None
    return isinstance(first, (list, tuple)) and len(first) > 0 and isinstance(first[0], (list, tuple)) \
        and not (len(first[0]) and isinstance(first[0][0], (list, tuple)))


def view_targets(scene, target, integrator: str = "direct") -> tuple[list[int], list[TensorXf]]:
    """The views a recovery renders and their target images: one image for a one-camera
    scene, a list (one per camera, in order) or a dict by camera id or index (those views
    only), each with the channels of the ``integrator``'s render. Errors name the camera
    whose target does not fit."""
    cameras = scene.cameras
    if isinstance(target, dict):
        if not target:
            raise SceneError("recover: the dict of targets is empty")
        pairs = [(scene.camera_index(which), image) for which, image in target.items()]
    elif isinstance(target, (list, tuple)) and not _nested_image(target):
        if len(target) != len(cameras):
            raise SceneError(f"recover: {len(target)} target images for {len(cameras)} cameras "
                             "(give one per camera, in order, or a dict by camera id)")
        pairs = list(enumerate(target))
    else:
        if len(cameras) != 1:
            raise SceneError(f"recover: the scene has {len(cameras)} cameras; give one target "
                             "image per camera (a list in camera order, or a dict by camera id)")
        pairs = [(0, target)]
    views, images = [], []
    for k, image in pairs:
        camera = cameras[k]
        name = f"camera {scene.camera_name(k)!r}"
        if not isinstance(image, TensorXf) and np.iscomplexobj(image):
            raise SceneError(f"recover: the target of {name} holds complex numbers; images are real")
        if not isinstance(image, TensorXf) and np.asarray(image).dtype.kind not in "fiu":
            raise SceneError(f"recover: the target of {name} must be an (H, W, C) image of numbers "
                             f"(read a file with instancing.read_exr), got {type(image).__name__} "
                             f"{image!r:.60}")
        image = image if isinstance(image, TensorXf) else TensorXf(np.asarray(image, np.float32))
        if image.ndim != 3 or tuple(image.shape[:2]) != (camera.height, camera.width):
            raise SceneError(f"recover: the target of {name} is {tuple(image.shape)}; its film is "
                             f"{camera.width}x{camera.height} (an (H, W, C) image)")
        channels = len(channel_names(integrator, scene=scene, camera=k))
        if image.shape[2] != channels:
            raise SceneError(f"recover: the target of {name} has {image.shape[2]} channels; the "
                             f"{integrator!r} render has {channels}")
        bad = dr.count(~dr.isfinite(image.array))[0]
        if bad:
            raise SceneError(f"recover: the target of {name} has {bad} non-finite pixel values "
                             "(NaN or infinity)")
        views.append(k)
        images.append(image)
    if len(set(views)) != len(views):
        raise SceneError("recover: two targets for one camera")
    return views, images


def transform_errors(current: np.ndarray, target: np.ndarray) -> tuple:
    """(translation error / size, rotation error in degrees, largest relative scale error)
    between affine matrices, from their decompositions (:func:`instancing.core.transform.decompose`):
    floats for two 4x4 matrices, arrays (N,) for two (N, 4, 4) stacks.

    The size is the instance's diameter, twice the largest singular value of the
    target's linear part (the canonical models span about [-1, 1]).
    """
    current, target = np.asarray(current, np.float64), np.asarray(target, np.float64)
    t0, q0, s0, _ = decompose(current)
    t1, q1, s1, _ = decompose(target)
    size = 2.0 * np.linalg.svd(target[..., :3, :3], compute_uv=False)[..., 0]
    cosine = np.minimum(1.0, np.abs(np.sum(q0 * q1, axis=-1)))
    errors = (np.linalg.norm(t0 - t1, axis=-1) / size, 2.0 * np.degrees(np.arccos(cosine)),
              np.max(np.abs(s0 - s1) / np.abs(s1), axis=-1))
    return tuple(float(e) for e in errors) if current.ndim == 2 else errors


def default_sppc(spp: int) -> int:
    """:func:`recover`'s samples per pixel of the interior derivative for ``spp``: half of
    them, drawn apart from the image's (at least 1)."""
    return max(1, spp // 2)


def recover(params: SceneParameters, target: TensorXf | np.ndarray | list | dict, keys: list[str], *,
            iterations: int = 300, spp: int = 16, sppc: int | None = None,
            sppp: int | None = None, sppi: int | None = None, lr: float = LR,
            lr_final_ratio: float = LR_FINAL_RATIO, blur_start: float = 0.0, blur_fraction: float = 0.5,
            average_fraction: float = AVERAGE_FRACTION, integrator: str = "direct", seed: int = 0,
            target_to_world: np.ndarray | dict | None = None, restarts: int = 0,
            restart_iterations: int | None = None,
            restart_spread: tuple[float, float, float] = (0.2, 60.0, 0.2),
            progress: Callable[[int, float], None] | None = None,
            checkpoint: Callable[[RecoveryCheckpoint], None] | None = None,
            checkpoint_every: int = 25,
            resume: RecoveryCheckpoint | None = None) -> RecoveryHistory:
    """Optimise ``keys`` of ``params`` so that the renders match the targets.

    Args:
        params: the parameters of the scene to adjust (:func:`instancing.traverse`).
        target: (H, W, C) target image at the camera's resolution; with several cameras
            one per camera (a list in camera order) or a dict from camera id (or index)
            to image, whose views alone are rendered. The loss is the mean over the
            views of their mean squared errors.
        keys: parameters to optimise, e.g. ``["box.translation", "box.rotation",
            "paint.reflectance"]``: instances' translation, rotation and scale, and any
            material parameter of ``params``.
        iterations: Adam steps.
        spp, sppp, sppi: samples per pixel of each iteration's image, silhouette term and
            shadow term (see :func:`instancing.render`).
        sppc: samples per pixel of the interior derivative, drawn apart from the image's
            (default ``spp // 2``, at least 1; ``sppc == spp`` reuses the image's samples).
            The squared error's gradient is then unbiased; from the image's own samples it
            carries their covariance with the derivative (see the module docstring).
        lr: base learning rate; translations move by about ``lr`` times the
            instance's size per step, rotations and scales by half that.
        lr_final_ratio: the learning rate decays geometrically to this fraction of ``lr``
            by the last step (default 1: constant; see the module docstring).
        blur_start, blur_fraction: coarse-to-fine schedule (see the module docstring).
        average_fraction: the returned parameters are the mean of the iterates over this
            last fraction of the run (0: the last iterate).
        integrator: 'direct' or 'aov' (the path tracer works too, slowly).
        seed: first iteration's seed (each iteration uses the next one).
        target_to_world: the target matrices, when known (errors are recorded): (N, 4, 4)
            for every instance in order, or a dict from instance id to its 4x4 matrix.
        restarts: random restarts for far-off starts: besides the given start, this many
            random ones (every optimised instance moved by up to ``restart_spread[0]``
            times its size, turned by up to ``restart_spread[1]`` degrees about a random
            axis, scaled by up to a factor 1 +- ``restart_spread[2]``); each descends
            ``restart_iterations`` steps (default a fifth of ``iterations``), and the run
            goes on for ``iterations`` from the end of the one whose loss over its last
            quarter is lowest. Material parameters start each probe as given.
        progress: called with (iteration, loss) after each step.
        checkpoint: called with a :class:`~instancing.ad.checkpoint.RecoveryCheckpoint`
            every ``checkpoint_every`` iterations of the descent (after the restarts' probes),
            e.g. to save it.
        resume: a checkpoint of a run with the same arguments: the descent goes on from it
            (no probes again) and ends where the uninterrupted run ends.

    Raises:
        SceneError: no key, an unknown key or a parameter recovery cannot optimise;
            ``iterations`` below 1, ``lr`` not a positive number; targets that do not match
            the cameras or have non-finite pixels; target matrices that do not match the
            instances.

    Warns when a view sees none of the optimised instances (it can only add noise).
    """
    if not isinstance(params, SceneParameters):
        raise SceneError(f"recover: params must be instancing.traverse(scene), got {type(params).__name__}")
    scene = params.scene
    iterations = integer("iterations", iterations, 1, where="recover")
    if not is_real(lr) or not 0.0 < lr < math.inf:
        raise SceneError(f"recover: lr (the learning rate) must be a positive finite number, "
                         f"got {lr!r}")
    _check_real("lr_final_ratio", lr_final_ratio, 0.0, 1.0, low_open=True)
    _check_real("average_fraction", average_fraction, 0.0, 1.0)
    _check_real("blur_fraction", blur_fraction, 0.0, 1.0)
    # A blur wider than the largest film blurs nothing more, and its taps grow with it.
    _check_real("blur_start", blur_start, 0.0,
                float(max((max(c.width, c.height) for c in scene.cameras), default=0)))
    spp = integer("spp", spp, 1, where="recover")
    seed = integer("seed", seed, 0, 2 ** 32 - 1, where="recover")
    if isinstance(keys, str):
        raise SceneError(f"recover: keys must be a list of parameter names, got the string {keys!r}")
    for name, function in (("progress", progress), ("checkpoint", checkpoint)):
        if function is not None and not callable(function):
            raise SceneError(f"recover: {name} must be a function or None, got {function!r}")
    if not keys:
        raise SceneError("recover: keys is empty; name the parameters to optimise (e.g. "
                         "'box.translation'; instancing.traverse lists them)")
    for key in keys:
        kind = params.kind(key) if key in params else None
        if kind not in ("instance", "group", "material") or (
                kind != "material" and key.rsplit(".", 1)[1] not in RECOVERABLE):
            raise SceneError(f"recover: cannot optimise {key!r}; expected '<instance or group>.' "
                             f"followed by one of {list(RECOVERABLE)}, or a material parameter "
                             "(instancing.traverse lists them)")
    if len(set(keys)) != len(keys):
        raise SceneError("recover: a key is given twice")
    unused = _unused_material_keys(params, keys)
    if unused:
        raise SceneError(f"recover: no instance uses the material of {unused}; the images do not "
                         "depend on it")
    restarts = integer("restarts", restarts, 0, where="recover")
    probe = integer("restart_iterations", max(1, iterations // 5) if restart_iterations is None
                    else restart_iterations, 1, where="recover")
    spread = _numbers(restart_spread, "restart_spread")
    if spread.shape != (3,) or not np.isfinite(spread).all() or (spread < 0).any() \
            or spread[2] >= 1:
        raise SceneError(f"recover: restart_spread must be (shift >= 0, degrees >= 0, "
                         f"0 <= scale < 1), got {restart_spread!r}")
    checkpoint_every = integer("checkpoint_every", checkpoint_every, 1, where="recover")
    if resume is not None and not isinstance(resume, RecoveryCheckpoint):
        raise SceneError(f"recover: resume must be a RecoveryCheckpoint (as the checkpoint "
                         f"function receives it), got {type(resume).__name__}")
    if resume is not None and not 0 < resume.iteration < iterations:
        raise SceneError(f"recover: the checkpoint is at iteration {resume.iteration}; it "
                         f"cannot resume a run of {iterations}")
    views, targets = view_targets(scene, target, integrator)
    truth = _target_matrices(scene, target_to_world)
    batch = _Batch(params, keys)
    if sppc is None:
        sppc = default_sppc(spp)
    settings = dict(spp=spp, sppc=sppc, sppp=sppp, sppi=sppi, lr=lr, lr_final_ratio=lr_final_ratio,
                    blur_start=blur_start, blur_fraction=blur_fraction, integrator=integrator)
    try:
        _warn_unseen(scene, views, batch.moved)
        if resume is not None:
            probes, chosen = resume.history["restarts"], resume.history["chosen"]
        else:
            probes, chosen = _best_start(params, batch, views, targets, restarts, probe, spread,
                                         seed, settings) if restarts else ([], 0)

        def saving(state: RecoveryCheckpoint) -> None:
            state.history.update(restarts=probes, chosen=chosen)
            checkpoint(state)

        history = _descend(params, batch, views, targets, truth, iterations=iterations,
                           average_fraction=average_fraction, seed=seed, progress=progress,
                           checkpoint=None if checkpoint is None else saving,
                           checkpoint_every=checkpoint_every, resume=resume, **settings)
        history.restarts, history.chosen = probes, chosen
        return history
    finally:
        batch.release()


def _best_start(params: SceneParameters, batch: "_Batch", views: list[int], targets: list,
                restarts: int, iterations: int, spread: np.ndarray, seed: int,
                settings: dict) -> tuple[list[list[float]], int]:
    """Random restarts (see :func:`recover`): leaves ``params`` at the end of the best
    probe; returns every probe's losses and the index of the best."""
    rng = np.random.default_rng([seed, 0x5EED])
    origin = {key: type(params[key])(dr.detach(params[key])) for key in batch.keys}
    probes, best = [], None
    for r in range(restarts + 1):
        for key, value in origin.items():
            params[key] = batch.perturbed(key, value, spread, rng) if r else value
        history = _descend(params, batch, views, targets, {}, iterations=iterations,
                           average_fraction=0.0, seed=seed + 100_003 * (r + 1), progress=None,
                           checkpoint=None, checkpoint_every=1, resume=None, **settings)
        probes.append(history.loss)
        score = float(np.mean(history.loss[-max(1, len(history.loss) // 4):]))
        if best is None or score < best[0]:
            best = (score, r, {key: type(params[key])(dr.detach(params[key])) for key in batch.keys})
    for key, value in best[2].items():
        params[key] = value
    return probes, best[1]


#: The group :func:`recover` optimises the instances named one by one through.
BATCH_GROUP = "recover~instances"


class _Batch:
    """The optimised keys as few arrays: instances named one by one (``"box.translation"``)
    become one group (:meth:`SceneParameters.group`) optimised through one key per part,
    each lane's learning rate scaled by its instance's size, 0 for parts not asked for."""

    def __init__(self, params: SceneParameters, keys: list[str]):
        self.params = params
        single = [key for key in keys if params.kind(key) == "instance"]
        ids = list(dict.fromkeys(key.rsplit(".", 1)[0] for key in single))
        self.group = BATCH_GROUP if ids else None
        if ids:
            # (The keys' own values give up their derivatives: the group optimises them.)
            for key in single:
                dr.disable_grad(params[key])
            params.group(BATCH_GROUP, ids)
        parts = list(dict.fromkeys(key.rsplit(".", 1)[1] for key in single))
        lane = {name: k for k, name in enumerate(ids)}
        #: The optimiser's keys, and per key: its lanes' relative learning rates (1, or 0 for
        #: a part an instance keeps) and instances.
        self.keys = [key for key in keys if params.kind(key) != "instance"]
        self.mask: dict[str, np.ndarray] = {}
        for part in parts:
            on = np.zeros(len(ids))
            on[[lane[key.rsplit(".", 1)[0]] for key in single if key.endswith("." + part)]] = 1.0
            self.keys.append(f"{BATCH_GROUP}.{part}")
            self.mask[self.keys[-1]] = on
        self.instances = {key: params.instances_of(key) for key in self.keys
                          if params.kind(key) == "group"}
        #: Every optimised instance (sorted) and its size (the largest side of its world box).
        self.moved = sorted({i for members in self.instances.values() for i in members})
        self.sizes = {}
        if self.moved:
            lo, hi = params.scene.instance_bounds(self.moved)
            self.sizes = dict(zip(self.moved, np.max(hi - lo, axis=1).tolist()))

    def perturbed(self, key: str, value, spread: np.ndarray, rng: np.random.Generator):
        """A random restart's value of ``key`` (:func:`recover`); lanes of parts an instance
        keeps, and material parameters, unchanged."""
        if key not in self.instances:
            return value
        part = key.rsplit(".", 1)[1]
        rows = np.array(value, np.float64).reshape(-1, dr.width(value)).T
        n = len(rows)
        if part == "translation":
            direction = rng.normal(size=(n, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            sizes = np.array([self.sizes[i] for i in self.instances[key]])
            new = rows + direction * (spread[0] * sizes * rng.uniform(0, 1, n))[:, None]
        elif part == "rotation":
            axis = rng.normal(size=(n, 3))
            axis /= np.linalg.norm(axis, axis=1, keepdims=True)
            half = np.radians(spread[1] * rng.uniform(0, 1, n)) / 2
            turn = np.column_stack([axis * np.sin(half)[:, None], np.cos(half)])
            new = np.column_stack(quaternion_product(turn.T, rows.T))
        else:
            new = rows * (1 + spread[2] * rng.uniform(-1, 1, (n, 3)))
        keep = self.mask.get(key, np.ones(n)) == 0
        new[keep] = rows[keep]
        component = dr.value_t(type(value))
        return type(value)(*[component(np.ascontiguousarray(c)) for c in new.T])

    def rates(self, lr: float) -> dict:
        """Per key its base learning rate: a float, or per lane (NumPy) for groups
        (translations in units of each instance's size)."""
        rates = {}
        for key in self.keys:
            part = key.rsplit(".", 1)[1]
            base = lr * RECOVERABLE.get(part, 1.0)
            if key in self.instances:
                scale_ = np.array([self.sizes[i] for i in self.instances[key]]) \
                    if part == "translation" else np.ones(len(self.instances[key]))
                base = base * scale_ * self.mask.get(key, 1.0)
            rates[key] = base
        return rates

    def keep_fixed(self, opt, start: dict) -> None:
        """Restore the lanes of parts an instance keeps (the iterate average may round them)."""
        for key, on in self.mask.items():
            if not on.all():
                opt[key] = dr.select(device_array(Bool, on > 0), opt[key], start[key])

    def release(self) -> None:
        """Grads off, values pushed, and the batch's group removed (with what it holds
        when pushing failed)."""
        for key in self.keys:
            dr.disable_grad(self.params[key])
        try:
            self.params.update()
        finally:
            if self.group is not None:
                self.params.ungroup(self.group, discard=True)


def _descend(params: SceneParameters, batch: _Batch, views: list[int], targets: list,
             truth: dict, *, iterations: int, spp: int, sppc: int, sppp: int | None,
             sppi: int | None,
             lr: float, lr_final_ratio: float, blur_start: float, blur_fraction: float,
             average_fraction: float, integrator: str, seed: int,
             progress: Callable[[int, float], None] | None,
             checkpoint: Callable[[RecoveryCheckpoint], None] | None, checkpoint_every: int,
             resume: RecoveryCheckpoint | None) -> RecoveryHistory:
    """The descent of :func:`recover` on the batched keys (from ``resume`` when given;
    ``checkpoint`` called every ``checkpoint_every`` iterations)."""
    scene = params.scene
    opt = drjit.opt.Adam(lr=lr)
    for key in batch.keys:
        opt[key] = params[key]
    start = {key: type(opt[key])(opt[key]) for key in batch.mask}
    # Learning rates as opaque values: the recorded step reads each step's decayed rate.
    base_rates = batch.rates(lr)
    # One blur width for the whole run (the taps narrow to the identity), one recording.
    radius = int(math.ceil(3 * blur_start)) if blur_start > 0 else 0
    step = OptimisationStep(params, opt, views_loss, integrator=integrator, spp=spp, sppc=sppc,
                            sppp=sppp, sppi=sppi, cameras=views)
    history = RecoveryHistory()
    tracked = np.array(sorted(set(batch.moved) & set(truth)), np.int64)
    truth_stack = np.array([truth[i] for i in tracked.tolist()]).reshape(-1, 4, 4)
    averaged = max(1, round(average_fraction * iterations)) if average_fraction > 0 else 0
    sums: dict = {}
    first = 0
    if resume is not None:
        resume.restore(opt, start, sums)
        history = RecoveryHistory(**dict(resume.history, errors=[
            {name: tuple(e) for name, e in entry.items()} for entry in resume.history["errors"]]))
        first = resume.iteration
    for it in range(first, iterations):
        begin = time.perf_counter()
        decay = lr_final_ratio ** (it / max(1, iterations - 1))
        opt.set_learning_rate({key: _rate(rate * decay) for key, rate in base_rates.items()})
        # Coarse to fine: the blur shrinks to 0 over the first blur_fraction of the run.
        sigma = blur_sigma(it, iterations, blur_start, blur_fraction)
        loss = step(seed + it, targets, blur_taps(sigma, radius))
        history.loss.append(float(loss[0]))
        history.seconds.append(time.perf_counter() - begin)
        if it >= iterations - averaged:
            _accumulate(sums, opt, batch.keys)
        if len(tracked):
            history.errors.append(_errors(scene, tracked, truth_stack))
        if progress is not None:
            progress(it, history.loss[-1])
        if checkpoint is not None and (it + 1) % checkpoint_every == 0 and it + 1 < iterations:
            checkpoint(RecoveryCheckpoint.capture(it + 1, opt, start, sums,
                                                  dataclasses.asdict(history)))
    for key, total in sums.items():
        opt[key] = type(total)(total / averaged)
    batch.keep_fixed(opt, start)
    params.update(opt)
    if len(tracked):
        history.errors.append(_errors(scene, tracked, truth_stack))
    return history


def _rate(rate) -> Float:
    """A learning rate (a number, or NumPy per lane) as an opaque Dr.Jit value."""
    if isinstance(rate, np.ndarray):
        return device_array(Float, rate.astype(np.float32))
    return dr.opaque(Float, rate)


def _target_matrices(scene, target_to_world: np.ndarray | dict | None) -> dict[int, np.ndarray]:
    """``target_to_world`` as instance index -> 4x4 float64 matrix (empty: unknown)."""
    if target_to_world is None:
        return {}
    ids = scene.instance_ids
    if isinstance(target_to_world, dict):
        unknown = [name for name in target_to_world if name not in ids]
        if unknown:
            raise SceneError(f"recover: target_to_world names instances {unknown[:5]} that "
                             f"the scene does not have")
        pairs = [(ids.index(name), matrix) for name, matrix in target_to_world.items()]
    else:
        matrices = _numbers(target_to_world, "target_to_world")
        if matrices.shape != (len(ids), 4, 4):
            raise SceneError(f"recover: target_to_world holds {matrices.shape} matrices; the "
                             f"scene has {len(ids)} instances: give ({len(ids)}, 4, 4), or a "
                             "dict from instance id to matrix")
        pairs = list(enumerate(matrices))
    truth = {}
    for i, matrix in pairs:
        matrix = _numbers(matrix, f"target_to_world of instance {ids[i]!r}")
        if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            got = f"shape {matrix.shape}" if matrix.shape != (4, 4) else "non-finite entries"
            raise SceneError(f"recover: target_to_world of instance {ids[i]!r} must be a "
                             f"finite 4x4 matrix, got {got}")
        try:
            check_affine_matrix(matrix, f"recover: target_to_world of instance {ids[i]!r}")
        except TransformError as err:
            raise SceneError(str(err)) from None
        truth[i] = matrix
    return truth


#: Film width at which recovery looks for the optimised instances in each view.
_SEEN_WIDTH = 64


def _unused_material_keys(params: SceneParameters, keys: list[str]) -> list[str]:
    """The material parameters among ``keys`` whose material no instance uses."""
    scene = params.scene
    worn = {scene.material_names[k] for k in np.unique(scene.description.instance_material_index)}
    return [key for key in keys if params.kind(key) == "material"
            and params.material_parameter(key)[0] not in worn]


def _warn_unseen(scene, views: list[int], instances: list[int]) -> None:
    """Warn about views in which none of ``instances`` is hit by a ray through the centre
    of a pixel of a reduced film (at most _SEEN_WIDTH wide)."""
    if not instances:
        return
    wanted = np.asarray(instances)
    for k in views:
        camera = scene.cameras[k]
        width = min(camera.width, _SEEN_WIDTH)
        small = camera.with_size(width, max(1, round(camera.height * width / camera.width)))
        o, d = small.pixel_centre_rays()
        seen = np.unique(scene.intersect(np.array(o).T, np.array(d).T).instance)
        if not np.isin(wanted, seen).any():
            warnings.warn(f"recover: camera {scene.camera_name(k)!r} sees none of the optimised "
                          "instances; its image only adds noise to the loss", stacklevel=3)


def _accumulate(sums: dict, opt, keys: list[str]) -> None:
    """Add the optimiser's current values to the running sums of the iterate average
    (a quaternion flipped to the hemisphere of the first one summed: q and -q are one
    rotation)."""
    for key in keys:
        value = opt[key]
        if key in sums and key.endswith(".rotation"):
            value = dr.select(dr.dot(value, sums[key]) < 0, -value, value)
        sums[key] = sums[key] + value if key in sums else type(value)(value)
        dr.eval(sums[key])


def _errors(scene, instances: np.ndarray, target_to_world: np.ndarray) -> dict:
    """Per instance id its :func:`transform_errors` against its row of ``target_to_world``."""
    columns = transform_errors(scene.to_world_of(instances), target_to_world)
    ids = scene.instance_ids
    return {ids[i]: row for i, row in zip(instances.tolist(), zip(*(c.tolist() for c in columns)))}


def write_convergence_plot(history: RecoveryHistory, path: str) -> None:
    """Loss (and, when known, per-instance errors) against iteration, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 1 + (3 if history.errors else 0)
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 3.4), squeeze=False)
    axes = axes[0]
    axes[0].semilogy(history.loss)
    axes[0].set(title="image loss (MSE)", xlabel="iteration")
    if history.errors:
        titles = ("translation error / object size", "rotation error (deg)", "scale error (relative)")
        targets = (0.01, 1.0, 0.01)
        for k in range(3):
            ax = axes[k + 1]
            for name in history.errors[0]:
                ax.semilogy([e[name][k] for e in history.errors], label=name)
            ax.axhline(targets[k], color="k", linestyle=":", linewidth=1, label="target")
            ax.set(title=titles[k], xlabel="iteration")
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    with replaced(path) as partial:
        fig.savefig(partial, dpi=110)
    plt.close(fig)


@dataclass
class RecoveryRun:
    """Result of :func:`recover_files`: the history, what was written where, and per
    recovered material parameter its values (before, after, target where known; texels
    by their mean)."""

    history: RecoveryHistory
    keys: list[str]
    written: list[str]
    materials: dict[str, tuple] = field(default_factory=dict)

    def table(self) -> str:
        """Per-instance errors before and after, iterations and time per iteration."""
        h = self.history
        lines = [f"{len(h.loss)} iterations, {np.median(h.seconds):.2f} s per iteration (median), "
                 f"loss {h.loss[0]:.3e} -> {h.loss[-1]:.3e}"]
        if h.errors:
            lines.append(f"{'instance':<12} {'translation/size':>17} {'rotation deg':>13} {'scale':>9}")
            for name in h.errors[0]:
                (t0, r0, s0), (t1, r1, s1) = h.errors[0][name], h.errors[-1][name]
                lines.append(f"{name:<12} {t0:>7.4f} -> {t1:<7.4f} {r0:>5.2f} -> {r1:<5.2f} "
                             f"{s0:>.3f} -> {s1:.3f}")
        if self.materials:
            lines.append(f"{'material parameter':<30} {'start':>22} {'recovered':>22} {'target':>22}")
            for key, values in self.materials.items():
                cells = ["-" if v is None else " ".join(f"{x:.3f}" for x in np.ravel(v))
                         for v in values]
                lines.append(f"{key:<30} " + " ".join(f"{c:>22}" for c in cells))
        return "\n".join(lines)


#: Samples per pixel of target images rendered from a target scene: their noise moves the
#: optimum where the loss is shallow (an ellipsoid whose closest axes are 4.8 % apart, from
#: 2 views: 1.37 degrees left with 256-spp targets, 0.94 with 1 024, 1.00 with 4 096).
REFERENCE_SPP = 1024


def recover_files(target: str | list[str], init: str, out_dir: str, *, iterations: int = 300,
                  spp: int = 16, sppc: int | None = None, sppp: int | None = None,
                  sppi: int | None = None, lr: float = LR, lr_final_ratio: float = LR_FINAL_RATIO,
                  blur_start: float = 0.0, instances: list[str] | None = None,
                  parameters: tuple[str, ...] = ("translation", "rotation", "scale"),
                  materials: list[str] | None = None,
                  reference_spp: int = REFERENCE_SPP, seed: int = 0, restarts: int = 0,
                  progress: Callable[[int, float], None] | None = None,
                  checkpoint_every: int = 25, resume: bool = False) -> RecoveryRun:
    """The ``instancing recover`` command: recover transforms (and material parameters) of
    ``init`` from ``target``, seen through every camera of the scene.

    Args:
        target: the target scene (.json / .xml; rendered through each of its cameras at
            ``reference_spp``, as are the PNGs; the same cameras as ``init``), or target
            images (.exr, one per camera of ``init`` in order, each at its camera's
            resolution).
        init: the scene with perturbed transforms to start from.
        out_dir: folder for target.png, before.png, after.png (with several cameras
            one per camera: ``target_<camera id or index>.png``, ...), convergence.png,
            recovered.json (the init scene with the recovered transforms) and
            history.json (loss, seconds and errors per iteration).
        instances: ids to optimise; default: those whose transforms differ between
            the target and init scenes (with target images: none).
        parameters: which of translation, rotation, scale to optimise.
        materials: material parameters to optimise (``"paint.reflectance"``, keys of
            :func:`instancing.traverse`); default: those whose values differ between the
            target and init scenes (with target images: none). Recovered values are
            written into recovered.json (texels as ``<key>.exr`` beside it).
        checkpoint_every: every this many iterations the run's state is saved to
            ``checkpoint.npz`` and the history so far to history.json (0: never); the
            arguments are in run.json from the start. A finished run removes the checkpoint.
        resume: continue the run in ``out_dir`` from its checkpoint (see
            :func:`resume_files`); the other arguments must be the run's own.
        Other arguments as :func:`recover`.
    """
    out = Path(out_dir)
    # (The counts and names this function computes with; recover checks the others.)
    for name, names in (("instances", instances), ("parameters", parameters), ("materials", materials)):
        if isinstance(names, str) or not (names is None or isinstance(names, (list, tuple))):
            raise SceneError(f"recover: {name} must be a list of names, got {names!r}")
    bad = [p for p in parameters if p not in RECOVERABLE]
    if bad or not parameters:
        raise SceneError(f"recover: parameters must be some of {list(RECOVERABLE)}, got {list(parameters)}")
    seed = integer("seed", seed, 0, 2 ** 32 - 1, where="recover")
    reference_spp = integer("reference_spp", reference_spp, 1, where="recover")
    checkpoint_every = integer("checkpoint_every", checkpoint_every, 0, where="recover")
    arguments = {"target": [os.path.abspath(t) for t in ([target] if isinstance(target, (str, os.PathLike))
                                                         else target)],
                 "init": os.path.abspath(init), "iterations": iterations, "spp": spp,
                 "sppc": sppc, "sppp": sppp, "sppi": sppi, "lr": lr, "lr_final_ratio": lr_final_ratio,
                 "blur_start": blur_start, "instances": instances, "parameters": list(parameters),
                 "materials": materials, "reference_spp": reference_spp, "seed": seed,
                 "restarts": restarts, "checkpoint_every": checkpoint_every}
    # The output folder, before any work: it may exist as a folder only, and not lie in a file.
    blocking = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise SceneError(f"recover: the output folder {str(out)!r} cannot be made: "
                         f"{str(blocking)!r} exists and is not a folder")
    state = None
    if resume:
        state = RecoveryCheckpoint.load(out / CHECKPOINT)
        remove_partials(out)
    scene = load_scene(init)
    target_to_world = None
    params = traverse(scene)
    target_params = None
    names = [str(t) for t in ([target] if isinstance(target, (str, os.PathLike)) else target)]
    if not scene.cameras:
        raise SceneError("recover: the init scene has no 'camera'")
    if names and all(name.lower().endswith(".exr") for name in names):
        if not instances and not materials:
            raise SceneError("recover: with target images, name the instances or material "
                             "parameters to optimise")
        instances, materials = instances or [], materials or []
        target_images = [np.asarray(read_exr(name)[0], np.float32)[..., :3] for name in names]
    elif len(names) == 1:
        target_scene = load_scene(names[0])
        if target_scene.instance_ids != scene.instance_ids:
            raise SceneError("recover: the target and init scenes must list the same instance ids")
        if [c.key() for c in target_scene.cameras] != [c.key() for c in scene.cameras]:
            raise SceneError("recover: the target and init scenes must have the same cameras "
                             "(the target is rendered through them)")
        target_to_world = target_scene.to_world
        target_images = [np.array(render(target_scene, "direct", spp=reference_spp,
                                         seed=seed + 10**6, camera=k))
                         for k in range(len(scene.cameras))]
        target_params = traverse(target_scene)
        if instances is None:
            moved = np.abs(target_to_world - scene.to_world).max(axis=(1, 2)) > 0
            instances = [scene.instance_ids[i] for i in np.flatnonzero(moved)]
        if materials is None:
            # Those that differ and that some instance wears (others change no image).
            candidates = [key for key in params if params.kind(key) == "material"]
            unused = set(_unused_material_keys(params, candidates))
            materials = [key for key in candidates if key not in unused
                         and _material_value(params, key).shape
                         == _material_value(target_params, key, key).shape
                         and not np.array_equal(_material_value(params, key),
                                                _material_value(target_params, key, key))]
    else:
        raise SceneError(f"recover: expected one target scene or target images (.exr), got "
                         f"{names}")
    unknown = [i for i in instances if i not in scene.instance_ids]
    if unknown or not (instances or materials):
        raise SceneError(f"recover: unknown or no instances to optimise: {unknown or instances} "
                         f"(and no material parameters)")
    bad_materials = [key for key in materials if key not in params or params.kind(key) != "material"]
    if bad_materials:
        known = [key for key in params if params.kind(key) == "material"]
        raise SceneError(f"recover: {bad_materials} are not material parameters of the init "
                         f"scene; it has {known}")
    views, _ = view_targets(scene, target_images)
    # (Created once the inputs are known good: a run refused for its input leaves no folder.)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SceneError(f"recover: cannot make the output folder {str(out)!r}: "
                         f"{err.strerror or err}") from None
    if not resume:
        _write_json(out / RUN, arguments)
    pictures = []
    for k, image in zip(views, target_images):
        suffix = "" if len(views) == 1 else f"_{scene.camera_name(k)}"
        pictures.append([out / f"{stage}{suffix}.png" for stage in ("target", "before", "after")])
        write_png(pictures[-1][0], image)
        write_png(pictures[-1][1], render(scene, "direct", spp=reference_spp, seed=seed, camera=k))
    keys = [f"{i}.{p}" for i in instances for p in parameters] + list(materials)
    before = {key: _material_value(params, key) for key in materials}

    def save(checkpoint: RecoveryCheckpoint) -> None:
        checkpoint.save(out / CHECKPOINT)
        _write_json(out / "history.json", {"keys": keys, **checkpoint.history})

    history = recover(params, target_images, keys, iterations=iterations, spp=spp, sppc=sppc,
                      sppp=sppp, sppi=sppi, lr=lr,
                      lr_final_ratio=lr_final_ratio, blur_start=blur_start, seed=seed,
                      target_to_world=target_to_world, restarts=restarts, progress=progress,
                      checkpoint=save if checkpoint_every else None,
                      checkpoint_every=max(1, checkpoint_every), resume=state)
    for k, files in zip(views, pictures):
        write_png(files[2], render(scene, "direct", spp=reference_spp, seed=seed, camera=k))
    write_convergence_plot(history, str(out / "convergence.png"))
    recovered, written_textures = {}, []
    for key in materials:
        i, name, part, checker = params.material_parameter(key)
        # A blend's or mask's BSDF: its entries nested under its key in the scene file.
        entries, owner = recovered.setdefault(i, {}), scene.materials[i]
        if part is not None:
            entries, owner = entries.setdefault(owner.part_names[part], {}), owner.parts[part]
        if key.endswith(".data"):
            texels = out / f"{key}.exr"
            write_exr(texels, np.array(params[key]))
            entries[name] = texels.name
            written_textures.append(str(texels))
        elif checker is not None and name == NORMAL_MAP:  # a normal map's checkerboard colour
            entries.setdefault(name, {})[checker] = np.array(params[key], np.float64).ravel().tolist()
        elif checker is not None:  # a checkerboard's colour, in its texture's dict (grey: a number)
            color = getattr(owner.values[name], checker)
            entries.setdefault(name, {})[checker] = (list(color) if owner.lobe.parameters[name].kind == COLOR
                                                   else color[0])
        else:
            entries.update(owner.file_entries({name}))
    write_scene_with_transforms(init, scene.to_world, out / "recovered.json", materials=recovered)
    _write_json(out / "history.json", {"keys": keys, **dataclasses.asdict(history)})
    (out / CHECKPOINT).unlink(missing_ok=True)
    written = ([str(f) for files in pictures for f in files]
               + [str(out / n) for n in ("convergence.png", "recovered.json", "history.json", RUN)]
               + written_textures)
    table = {key: (_summary(before[key]), _summary(_material_value(params, key)),
                   None if target_params is None else _summary(_material_value(target_params, key, key)))
             for key in materials}
    return RecoveryRun(history, keys, written, table)


#: The files in a recovery's output folder that hold its arguments and its last checkpoint.
RUN, CHECKPOINT = "run.json", "checkpoint.npz"


def resume_files(out_dir: str, progress: Callable[[int, float], None] | None = None) -> RecoveryRun:
    """Continue the ``instancing recover`` run whose output folder is ``out_dir`` from its
    last checkpoint, with the arguments in its run.json: it ends where the uninterrupted run
    would have ended (same seeds)."""
    out = Path(out_dir)
    try:
        arguments = json.loads((out / RUN).read_text())
    except FileNotFoundError:
        raise SceneError(f"recover --resume: {out} holds no {RUN}: not the output folder of a "
                         "recovery") from None
    except (OSError, ValueError) as err:
        raise SceneError(f"recover --resume: cannot read {out / RUN}: {err}") from None
    if not (out / CHECKPOINT).is_file():
        raise SceneError(f"recover --resume: {out} holds no {CHECKPOINT}: the run finished, or "
                         "stopped before its first checkpoint (run it again)")
    return recover_files(arguments.pop("target"), arguments.pop("init"), str(out), resume=True,
                         progress=progress, **arguments)


def _write_json(path: Path, content: dict) -> None:
    """``content`` as JSON at ``path``, written whole or not at all."""
    with replaced(path) as partial:
        # (NumPy scalars among the arguments are written as the numbers they hold.)
        Path(partial).write_text(json.dumps(content, default=_plain_number))


def _plain_number(value: Any) -> Any:
    """A NumPy scalar as the Python number it holds (json's fallback for other types)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _material_value(params: SceneParameters, key: str, needed: str | None = None) -> np.ndarray:
    """A material parameter's value as float64 NumPy (texels (H, W, 3)); with ``needed``,
    an error naming it where ``params`` lacks it (the target scene's materials)."""
    if key not in params:
        raise SceneError(f"recover: the target scene has no material parameter {needed!r}")
    value = np.array(params[key], np.float64)
    return value if key.endswith(".data") else value.reshape(-1)


def _summary(value: np.ndarray) -> np.ndarray:
    """A parameter's value for the report: texels by their mean per channel."""
    return value.reshape(-1, 3).mean(axis=0) if value.ndim == 3 else value
