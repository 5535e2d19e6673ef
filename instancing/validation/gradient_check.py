"""Checking image gradients against central finite differences.

Used by the test suite (small images) and by ``benchmarks/gradients.py``
(full size). A gradient image is the derivative of every pixel with respect
to one parameter moved along one tangent direction; the reference is the
central difference of two detached renders at ``value +- step * tangent``
with the same random numbers (so most Monte Carlo noise cancels).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from ..ad.parameters import SceneParameters, traverse
from ..core.backend import Matrix4f, Matrix4f64, TensorXf, dr
from ..io.image import write_exr
from ..io.scene_file import load_scene
from ..rendering.film import render

#: The package's validation meshes (written by scenes/meshes/generate.py).
DATA = Path(__file__).resolve().parent / "data"


def _numbers(value: Any) -> np.ndarray:
    return np.array(dr.detach(value), np.float64).reshape(-1)


def _as_value(like: Any, numbers: np.ndarray) -> Any:
    """Flat numbers as a Dr.Jit value of the type (and, for a tensor, the shape) of
    parameter value ``like``: width 1, matrices row-major."""
    numbers = np.asarray(numbers, np.float64)
    if isinstance(like, (Matrix4f, Matrix4f64)):
        return type(like)(numbers.reshape(4, 4).tolist())
    if isinstance(like, TensorXf):
        return TensorXf(numbers.reshape(like.shape).astype(np.float32))
    return type(like)(*numbers.ravel().tolist())


def _with_offset(params: SceneParameters, key: str, value: np.ndarray) -> None:
    params[key] = _as_value(params[key], value)


def gradient_image(params: SceneParameters, key: str, tangent, **render_args) -> np.ndarray:
    """Forward-mode derivative (H, W, C) of ``render(params.scene, ...)`` along ``tangent``.

    Args:
        params: the scene's parameters (:func:`instancing.traverse`).
        key: the parameter, e.g. ``"ball.translation"``.
        tangent: the direction in the parameter's own coordinates (same length; a
            4x4 array for ``to_world``).
        render_args: passed to :func:`instancing.render` (spp, sppc, sppp, ...).
    """
    value = params[key]
    base = _numbers(value)
    _with_offset(params, key, base)
    value = params[key]
    dr.enable_grad(value)
    params.update()
    image = render(params.scene, **render_args)
    dr.set_grad(value, _as_value(value, tangent))
    dr.enqueue(dr.ADMode.Forward, value)
    dr.traverse(dr.ADMode.Forward)
    grad = np.array(dr.grad(image))
    dr.disable_grad(value)
    params.update()
    return grad


def finite_difference_image(params: SceneParameters, key: str, tangent, step: float,
                            **render_args) -> np.ndarray:
    """Central difference ``(I(v + step t) - I(v - step t)) / (2 step)`` of detached renders."""
    base = _numbers(params[key])
    tangent = np.asarray(tangent, np.float64).ravel()
    images = []
    for sign in (1.0, -1.0):
        _with_offset(params, key, base + sign * step * tangent)
        params.update()
        images.append(np.array(render(params.scene, **render_args)))
    _with_offset(params, key, base)
    params.update()
    return (images[0] - images[1]) / (2.0 * step)


def relative_error(ours: np.ndarray, reference: np.ndarray) -> float:
    """Mean of ``|a - r| / max(|r|, 0.2 max|r|)`` over the pixels where either is non-zero.

    The floor keeps pixels where the true derivative is near zero from
    dominating; restricting the mean to the support keeps empty background
    from diluting it.
    """
    scale = np.maximum(np.abs(reference), 0.2 * np.abs(reference).max())
    support = (reference != 0) | (ours != 0)
    if not support.any():
        return 0.0
    return float((np.abs(ours - reference) / scale)[support].mean())


#: Validation cases: one instance of each model kind under an affine map (non-uniform
#: scale on the sphere and cylinder, shear on the cube, reflections on the disk and the
#: mesh), placed off-centre so that no edge runs along a pixel boundary.
VALIDATION_TRANSFORMS = {
    "sphere": [{"translate": [0.13, -0.07, 0]}, {"rotate": {"axis": [0, 0, 1], "angle": 30}},
               {"scale": [1.2, 0.7, 0.9]}],
    "cube": [{"translate": [0.11, 0.06, 0]}, {"rotate": {"axis": [1, 1, 0], "angle": 35}},
             {"matrix": [[0.8, 0.2, 0, 0], [0, 0.8, 0, 0], [0, 0, 0.8, 0], [0, 0, 0, 1]]}],
    "rectangle": [{"translate": [-0.09, 0.12, 0]}, {"rotate": {"axis": [1, 0.3, 0], "angle": 147}},
                  {"scale": [1.1, 0.8, 1]}],
    "disk": [{"translate": [0.08, 0.1, 0]}, {"rotate": {"axis": [0, 1, 0.2], "angle": 152}},
             {"reflect": "x"}],
    "cylinder": [{"translate": [0.07, -0.45, 0]}, {"rotate": {"axis": [1, 0.2, 0], "angle": -70}},
                 {"scale": [0.7, 0.6, 1.4]}],
    "mesh": [{"translate": [-0.06, 0.09, 0]}, {"rotate": {"axis": [1, 0.1, 0], "angle": -50}},
             {"reflect": "y"}, {"scale": 1.1}],
}


def mesh_model(mesh_file: str, smooth: bool = False) -> dict:
    """The mesh model of the validation scenes: shaded flat by default (its creases are
    visibility jumps of their own), or smoothly (Mitsuba's default: no crease jumps)."""
    return {"type": "obj", "filename": mesh_file, **({} if smooth else {"face_normals": True})}


def validation_scene(model: str, size: int, mesh_file: str, smooth: bool = False) -> dict:
    """A gradient-validation scene: the instance ``obj`` in front of a lit wall (a mesh
    ``obj`` shaded smoothly with ``smooth``).

    The point light sits at the camera, so every shadow is hidden behind the
    object that casts it: the image has no shadow boundaries, whose
    derivatives this renderer does not sample (see :mod:`instancing.rendering.boundary_term`).
    """
    return {
        "camera": {"type": "perspective", "fov": 45, "width": size, "height": size,
                   "to_world": [{"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0],
                                             "up": [0, 1, 0]}}]},
        "models": {"mesh": mesh_model(mesh_file, smooth)},
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
        "lights": [{"type": "point", "position": [0, 0, -5], "intensity": [30, 30, 30]}],
        "instances": [
            {"id": "obj", "model": model, "material": "paint", "to_world": VALIDATION_TRANSFORMS[model]},
            {"id": "wall", "model": "rectangle",
             "to_world": [{"translate": [0, 0, 3]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}},
                          {"scale": 5}]},
        ],
    }


def orthographic_view(description: dict, extent: float) -> dict:
    """``description`` seen by an orthographic camera in its camera's pose, the film
    ``extent`` world units wide (Mitsuba's ``orthographic``, its ``to_world`` scaled): the
    curves are seen from a viewer at infinity."""
    camera = description["camera"]
    description["camera"] = {"type": "orthographic", "width": camera["width"], "height": camera["height"],
                             "to_world": camera["to_world"] + [{"scale": [extent / 2, extent / 2, 1]}]}
    return description


#: Where the shadow cases put the point light, so that the object's shadow on the wall is in view.
SHADOW_LIGHT = [1.5, 1.5, -5.0]


#: The area lamp of the penumbra cases: off the camera, so that the object's soft shadow on
#: the wall is in view.
AREA_LAMP = [{"translate": [1.5, 1.5, -3]}, {"rotate": {"axis": [1, 0, 0], "angle": 10}},
             {"scale": [0.6, 0.4, 0.5]}]


def penumbra_scene(model: str, size: int, mesh_file: str, light: str) -> dict:
    """:func:`validation_scene` lit by an area lamp ``lamp`` of model ``light``
    ('rectangle', 'sphere', ...) at :data:`AREA_LAMP`, or by a uniform environment
    (``light='constant'``) instead of the point light: the object's soft shadow on the wall
    is in view."""
    description = validation_scene(model, size, mesh_file)
    if light == "constant":
        description["lights"] = [{"type": "constant", "radiance": [1, 1, 1]}]
        return description
    description["lights"] = []
    description["instances"].append(
        {"id": "lamp", "model": light, "emitter": {"type": "area", "radiance": [40, 40, 40]},
         "to_world": AREA_LAMP})
    return description


def reflected_penumbra_scene(model: str, size: int, mesh_file: str, light: str = "area") -> dict:
    """A scene whose camera sees an object's shadow only by one bounce: a lamp over a floor
    (``light``: 'area', a small rectangle lamp, the shadow soft; 'point', a point light,
    the shadow hard), the instance ``obj`` under the lamp
    (its shadow on the floor), and a screen below the object and beside it, facing down
    (the lamp lights only its back; the object is behind its plane); the camera looks up
    at the screen, which shows the floor by diffuse interreflection. The image's
    derivative is the shadow's motion, a visibility change seen from the path's second
    vertex (the penumbra) or the jump of the light that the third vertex gathers (the hard
    shadow's edge), and nothing else: no path that reaches the camera meets the object."""
    if light not in ("area", "point"):
        raise ValueError(f"light must be 'area' or 'point', got {light!r}")
    description = {
        "camera": {"type": "perspective", "fov": 40, "width": size, "height": size,
                   "to_world": [{"look_at": {"origin": [2.2, 0.0, 0], "target": [2.2, 0.5, 0],
                                             "up": [0, 0, 1]}}]},
        "models": {"mesh": mesh_model(mesh_file)},
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]},
                      "white": {"type": "diffuse", "reflectance": [0.8, 0.8, 0.8]}},
        "instances": [
            {"id": "obj", "model": model, "material": "paint",
             "to_world": [{"translate": [0.3, 1.6, 0.0]}, {"scale": 0.5}]
             + VALIDATION_TRANSFORMS[model][1:]},
            {"id": "floor", "model": "rectangle", "material": "white",
             "to_world": [{"translate": [0, -1, 0]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}},
                          {"scale": 4}]},
            {"id": "screen", "model": "rectangle", "material": "white",
             "to_world": [{"translate": [2.2, 0.5, 0]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                          {"scale": [1.2, 2.0, 1.0]}]},
        ],
    }
    if light == "area":
        description["instances"].append(
            {"id": "lamp", "model": "rectangle", "emitter": {"type": "area", "radiance": [400, 400, 400]},
             "to_world": [{"translate": [0, 3, 0]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                          {"scale": 0.3}]})
    else:
        description["lights"] = [{"type": "point", "position": [0, 3, 0], "intensity": [100, 100, 100]}]
    return description


def interreflection_scene(model: str, size: int, mesh_file: str) -> dict:
    """A scene where the instance ``obj`` is seen only through diffuse interreflection: it
    hangs above the camera's view, lit from below by a directional light that grazes the
    wall from behind (the wall gets no direct light) and casts the object's shadow out of
    view; the wall shows the object's light by one bounce."""
    description = validation_scene(model, size, mesh_file)
    description["lights"] = [{"type": "directional", "direction": [0, 1, 0.25],
                              "irradiance": [20, 20, 20]}]
    description["instances"][0]["to_world"] = (
        [{"translate": [0, 4.3, 2.0]}] + VALIDATION_TRANSFORMS[model])
    return description


#: Contact cases: each model kind sinking into a floor (the floor cuts it).
CONTACT_TRANSFORMS = {
    "sphere": [{"translate": [0.1, 0.05, 0.3]}, {"rotate": {"axis": [0, 0, 1], "angle": 30}},
               {"scale": [0.9, 0.7, 0.8]}],
    "cube": [{"translate": [0.1, 0.05, 0.2]}, {"rotate": {"axis": [1, 1, 0], "angle": 35}},
             {"scale": 0.6}],
    "cylinder": [{"translate": [0.1, 0.05, -0.3]}, {"rotate": {"axis": [1, 0.2, 0], "angle": 30}},
                 {"scale": [0.6, 0.5, 1.2]}],
    "mesh": [{"translate": [0.1, 0.05, 0.1]}, {"rotate": {"axis": [1, 0.1, 0], "angle": -50}},
             {"scale": 0.9}],
}


#: What the contact cases' instance sinks into: a floor (a rectangle), the top face of a
#: turned box (a cube), a floor of mesh tiles (32 coplanar triangles), the faceted top of a
#: big mesh sphere (triangles that are not coplanar), or the top of a big sphere or of a big
#: cylinder lying along x (curved); each surface's top at z = 0.
CONTACT_RECEIVERS = {
    "floor": ("rectangle", [{"scale": 3}]),
    "box": ("cube", [{"translate": [0, 0, -1]}, {"rotate": {"axis": [0, 0, 1], "angle": 20}},
                     {"scale": [1.5, 1.5, 1]}]),
    "tiles": ("tiles", [{"rotate": {"axis": [0, 0, 1], "angle": 10}}, {"scale": 3}]),
    "boulder": ("boulder", [{"translate": [0, 0, -2.5]}, {"scale": 2.5}]),  # top vertex at z = 1
    "dome": ("sphere", [{"translate": [0, 0, -2.5]}, {"scale": 2.5}]),
    "drum": ("cylinder", [{"translate": [-3, 0, -2.5]}, {"rotate": {"axis": [0, 1, 0], "angle": 90}},
                          {"scale": [2.5, 2.5, 6]}]),
}


def contact_scene(model: str, size: int, mesh_file: str, receiver: str = "floor") -> dict:
    """A gradient-validation scene for contact curves: the instance ``obj`` cut by the
    surface ``receiver`` (:data:`CONTACT_RECEIVERS`), seen from above at an angle, lit from
    the camera (no shadow in view)."""
    floor_model, floor_transform = CONTACT_RECEIVERS[receiver]
    return {
        "camera": {"type": "perspective", "fov": 40, "width": size, "height": size,
                   "to_world": [{"look_at": {"origin": [0, -4, 3], "target": [0, 0, 0],
                                             "up": [0, 0, 1]}}]},
        "models": {"mesh": mesh_model(mesh_file),
                   "tiles": {"type": "obj", "filename": str(DATA / "tiles.obj")},
                   "boulder": {"type": "obj", "filename": str(DATA / "icosphere.obj")}},
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]},
                      "floor": {"type": "diffuse", "reflectance": [0.3, 0.4, 0.5]}},
        "lights": [{"type": "point", "position": [0, -4, 3], "intensity": [30, 30, 30]}],
        "instances": [
            {"id": "obj", "model": model, "material": "paint", "to_world": CONTACT_TRANSFORMS[model]},
            {"id": "floor", "model": floor_model, "material": "floor", "to_world": floor_transform}]}


#: An upright panel standing in the contact cases' floor (a rectangle turned about x).
PANEL_TRANSFORM = [{"translate": [0.1, 0.05, 0.3]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                   {"scale": [0.8, 0.6, 1]}]


def bounce_contact_scene(model: str, size: int, mesh_file: str, floor: dict | None = None) -> dict:
    """:func:`contact_scene` on the floor (``model`` 'rectangle': :data:`PANEL_TRANSFORM`)
    rendered by ``path`` (``max_depth`` 3) and lit from the side: each surface bounces light
    onto the other, up to their contact line. ``floor``: the floor's material (default
    diffuse)."""
    description = contact_scene("sphere" if model == "rectangle" else model, size, mesh_file)
    if floor is not None:
        description["materials"]["floor"] = floor
    if model == "rectangle":
        description["instances"][0].update(model="rectangle", to_world=PANEL_TRANSFORM)
    description["lights"] = [{"type": "point", "position": [1.5, -2.0, 3.0], "intensity": [30, 30, 30]}]
    description["integrator"] = {"type": "path", "max_depth": 3}
    return description


def bounce_contact_tangent(params: SceneParameters, model: str, name: str) -> np.ndarray:
    """The tangent of :func:`bounce_contact_scene`'s cases: the panel moved along its normal,
    other models along (0.3, 0.2, 1) (sinking); a rotation about world z (per radian)."""
    if name == "translation":
        return np.array([0.0, 1.0, 0.0]) if model == "rectangle" else np.array([0.3, 0.2, 1.0])
    return rotation_tangent(_numbers(params[f"obj.{name}"]), [0.0, 0.0, 1.0])


def lamp_scene(kind: str, size: int) -> dict:
    """A gradient-validation scene for a moving area light: a wall lit by an emitting
    instance ``lamp`` of model ``kind`` (non-uniformly scaled and turned), with nothing
    between them."""
    return {
        "camera": {"type": "perspective", "fov": 45, "width": size, "height": size,
                   "to_world": [{"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0],
                                             "up": [0, 1, 0]}}]},
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
        "instances": [
            {"id": "wall", "model": "rectangle", "material": "paint",
             "to_world": [{"translate": [0, 0, 3]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}},
                          {"scale": 5}]},
            {"id": "lamp", "model": kind, "emitter": {"type": "area", "radiance": [6, 6, 6]},
             "to_world": [{"translate": [0.6, 0.4, 1.2]}, {"rotate": {"axis": [1, 0, 0], "angle": 20}},
                          {"scale": [0.5, 0.3, 0.4]}]}]}


def glossy_bounce_scene(size: int, alpha: float = 0.2) -> dict:
    """A scene whose image changes through a glossy bounce off the moving instance's own
    light: a spot light aims at a rough metal floor (GGX, roughness ``alpha``), whose
    highlight lands on the instance ``obj``, a diffuse panel facing the camera above the
    floor, outside the spot's cone. Moving the panel towards the camera moves the camera
    rays' hits on it, and with them the direction in which the floor must reflect the spot:
    the highlight's derivative is the floor's BSDF changing with its incoming direction, a
    vertex away from the moving one."""
    return {
        "camera": {"type": "perspective", "fov": 45, "width": size, "height": size,
                   "to_world": [{"look_at": {"origin": [0, 0, -5], "target": [0, 0, 0],
                                             "up": [0, 1, 0]}}]},
        "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]},
                      "floor": {"type": "roughconductor", "material": "Al", "distribution": "ggx",
                                "alpha": alpha}},
        "lights": [{"type": "spot", "intensity": [200, 200, 200], "cutoff_angle": 25,
                    "to_world": [{"look_at": {"origin": [0, 1.5, -2.5], "target": [0, -1.3, -1.2],
                                              "up": [0, 0, 1]}}]}],
        "instances": [
            {"id": "obj", "model": "rectangle", "material": "paint",
             "to_world": [{"translate": [0.05, 0.03, 0]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}},
                          {"scale": [3, 1.1, 1]}]},
            {"id": "floor", "model": "rectangle", "material": "floor",
             "to_world": [{"translate": [0, -1.3, 0]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}},
                          {"scale": 6}]}]}


def mirror_floor_scene(size: int, floor: dict, mesh_file: str | None = None) -> dict:
    """The ellipsoid ``obj`` of :func:`validation_scene` over a floor of material ``floor``
    (a mirror, a smooth plastic), seen from above at an angle, so that the camera sees it
    and its reflection; a point light off the camera and a dim uniform environment. The
    floor is a rectangle, or the flat mesh ``mesh_file`` in its z = 0 plane."""
    description = validation_scene("sphere", size, "")
    description["models"] = {} if mesh_file is None else {"floor": {"type": "obj", "filename": mesh_file}}
    description["camera"]["to_world"] = [{"look_at": {"origin": [0, 1.0, -5], "target": [0, -0.6, 0],
                                                      "up": [0, 1, 0]}}]
    description["materials"]["floor"] = floor
    description["lights"] = [{"type": "point", "position": [1.5, 3.0, -4.0], "intensity": [40, 40, 40]},
                             {"type": "constant", "radiance": [0.2, 0.2, 0.2]}]
    description["instances"].append(
        {"id": "floor", "model": "rectangle" if mesh_file is None else "floor", "material": "floor",
         "to_world": [{"translate": [0, -1.2, 0]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}},
                      {"scale": 5}]})
    return description


def smooth_environment_map(path: Path) -> Path:
    """Write a smooth 64x32 environment map (colours varying as low sines over the sphere of
    directions) to ``path``: what a mirror or a glass shows changes smoothly as it moves."""
    v, u = np.meshgrid((np.arange(32) + 0.5) / 32, (np.arange(64) + 0.5) / 64, indexing="ij")
    texels = np.stack([1.0 + 0.8 * np.sin(2 * np.pi * u) * np.sin(np.pi * v),
                       1.0 + 0.8 * np.cos(np.pi * v),
                       1.0 + 0.8 * np.sin(4 * np.pi * u + 1.0) * np.sin(np.pi * v) ** 2], axis=-1)
    write_exr(path, texels.astype(np.float32))
    return path


def delta_lobe_scene(model: str, material: dict, size: int, environment: Path) -> dict:
    """The instance ``obj`` of :func:`validation_scene` alone, of a smooth ``material`` (a
    mirror, a glass), under the environment map ``environment``: its image is what it
    reflects or refracts, which moves with it through its delta lobes."""
    description = validation_scene(model, size, "")
    description["materials"]["paint"] = material
    description["lights"] = [{"type": "envmap", "filename": str(environment)}]
    description["instances"] = description["instances"][:1]
    description.pop("models")
    return description


def rotation_tangent(q: np.ndarray, axis) -> np.ndarray:
    """Quaternion tangent of a rotation by one radian about the object-space ``axis``:
    d/da (q * (sin(a/2) axis, cos(a/2))) at a = 0, i.e. q * (axis / 2, 0)."""
    x, y, z, w = np.asarray(q, np.float64)
    v = 0.5 * np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return np.array([w * v[0] + y * v[2] - z * v[1], w * v[1] + z * v[0] - x * v[2],
                     w * v[2] + x * v[1] - y * v[0], -(x * v[0] + y * v[1] + z * v[2])])


def validation_tangent(params: SceneParameters, name: str) -> np.ndarray:
    """The tangent used for parameter ``name`` of ``obj``: a translation along (1, 0.5, 0),
    a rotation about object-space y (per radian), a scale of the x axis."""
    if name == "translation":
        return np.array([1.0, 0.5, 0.0])
    if name == "scale":
        return np.array([1.0, 0.0, 0.0])
    return rotation_tangent(_numbers(params["obj.rotation"]), [0.0, 1.0, 0.0])


def parameter(params: SceneParameters, name: str) -> tuple[str, np.ndarray]:
    """(key, tangent) of a validation parameter: the object's (:func:`validation_tangent`),
    or the lamp's ('lamp.translation' along (1, 0.5, 0), 'lamp.rotation' about its y)."""
    if name == "lamp.translation":
        return name, np.array([1.0, 0.5, 0.0])
    if name == "lamp.rotation":
        return name, rotation_tangent(_numbers(params[name]), [0.0, 1.0, 0.0])
    return f"obj.{name}", validation_tangent(params, name)


def against_finite_differences(params: SceneParameters, key: str, tangent, step: float,
                               ours: dict, reference: dict, without: dict | None = None) -> dict:
    """Our gradient image (render arguments ``ours``, seed 1) against central differences
    (``reference``, seeds 2 and 3): {'error', 'spread' (the two differences' relative
    error), 'peak' (max |difference|), 'seconds' (ours), and with ``without`` (arguments
    overriding ``ours``, e.g. a term switched off) 'without', that render's error}."""
    start = time.perf_counter()
    image = gradient_image(params, key, tangent, seed=1, **ours)
    seconds = time.perf_counter() - start
    refs = [finite_difference_image(params, key, tangent, step, seed=seed, **reference)
            for seed in (2, 3)]
    result = {"error": relative_error(image, refs[0]), "spread": relative_error(refs[1], refs[0]),
              "peak": float(np.abs(refs[0]).max()), "seconds": seconds}
    if without is not None:
        result["without"] = relative_error(
            gradient_image(params, key, tangent, seed=1, **{**ours, **without}), refs[0])
    return result


#: Penumbra cases (model, parameter, light, integrator): every model kind and transform
#: parameter under a rectangle lamp in `direct` and `path`, each kind's translation under a
#: sphere lamp and under the environment, and the lamps' own translation (and the
#: rectangle's rotation) with the ellipsoid between lamp and wall. (Turning the sphere lamp
#: changes this image by less than its finite differences' noise, 10 %; its rotation is
#: checked without occluder, :func:`lamp_scene`.)
PENUMBRA_CASES = (
    [(m, p, "rectangle", i) for m in VALIDATION_TRANSFORMS for p in ("translation", "rotation", "scale")
     for i in ("direct", "path")]
    + [(m, "translation", light, "direct") for m in VALIDATION_TRANSFORMS
       for light in ("sphere", "constant")]
    + [("sphere", "lamp.translation", light, i) for light in ("rectangle", "sphere")
       for i in ("direct", "path")]
    + [("sphere", "lamp.rotation", "rectangle", i) for i in ("direct", "path")])


def penumbra_case(model: str, name: str, light: str, integrator: str, size: int, mesh_file: str,
                  without: bool = False) -> dict:
    """A :data:`PENUMBRA_CASES` case against central differences (see
    :func:`against_finite_differences`; ``without``: also with sppi = 0)."""
    params = traverse(load_scene(penumbra_scene(model, size, mesh_file, light)))
    key, tangent = parameter(params, name)
    args = {"integrator": integrator, "max_depth": 3 if integrator == "path" else None}
    spp = 2048 if model in ("sphere", "cylinder") else 1024
    # Few of the torus's 432 edges are silhouettes from any one point: more samples.
    sppi = 4096 if model == "mesh" else 1024
    return against_finite_differences(
        params, key, tangent, 0.004, {"spp": spp, "sppp": 1024, "sppi": sppi, **args},
        {"spp": 16384 if integrator == "direct" else 8192, **args},
        {"sppi": 0} if without else None)


#: The interreflection cases' models: closed ones (a one-sided card or disk out of view
#: turns its lit or its black side to the wall by the validation transform's chance).
INTERREFLECTION_MODELS = ("sphere", "cube", "cylinder", "mesh")


def reflected_penumbra_case(model: str, size: int, mesh_file: str, max_depth: int = 3,
                            sppi: int = 262144, fd_spp: int = 65536, light: str = "area",
                            without: bool = False) -> dict:
    """:func:`reflected_penumbra_scene`'s object translated, `path`, against central
    differences with a larger step at ``fd_spp`` (a smooth field under path noise, which
    common random numbers cancel well): 0.1 for the area lamp's penumbra; for the point
    light's hard shadow, whose image curves more, 0.05 (for the cube, steps 0.2, 0.1 and
    0.05 give mean derivatives 0.0244, 0.0226 and 0.0206: the differences' own bias at
    0.1 is 9 %) and 0.025 for the torus mesh (0.160 at 0.05, 0.181 at 0.025). Ours with ``sppi`` secondary samples (the floor's shadow is a small
    part of the second vertices, and its lamp a small part of the occluder's outline seen
    from there) and 65 536 spp for the interior (from max_depth 4 on, paths bounce off
    the object, grazing it near its outline); ``without``: also with sppi = 0."""
    params = traverse(load_scene(reflected_penumbra_scene(model, size, mesh_file, light)))
    key, tangent = parameter(params, "translation")
    args = {"integrator": "path", "max_depth": max_depth}
    step = 0.1 if light == "area" else 0.025 if model == "mesh" else 0.05
    return against_finite_differences(params, key, tangent, step,
                                      {"spp": 65536, "sppp": 64, "sppi": sppi, **args},
                                      {"spp": fd_spp, **args}, {"sppi": 0} if without else None)


def interreflection_case(model: str, size: int, mesh_file: str, spp: int,
                         without: bool = False) -> dict:
    """:func:`interreflection_scene`'s object translated, `path` (max_depth 3), against
    central differences with a larger step (0.03) and 65 536 spp: the field is smooth and
    path-tracing noise dominates the differences."""
    params = traverse(load_scene(interreflection_scene(model, size, mesh_file)))
    key, tangent = parameter(params, "translation")
    args = {"integrator": "path", "max_depth": 3}
    return against_finite_differences(
        params, key, tangent, 0.03, {"spp": spp, "sppp": 1024, "sppi": 2048, **args},
        {"spp": 65536, **args}, {"sppi": 0} if without else None)

