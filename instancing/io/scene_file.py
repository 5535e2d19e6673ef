"""Reading scene descriptions: JSON files or equivalent Python dicts.

The format follows Mitsuba's dict vocabulary where the concept is the same
(``type``, ``filename``, ``to_world``, ``reflectance``) and adds what Mitsuba
lacks: models shared by many instances and per-instance materials::

    {
      "models":    {"ball": {"type": "sphere"}, "tree": {"type": "ply", "filename": "tree.ply"}},
      "materials": {"red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}},
      "instances": [{"id": "a", "model": "ball", "material": "red",
                     "to_world": [{"translate": [0, 0, 1]}, {"scale": [1, 2, 1]}]},
                    {"model": "tree", "material": "red", "to_world": "forest.npy"}],
      "camera": {...}, "lights": [...]
    }

A scene with several views lists them as ``"cameras": [{...}, ...]`` (each may have an
``"id"``) instead of one ``"camera"``.

Mesh models are shaded as Mitsuba shades them: smoothly, by the file's vertex
normals or by normals computed like Mitsuba's; ``"face_normals": true`` shades
them flat and ``"flip_normals": true`` turns them inside out.

``to_world`` is a 4x4 row-major matrix, a list of operations composed in
written order like Mitsuba's ``T().translate(..).rotate(..).scale(..)`` (the
last operation acts first on points), or, for large sets, the name of a
``.npy`` file (or a NumPy array) of (N, 4, 4) matrices giving N instances.
Every problem raises :class:`~instancing.core.errors.SceneError` naming the culprit.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import gc
import itertools
import json
import math
import os
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from ..core import transform as tf
from ..core.arguments import FLOAT32_MAX, integer, is_real
from ..core.errors import SceneError, TransformError
from ..core.transform_spec import parse_transform, parse_transforms, require_numbers
from ..core.memory import PEAK_BYTES_PER_INSTANCE, require_memory
from ..materials.bump_map import is_texture_spec
from ..materials.material import Material, parse_material
from ..materials.texture import Texture, is_texture, parse_texture
from ..models.analytic import ANALYTIC_MODELS
from ..models.bspline_curve import BSplineCurveData
from ..models.linear_curve import LinearCurveData, read_curve_file
from ..models.mesh import MeshData, vertex_normals
from ..models.sdf_grid import NORMAL_MODES, SDFGridData
from ..rendering.film import MAX_DEPTH, RR_DEPTH
from ..rendering.integrators.aov import MITSUBA_AOVS, mitsuba_aov_channel_names
from ..rendering.integrators.direct import strategy_samples
from ..scene.camera import (CAMERAS, CUBIC_FILTERS, MAX_FILM_SIZE, RFILTER_SIZES, RFILTERS, Camera,
                            diagonal_fov, fov_along_x)
from ..scene.medium import MEDIUM_TYPES, PHASE_FUNCTIONS, Medium
from ..scene.description import (ENVIRONMENTS, AreaEmitter, ConstantLight, DirectionalLight,
                                 EnvironmentMap, InstanceMatrices, Light, ModelSpec, PointLight,
                                 IntegratorChoice, ProjectorLight, SceneDescription, SpotLight)
from ..scene.instance_ids import InstanceIds
from ..scene.instance_table import BSPLINE_KIND, CURVE_KIND, GRID_KIND
from ..scene.scene import Accel, Scene
from .image import ImageFileError, read_texture
from .mesh_file import read_mesh
from .mitsuba_xml import xml_to_scene_dict
from .volume_grid import read_volume_grid
from .output_file import replaced
from .scene_json import DuplicateKeyError, read_scene_json

MESH_FILE_TYPES = ("obj", "ply", "serialized")
#: The keys of an SDF grid model (Mitsuba's ``sdfgrid``: a volume grid file, or the values).
_GRID_MODEL_KEYS = frozenset({"type", "filename", "values", "normals"})
#: The keys of a curve model (Mitsuba's ``linearcurve`` and ``bsplinecurve``: a curve file, or the
#: curves).
_CURVE_MODEL_KEYS = frozenset({"type", "filename", "curves", "points_to_world"})
#: The control points' type of each curve model type.
_CURVE_DATA = {CURVE_KIND: LinearCurveData, BSPLINE_KIND: BSplineCurveData}
_MESH_MODEL_KEYS = frozenset({"type", "filename", "face_normals", "flip_normals", "flip_tex_coords",
                              "shape_index", "computed_normals_to_world"})
#: Whether a mesh file type's v texture coordinate is flipped by default (Mitsuba's plugins).
_FLIP_TEX_COORDS = {"obj": True, "ply": False, "serialized": False}
#: Mitsuba's default BSDF: diffuse with reflectance 0.5.
DEFAULT_MATERIAL = parse_material("default", {"type": "diffuse", "reflectance": 0.5})
_TOP_LEVEL_KEYS = {"models", "materials", "instances", "camera", "cameras", "lights", "media",
                   "integrator"}
_INSTANCE_KEYS = {"id", "model", "material", "to_world", "emitter", "interior", "exterior"}
#: The keys of a plain instance entry: one instance placed by one 4x4 matrix.
_PLAIN_KEYS = frozenset(_INSTANCE_KEYS - {"emitter", "interior", "exterior"})
_MEDIUM_KEYS = {"type", "sigma_t", "albedo", "scale", "phase", "sample_emitters",
                "has_spectral_extinction"}


#: File kinds that users pass where a scene belongs, by extension.
_NOT_SCENES = {".obj": "a mesh file", ".ply": "a mesh file", ".serialized": "a mesh file",
               ".exr": "an image", ".png": "an image", ".npy": "an array file"}


def read_scene_source(source: str | os.PathLike | dict,
                      base_dir: str | os.PathLike | None = None,
                      parameters: dict[str, Any] | None = None) -> tuple[dict, Path]:
    """The scene dict and the folder relative paths resolve against: a file's own folder;
    for a dict ``base_dir``, by default the current directory. ``parameters`` set a Mitsuba
    XML scene's ``$name`` values."""
    if parameters and not (isinstance(source, (str, os.PathLike))
                           and Path(source).suffix.lower() == ".xml"):
        raise SceneError(f"scene parameters {sorted(parameters)} apply to Mitsuba XML scenes "
                         "($name values) only")
    if isinstance(source, dict):
        if base_dir is not None and not isinstance(base_dir, (str, os.PathLike)):
            raise TypeError(f"base_dir must be a folder's path (str or os.PathLike), got "
                            f"{type(base_dir).__name__} {base_dir!r:.60}")
        return source, Path.cwd() if base_dir is None else Path(base_dir)
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source must be a scene dict or the path (str or os.PathLike) of a "
                        f".json or .xml scene file, got {type(source).__name__} {source!r:.60}")
    if base_dir is not None:
        raise SceneError(f"base_dir is for dict scenes; relative file names in {str(source)!r} "
                         "resolve against its own folder")
    path = Path(source)
    if path.is_dir():
        raise SceneError(f"scene {str(source)!r} is a folder ({path.resolve()}); expected a scene "
                         "file (.json or .xml)")
    if not path.is_file():
        raise SceneError(f"scene file not found: {path} (resolved: {path.resolve()})")
    if path.suffix.lower() in _NOT_SCENES:
        raise SceneError(f"{path} is {_NOT_SCENES[path.suffix.lower()]}, not a scene; a scene "
                         "(.json or .xml) places models and instances (docs/scene-format.md)")
    if path.suffix.lower() == ".xml":
        return xml_to_scene_dict(path, parameters, check=_check_record)
    try:
        data = read_scene_json(path)
    except json.JSONDecodeError as err:
        raise SceneError(f"{path}: malformed JSON at line {err.lineno}, column {err.colno}: "
                         f"{err.msg}") from None
    except DuplicateKeyError as err:
        raise SceneError(f"{path}: the key {err.key!r} is given twice in one object (keys {err.keys}); "
                         "give each key once") from None
    except UnicodeDecodeError as err:
        raise SceneError(f"{path}: not a UTF-8 text file ({err.reason})") from None
    except RecursionError:
        raise SceneError(f"{path}: its JSON is nested too deeply to read (a scene's values nest a "
                         "few levels deep)") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: the top level must be a JSON object, got {type(data).__name__}")
    return data, path.parent


def parse_scene(source: str | os.PathLike | dict,
                base_dir: str | os.PathLike | None = None,
                parameters: dict[str, Any] | None = None) -> SceneDescription:
    """Validate a scene dict or JSON file and flatten its instances (``base_dir``,
    ``parameters``: see :func:`load_scene`)."""
    with _no_cycle_collection():
        return _parsed(source, base_dir, parameters)


@contextlib.contextmanager
def _no_cycle_collection():
    """The cyclic garbage collector paused: reading a scene makes hundreds of thousands of
    lists and dicts (a large file's entries) without cycles, and each collection pass they
    trigger walks every live object of the process."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _parsed(source: str | os.PathLike | dict, base_dir: str | os.PathLike | None,
            parameters: dict[str, Any] | None) -> SceneDescription:
    """:func:`parse_scene`'s result; a scene file's problems found in its values name the
    file first (its reader's, a JSON or XML error, name it themselves)."""
    data, base = read_scene_source(source, base_dir, parameters)
    if isinstance(source, dict):
        return _described(data, base)
    try:
        return _described(data, base)
    except SceneError as err:
        raise type(err)(f"{Path(source)}: {err}") from None


def _described(data: dict, base: Path) -> SceneDescription:
    """The scene description of the scene dict ``data`` (relative file names resolved
    against ``base``)."""
    unknown = sorted(set(data) - _TOP_LEVEL_KEYS)
    if unknown:
        raise SceneError(f"unknown top-level scene keys {unknown}; expected some of "
                         f"{sorted(_TOP_LEVEL_KEYS)}")
    models = _parse_models(data.get("models", {}), base)
    materials = _parse_materials(data.get("materials", {}), base)
    instances = data.get("instances", [])
    if not isinstance(instances, list):
        raise SceneError(f"'instances' must be a list, got {type(instances).__name__}")
    materials.setdefault("default", DEFAULT_MATERIAL)
    media = parse_media(data.get("media", {}), base)
    ids, model_of, material_of, matrices, emitters, instance_media = _parse_instances(
        instances, models, materials, base, media)
    cameras = parse_cameras(data)
    for k, camera in enumerate(cameras):
        if camera.medium and camera.medium not in media:
            raise SceneError(f"camera {camera.id or k!r}: unknown medium {camera.medium!r}; defined "
                             f"media are {sorted(media)}")
    lights = parse_lights(data.get("lights", []), base)
    clash = sorted(light.id for light in lights
                   if getattr(light, "id", None) and (light.id in ids or light.id in materials))
    if clash:
        raise SceneError(f"light ids {clash} are also instance or material names: parameter "
                         "keys would be ambiguous")
    integrator = parse_integrator(data["integrator"]) if "integrator" in data else None
    return SceneDescription(models, materials, ids, model_of, material_of, matrices, emitters,
                            cameras, lights, base, media, instance_media, integrator)


#: Mitsuba's integrators whose images ours render, by ours: the same estimator, or one of
#: the same expectation (the projective and path-replay ones differ in their derivatives,
#: volpathmis in its sampling of the channels).
INTEGRATOR_EQUIVALENTS = {"direct": ("direct", "direct_projective"),
                          "path": ("path", "prb", "prb_basic", "prb_projective"),
                          "volpath": ("volpath", "volpathmis", "prbvolpath")}
#: Mitsuba's other integrators: a file may name them, and renders must then name theirs.
OTHER_INTEGRATORS = ("depth", "ptracer", "stokes", "prb_reparam",
                     "direct_reparam", "emission_reparam", "volprim_rf_basic")
#: Where Mitsuba's integrators that ours render start Russian roulette, as ours count it
#: (the rr_depth of ours that stops paths after the same bounces): its path, volpath,
#: volpathmis and prbvolpath as ours; prb and prb_projective one bounce later (they compare
#: the depth before counting the bounce); prb_basic never.
_ROULETTE_OFFSET = {"prb": 1, "prb_projective": 1}
_NO_ROULETTE = ("prb_basic",)
#: Integrator parameters that change a render's noise or cost only (sample counts,
#: derivative terms' samples and guiding): read, not honoured (but for the strategies'
#: sample counts of Mitsuba's ``direct``, _STRATEGY_KEYS).
_NOISE_ONLY = {"emitter_samples", "bsdf_samples", "shading_samples", "sppc", "sppp",
               "sppi", "guiding", "guiding_proj", "guiding_rounds", "proj_seed_spp"}
#: Mitsuba's direct integrator's samples per strategy (``shading_samples``: both), honoured.
_STRATEGY_KEYS = ("emitter_samples", "bsdf_samples", "shading_samples")


def parse_integrator(spec: Any) -> IntegratorChoice:
    """Validate a scene's ``"integrator"`` (Mitsuba's ``<integrator>``: ``{"type": ...,
    parameter: value}``) into the :class:`~instancing.scene.description.IntegratorChoice`
    that renders naming none use. A type of :data:`INTEGRATOR_EQUIVALENTS` is rendered by
    ours with its ``max_depth`` and its Russian roulette (``rr_depth`` in our count, see
    ``_ROULETTE_OFFSET``) and ``hide_emitters``; a type of :data:`OTHER_INTEGRATORS`, a
    ``max_depth`` or ``rr_depth`` on ``direct``, or a parameter that is not in
    :data:`_NOISE_ONLY` leaves a refusal instead (raised by such renders); Mitsuba's ``aov``
    and ``moment`` see :func:`_parse_aov` and :func:`_parse_moment`. Unknown types and
    malformed values raise :class:`SceneError` here."""
    if not isinstance(spec, dict) or not isinstance(spec.get("type"), str):
        raise SceneError(f"integrator must be a dict with a 'type', got {spec!r}")
    given = spec["type"]
    if given == "aov":
        return _parse_aov(spec)
    if given == "moment":
        return _parse_moment(spec)
    name = next((ours for ours, types in INTEGRATOR_EQUIVALENTS.items() if given in types), None)
    if name is None and given not in OTHER_INTEGRATORS:
        known = sorted(t for types in INTEGRATOR_EQUIVALENTS.values() for t in types)
        raise SceneError(f"integrator: unknown type {given!r}; known: "
                         f"{known + ['aov', 'moment'] + sorted(OTHER_INTEGRATORS)}")
    if name is None:
        return IntegratorChoice(given, refusal=f"{given!r} has no counterpart here")
    for key, value in spec.items():
        if key != "type" and not isinstance(value, (bool, int, float, str)):
            raise SceneError(f"integrator: {key!r} must be a number, a flag or a string, got {value!r}")
    depths = {key: integer(key, spec[key], low, MAX_DEPTH, "integrator")
              for key, low in (("max_depth", -1), ("rr_depth", 1)) if key in spec}
    hide = spec.get("hide_emitters")
    if hide is not None and not isinstance(hide, bool):
        raise SceneError(f"integrator: hide_emitters must be true or false, got {hide!r}")
    strategies = _strategies(spec) if given == "direct" else {}
    unhonoured = sorted(set(spec) - {"type", "hide_emitters"} - set(depths) - _NOISE_ONLY)
    if name == "direct":
        unhonoured += sorted(depths)
    if unhonoured:
        return IntegratorChoice(given, refusal=f"{given!r} with {unhonoured}, which ours do not "
                                               "render as Mitsuba's")
    rr_depth = depths.get("rr_depth")
    if given in _NO_ROULETTE:
        rr_depth = MAX_DEPTH
    elif given in _ROULETTE_OFFSET:
        rr_depth = min((rr_depth or RR_DEPTH) + _ROULETTE_OFFSET[given], MAX_DEPTH)
    return IntegratorChoice(given, name, depths.get("max_depth"), rr_depth, hide, **strategies)


def _parse_aov(spec: dict) -> IntegratorChoice:
    """Mitsuba's ``aov`` integrator: ``aovs`` as ``"label:type, ..."`` (types of
    :data:`MITSUBA_AOVS`) and the ``integrators`` nested in it (:func:`_nested_integrators`),
    each rendered as its own RGB before the AOVs, as Mitsuba's ``mi.render`` gives them;
    channels are named as Mitsuba names them (``label.X``)."""
    unhonoured = sorted(set(spec) - {"type", "aovs", "integrators"})
    if unhonoured:
        return IntegratorChoice("aov", refusal=f"'aov' with {unhonoured}, which ours do not render as "
                                               "Mitsuba's")
    text = spec.get("aovs", "")
    if not isinstance(text, str):
        raise SceneError(f"integrator: aovs must be a string of 'label:type' entries, got {text!r}")
    entries = [entry.strip() for entry in text.split(",") if entry.strip()]
    pairs = [entry.rsplit(":", 1) for entry in entries]
    malformed = [entry for entry, pair in zip(entries, pairs)
                 if len(pair) != 2 or not all(x.strip() for x in pair)]
    if malformed:
        raise SceneError(f"integrator: aovs entries {malformed} are not 'label:type'")
    pairs = [(label.strip(), kind.strip()) for label, kind in pairs]
    nested = _nested_integrators(spec)
    other = sorted({kind for _, kind in pairs} - set(MITSUBA_AOVS))
    if other:
        return IntegratorChoice("aov", refusal=f"'aov' with the AOV types {other}, which ours do not "
                                               f"give as Mitsuba's (ours: {sorted(MITSUBA_AOVS)})")
    if isinstance(nested, IntegratorChoice):
        return nested
    channels = mitsuba_aov_channel_names(pairs, [label for label, _ in nested])
    if not channels:
        return IntegratorChoice("aov", refusal="'aov' with neither AOVs nor integrators")
    twice = sorted({c for c in channels if channels.count(c) > 1})
    if twice:
        raise SceneError(f"integrator: the aov integrator names the channels {twice} twice")
    return IntegratorChoice("aov", "aov", aovs=tuple(pairs), nested=nested)


def _parse_moment(spec: dict) -> IntegratorChoice:
    """Mitsuba's ``moment`` integrator: the ``integrators`` nested in it
    (:func:`_nested_integrators`, at least one), each rendered with the first and second
    moments of its samples' XYZ (:func:`~instancing.rendering.film.moment_channel_names`)."""
    unhonoured = sorted(set(spec) - {"type", "integrators"})
    if unhonoured:
        return IntegratorChoice("moment", refusal=f"'moment' with {unhonoured}, which ours do not "
                                                  "render as Mitsuba's")
    nested = _nested_integrators(spec)
    if isinstance(nested, IntegratorChoice):
        return nested
    if not nested:
        raise SceneError("integrator: 'moment' needs an integrator nested in it (as Mitsuba's)")
    labels = [label for label, _ in nested]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        raise SceneError(f"integrator: the moment integrator names the integrators {twice} twice")
    return IntegratorChoice("moment", "moment", nested=nested)


def _nested_integrators(spec: dict) -> tuple[tuple[str, IntegratorChoice], ...] | IntegratorChoice:
    """The ``integrators`` nested in Mitsuba's ``aov`` or ``moment`` (``{"type": ..., "id":
    label, parameter: value}`` each, the label naming its channels), as (label, choice)
    pairs; or a refusal where ours do not render one of them as asked (an ``aov`` or
    ``moment`` nested in another among them)."""
    around = spec["type"]
    nested = spec.get("integrators", [])
    if not isinstance(nested, list) or not all(isinstance(n, dict) for n in nested):
        raise SceneError(f"integrator: 'integrators' (those nested in {around!r}) must be a list of "
                         f"integrators, got {nested!r}")
    labels = [str(n.get("id") or n.get("type")) for n in nested]
    choices = [parse_integrator({k: v for k, v in n.items() if k != "id"}) for n in nested]
    for choice in choices:
        if choice.name in (None, "aov", "moment"):
            why = choice.refusal or f"an {choice.given!r} nested in {around!r}"
            return IntegratorChoice(around, refusal=f"{around!r} around {choice.given!r}: {why}")
    return tuple(zip(labels, choices))


def _strategies(spec: dict) -> dict:
    """Mitsuba's direct integrator's ``emitter_samples`` and ``bsdf_samples`` (each defaulting
    to ``shading_samples``, else 1), checked; {} where the file sets none."""
    given = [key for key in _STRATEGY_KEYS if key in spec]
    if not given:
        return {}
    if "shading_samples" in given and len(given) > 1:
        raise SceneError("integrator: shading_samples sets both emitter_samples and bsdf_samples; "
                         "give either it or them (as Mitsuba's direct)")
    both = spec.get("shading_samples", 1)
    emitter, bsdf = strategy_samples(spec.get("emitter_samples", both), spec.get("bsdf_samples", both),
                                     "integrator")
    return {"emitter_samples": emitter, "bsdf_samples": bsdf}


def parse_media(media: Any, base: Path | None = None) -> dict[str, Medium]:
    """Validate ``"media"``: name -> homogeneous medium (:class:`~instancing.scene.medium.Medium`;
    a volume texture's file relative to ``base``)."""
    if not isinstance(media, dict):
        raise SceneError("'media' must be an object of name -> medium")
    return {name: parse_medium(name, spec, base) for name, spec in media.items()}


def parse_medium(name: str, spec: Any, base: Path | None = None, where: str | None = None,
                 read_image: Callable | None = None) -> Medium:
    """One medium record: Mitsuba's ``homogeneous`` or ``heterogeneous`` medium with their
    defaults (albedo 0.75, sigma_t 1, scale 1, an isotropic phase function, emitter sampling
    on, spectral extinction); a heterogeneous medium's sigma_t a ``volume`` texture, the
    albedo a colour or a ``volume`` texture. Its problems are named by ``where`` (default:
    the medium's name); its grids read by ``read_image`` (as ``parse_texture``'s; default:
    files relative to ``base``, by default the current directory)."""
    where = f"medium {name!r}" if where is None else where
    if not isinstance(spec, dict) or spec.get("type") not in MEDIUM_TYPES:
        kind = spec.get("type") if isinstance(spec, dict) else spec
        raise SceneError(f"{where}: unknown medium type {kind!r}; supported: {list(MEDIUM_TYPES)}")
    extra = sorted(set(spec) - _MEDIUM_KEYS)
    if extra:
        raise SceneError(f"{where}: unknown keys {extra}; a medium has some of {sorted(_MEDIUM_KEYS)}")
    if read_image is None:
        read_image = _image_reader(Path(".") if base is None else base, read_texture, where)

    def unit_rgb(value: Any, at: str) -> list[float]:
        rgb = _rgb(value, at)
        if max(rgb) > 1:
            raise SceneError(f"{at} must lie in [0, 1] per channel, got {rgb}")
        return rgb

    def volume(key: str, value: Any, check: Callable) -> Texture:
        if value.get("type") != "volume":
            raise SceneError(f"{where}: {key}: a medium's texture must be a 'volume' (a "
                             f"gridvolume's or constvolume's values in space), got {value.get('type')!r}")
        return parse_texture(f"{where}: {key}", value, check, read_image)

    sigma_t = spec.get("sigma_t", 1.0)
    if spec["type"] == "heterogeneous":
        if not is_texture(sigma_t):
            raise SceneError(f"{where}: a heterogeneous medium's sigma_t is a 'volume' texture (a "
                             f"gridvolume or constvolume), got {sigma_t!r}; a constant one is a "
                             "'homogeneous' medium")
        sigma_t = volume("sigma_t", sigma_t, _rgb)
        channels = sigma_t.texels.reshape(-1, 3)
        if np.any(channels < 0) or not np.isfinite(channels).all():
            raise SceneError(f"{where}: sigma_t: the grid's values must be finite and non-negative")
        spectral = bool(np.any(channels != channels[:, :1]))
    else:
        if is_texture(sigma_t):
            raise SceneError(f"{where}: a homogeneous medium's sigma_t is a constant; give a "
                             "volume to a 'heterogeneous' medium")
        sigma_t = tuple(_rgb(sigma_t, f"{where}: sigma_t"))
        spectral = len(set(sigma_t)) > 1
    albedo = spec.get("albedo", 0.75)
    albedo = (volume("albedo", albedo, unit_rgb) if is_texture(albedo)
              else tuple(unit_rgb(albedo, f"{where}: albedo")))
    scale = spec.get("scale", 1.0)
    if not is_real(scale) or not math.isfinite(scale) or scale < 0:
        raise SceneError(f"{where}: scale must be a non-negative number, got {scale!r}")
    peak = float(np.max(channels if spec["type"] == "heterogeneous" else sigma_t))
    if peak * scale > FLOAT32_MAX:
        raise SceneError(f"{where}: sigma_t times scale reaches {peak * scale:.3g}, beyond float32's "
                         f"largest number ({FLOAT32_MAX:.3g})")
    flags = {}
    for key in ("sample_emitters", "has_spectral_extinction"):
        flags[key] = spec.get(key, True)
        if not isinstance(flags[key], bool):
            raise SceneError(f"{where}: {key} must be true or false, got {flags[key]!r}")
    if not flags["has_spectral_extinction"] and spectral:
        raise SceneError(f"{where}: sigma_t differs between channels, but "
                         "has_spectral_extinction is false (Mitsuba then samples distances as if "
                         "the channels were equal); give one extinction or set it true")
    phase = spec.get("phase", {"type": "isotropic"})
    kind = phase.get("type") if isinstance(phase, dict) else None
    if kind not in PHASE_FUNCTIONS:
        raise SceneError(f"{where}: phase: expected {{\"type\": one of {list(PHASE_FUNCTIONS)}}}, "
                         f"got {phase!r}")
    allowed = {"type", "g"} if kind == "hg" else {"type"}
    if set(phase) - allowed:
        raise SceneError(f"{where}: phase: unknown keys {sorted(set(phase) - allowed)}; a {kind!r} "
                         f"phase function has some of {sorted(allowed)}")
    g = phase.get("g", 0.8) if kind == "hg" else 0.0
    if not is_real(g) or not -1 < g < 1:
        raise SceneError(f"{where}: phase: g must be a number in (-1, 1), got {g!r}")
    return Medium(sigma_t, albedo, float(scale), kind, float(g), id=name, type=spec["type"], **flags)


def _rgb(value, what: str) -> list[float]:
    """A colour or value per channel: one or three non-negative numbers that float32 holds
    (the kernels' precision: a larger one would render as inf or NaN)."""
    if is_real(value):
        value = [value] * 3
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(is_real(c) and math.isfinite(c) and 0 <= c <= FLOAT32_MAX for c in value)):
        raise SceneError(f"{what}: expected a non-negative number or 3 such numbers (at most "
                         f"{FLOAT32_MAX:.3g}, float32's largest), got {value!r}")
    return [float(c) for c in value]


def _vector(value, what: str) -> np.ndarray:
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(is_real(c) and math.isfinite(c) for c in value)):
        raise SceneError(f"{what}: expected 3 finite numbers, got {value!r}")
    return np.array(value, np.float64)


_LIGHT_KEYS = {"point": {"position", "intensity"}, "directional": {"direction", "irradiance"},
               "constant": {"radiance"}, "envmap": {"filename"}, "spot": {"to_world"},
               "projector": {"to_world"}}
#: Keys a light may leave out (with Mitsuba's defaults).
_LIGHT_OPTIONAL = {"envmap": {"to_world", "scale"},
                   "spot": {"intensity", "cutoff_angle", "beam_width", "texture"},
                   "projector": {"irradiance", "scale", "fov", "fov_axis"}}
_CAMERA_KEYS = {"type", "id", "to_world", "width", "height", "crop", "sample_border", "rfilter",
                "near_clip", "medium", "spp", "sampler", "seed", "jitter", "pixel_format"}
#: Keys of each camera type besides _CAMERA_KEYS.
_CAMERA_TYPE_KEYS = {"perspective": {"fov", "principal_point"},
                     "thinlens": {"fov", "aperture_radius", "focus_distance"}, "orthographic": set()}


def parse_lights(lights: Any, base: Path | None = None) -> tuple[Light, ...]:
    """Validate ``"lights"``: point, spot, directional, constant and envmap light records in
    order (an envmap's file relative to ``base``, by default the current directory)."""
    if not isinstance(lights, list):
        raise SceneError("'lights' must be a list of light objects")
    out: list[Light] = []
    for k, spec in enumerate(lights):
        where = f"lights[{k}]"
        light = parse_light(spec, where, base)
        name = getattr(light, "id", None)
        if name is not None and name in {getattr(other, "id", None) for other in out}:
            raise SceneError(f"{where}: 'id' must be a non-empty string naming one light, got {name!r}")
        if isinstance(light, ENVIRONMENTS) and any(isinstance(other, ENVIRONMENTS) for other in out):
            raise SceneError(f"{where}: only one environment ('constant' or 'envmap') per "
                             "scene, as in Mitsuba")
        out.append(light)
    return tuple(out)


def parse_light(spec: Any, where: str, base: Path | None = None,
                read: Callable[..., np.ndarray] = read_texture) -> Light:
    """One light record, its problems named by ``where``; an envmap's or a spot's texture's
    image read by ``read`` (path, raw; its file relative to ``base``, by default the current
    directory)."""
    kind = spec.get("type") if isinstance(spec, dict) else spec
    if not isinstance(kind, str) or kind not in _LIGHT_KEYS:
        raise SceneError(f"{where}: unknown light type {kind!r}; supported: "
                         f"{sorted(_LIGHT_KEYS)} (area lights are instance emitters)")
    extra = sorted(set(spec) - _LIGHT_KEYS[kind] - _LIGHT_OPTIONAL.get(kind, set()) - {"type", "id"})
    missing = sorted(_LIGHT_KEYS[kind] - set(spec))
    if extra or missing:
        raise SceneError(f"{where} ({kind}): unknown keys {extra}, missing keys {missing}")
    name = spec.get("id", where)
    if not isinstance(name, str) or not name:
        raise SceneError(f"{where}: 'id' must be a non-empty string naming one light, got {name!r}")
    if kind == "point":
        return PointLight(tuple(map(float, _vector(spec["position"], f"{where}.position"))),
                          tuple(_rgb(spec["intensity"], f"{where}.intensity")), name)
    base = Path.cwd() if base is None else base
    if kind == "spot":
        return _parse_spot(spec, where, name, _image_reader(base, read, where))
    if kind == "projector":
        return _parse_projector(spec, where, name, _image_reader(base, read, where))
    if kind == "directional":
        direction = _vector(spec["direction"], f"{where}.direction")
        largest = np.abs(direction).max()
        if largest == 0:
            raise SceneError(f"{where}.direction: zero vector")
        # Normalised after a division by its largest component: the squares of
        # [1e300, 1e300, 1e300] overflow (and those of [1e-300, ...] vanish).
        direction = direction / largest
        return DirectionalLight(tuple(map(float, direction / np.linalg.norm(direction))),
                                tuple(_rgb(spec["irradiance"], f"{where}.irradiance")), name)
    if kind == "constant":
        return ConstantLight(tuple(_rgb(spec["radiance"], f"{where}.radiance")), name)
    return dataclasses.replace(_parse_envmap(spec, where, base, read), id=name)


def _check_record(kind: str, spec: dict, where: str) -> None:
    """A ``light`` or ``medium`` record's values checked as :func:`parse_light` and
    :func:`parse_medium` check them, its images and grids not read (the scene reads them
    once, when it is parsed, and checks a grid's values then)."""
    if kind == "light":
        parse_light(spec, where, read=lambda path, raw=False: np.zeros((1, 1, 3), np.float32))
    else:
        parse_medium(where, spec, where=where, read_image=lambda filename, raw, volume=False: (
            (np.zeros((1, 1, 1, 3), np.float32), (np.zeros(3), np.ones(3))), filename))


def _image_reader(base: Path, read: Callable[..., np.ndarray], where: str):
    """A texture's file reader for ``parse_texture`` (file name, raw, whether it is a volume
    grid -> its texels or grid, the resolved path): the file relative to ``base``, an image
    read by ``read``, errors named by ``where``."""
    def read_image(filename: str, raw: bool, volume: bool = False) -> tuple[Any, str]:
        path = (base / filename).resolve()
        try:
            if volume:
                grid = read_volume_grid(path)
                return (grid.values, grid.bounds), str(path)
            return read(path, raw), str(path)
        except ImageFileError as err:
            raise SceneError(f"{where}: texture {filename!r}: {err}") from None
    return read_image


def _parse_spot(spec: dict, where: str, name: str, read_image) -> SpotLight:
    """A ``spot``: at its ``to_world``'s origin, shining along its +z; ``intensity``
    (default 1), ``cutoff_angle`` in (0, 90] degrees (default 20) and ``beam_width`` in
    (0, cutoff_angle] (default 3/4 of it), as Mitsuba's plugin; a ``texture`` (a bitmap or
    checkerboard, as Mitsuba's asks for a spatially varying one) projected onto its cone."""
    transform = parse_transform(spec["to_world"], f"{where}.to_world")
    # Only the frame's origin and +z place the spot: a scale or shear would silently change
    # its cone (and dim it).
    _rigid(transform, f"{where}.to_world")
    to_world = transform.to_numpy()[0]
    cutoff = spec.get("cutoff_angle", 20.0)
    if not is_real(cutoff) or not 0 < cutoff <= 90:
        raise SceneError(f"{where}.cutoff_angle must be a number of degrees in (0, 90], got {cutoff!r}")
    beam = spec.get("beam_width", 0.75 * cutoff)
    if not is_real(beam) or not 0 < beam <= cutoff:
        raise SceneError(f"{where}.beam_width must be a number of degrees in (0, cutoff_angle "
                         f"{cutoff}], got {beam!r}")
    texture = spec.get("texture")
    if texture is not None:
        if not is_texture(texture) or texture.get("type") not in ("bitmap", "checkerboard"):
            raise SceneError(f"{where}.texture must be a bitmap or checkerboard texture (Mitsuba's "
                             f"spot takes a spatially varying one), got {texture!r}")
        texture = parse_texture(f"{where}.texture", texture, lambda value, at: _rgb(value, at), read_image)
    return SpotLight(tuple(map(float, to_world[:3, 3])),
                     tuple(_rgb(spec.get("intensity", 1.0), f"{where}.intensity")), name,
                     tuple(np.linalg.inv(to_world[:3, :3]).ravel().tolist()), float(cutoff), float(beam),
                     texture)


def _parse_projector(spec: dict, where: str, name: str, read_image) -> ProjectorLight:
    """A ``projector``: a pinhole at its ``to_world``'s origin looking along its +z; its
    ``irradiance`` (a colour, default 1, or a bitmap or checkerboard texture), ``scale``
    (default 1) and field of view ``fov`` (degrees, default Mitsuba's for a 50 mm lens
    along the diagonal) along ``fov_axis`` (default "x") of a film shaped as the texture."""
    transform = parse_transform(spec["to_world"], f"{where}.to_world")
    _rigid(transform, f"{where}.to_world")
    to_world = transform.to_numpy()[0]
    scale = spec.get("scale", 1.0)
    if not is_real(scale) or not math.isfinite(scale) or scale < 0:
        raise SceneError(f"{where}.scale must be a non-negative number, got {scale!r}")
    irradiance, texture = spec.get("irradiance", 1.0), None
    if is_texture(irradiance):
        if irradiance.get("type") not in ("bitmap", "checkerboard"):
            raise SceneError(f"{where}.irradiance must be a colour or a bitmap or checkerboard "
                             f"texture, got {irradiance!r}")
        texture = parse_texture(f"{where}.irradiance", irradiance, lambda value, at: _rgb(value, at),
                                read_image)
        irradiance = 1.0
    aspect = 1.0 if texture is None or texture.type != "bitmap" else \
        texture.texels.shape[1] / texture.texels.shape[0]
    fov, axis = spec.get("fov", diagonal_fov(50.0)), spec.get("fov_axis", "x" if "fov" in spec else "diagonal")
    if not is_real(fov) or not math.isfinite(fov) or not isinstance(axis, str):
        raise SceneError(f"{where}: 'fov' must be a number of degrees and 'fov_axis' a name, got "
                         f"{fov!r}, {axis!r}")
    try:
        fov = fov_along_x(float(fov), axis, aspect)
    except ValueError as err:
        raise SceneError(f"{where}: {err}") from None
    intensity = _rgb([scale * c for c in _rgb(irradiance, f"{where}.irradiance")],
                     f"{where}: irradiance times scale")
    return ProjectorLight(tuple(map(float, to_world[:3, 3])), tuple(intensity), name,
                          tuple(np.linalg.inv(to_world[:3, :3]).ravel().tolist()), fov, aspect, texture)


def _parse_envmap(spec: dict, where: str, base: Path,
                  read: Callable[[Path], np.ndarray]) -> EnvironmentMap:
    """An ``envmap``: its image (linear RGB, 8-bit files sRGB-decoded, read by ``read``), a
    rotation ``to_world`` and a non-negative ``scale``."""
    filename = spec["filename"]
    if not isinstance(filename, str) or not filename:
        raise SceneError(f"{where}.filename must be a file name, got {filename!r}")
    path = (base / filename).resolve()
    try:
        texels = read(path)
    except ImageFileError as err:
        raise SceneError(f"{where}: {err}") from None
    to_world = parse_transform(spec.get("to_world", np.eye(4).tolist()), f"{where}.to_world").to_numpy()[0]
    linear = to_world[:3, :3]
    if not np.allclose(linear.T @ linear, np.eye(3), atol=1e-5):
        raise SceneError(f"{where}.to_world must be a rotation (an environment lies infinitely "
                         f"far away: no scale or shear), got {np.round(linear, 6).tolist()}")
    scale = spec.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale < 0:
        raise SceneError(f"{where}.scale must be a non-negative number, got {scale!r}")
    # Radiance: finite and non-negative, as a constant environment's; within float32 once scaled.
    bad = ~np.isfinite(texels) | (texels < 0)
    if bad.any():
        raise SceneError(f"{where}: the radiance in {path.name!r} must be finite and non-negative; "
                         f"{int(bad.sum())} texel values are not (e.g. {float(texels[bad].flat[0])})")
    if texels.size and float(texels.max()) * scale > FLOAT32_MAX:
        raise SceneError(f"{where}: the largest radiance in {path.name!r} times scale is "
                         f"{float(texels.max()) * scale:.3g}, beyond float32's largest number")
    return EnvironmentMap(str(path), texels, to_world, float(scale))


def _parse_emitter(spec: Any, where: str, read_image) -> AreaEmitter:
    """An instance's ``area`` emitter: its ``radiance``, a colour or a bitmap or checkerboard
    texture (looked up at the surface coordinates, as Mitsuba's)."""
    if not isinstance(spec, dict) or spec.get("type") != "area" or set(spec) != {"type", "radiance"}:
        raise SceneError(f"{where}: expected {{'type': 'area', 'radiance': [r, g, b] or a "
                         f"texture}}, got {spec!r}")
    radiance = spec["radiance"]
    if not is_texture(radiance):
        return AreaEmitter(tuple(_rgb(radiance, f"{where}.radiance")))
    if radiance.get("type") not in ("bitmap", "checkerboard"):
        raise SceneError(f"{where}.radiance must be a colour or a bitmap or checkerboard texture, "
                         f"got {radiance!r}")
    texture = parse_texture(f"{where}.radiance", radiance, lambda value, at: _rgb(value, at), read_image)
    return AreaEmitter((1.0, 1.0, 1.0), texture)


def parse_cameras(data: dict) -> tuple[Camera, ...]:
    """A scene's views: its ``"camera"``, or the list ``"cameras"`` (ids unique where given)."""
    if "camera" in data and "cameras" in data:
        raise SceneError("give either 'camera' or 'cameras' (a list of cameras), not both")
    if "cameras" not in data:
        if "camera" in data and data["camera"] is None:
            raise SceneError("camera: null; give a camera object, or leave the key out for a "
                             "scene without one")
        return (parse_camera(data["camera"]),) if "camera" in data else ()
    specs = data["cameras"]
    if not isinstance(specs, list) or not specs:
        raise SceneError(f"'cameras' must be a non-empty list of cameras, got {specs!r}")
    cameras = tuple(parse_camera(spec, f"cameras[{k}]") for k, spec in enumerate(specs))
    ids = [camera.id for camera in cameras if camera.id]
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise SceneError(f"cameras: ids {repeated} are given to more than one camera")
    return cameras


def parse_camera(spec: Any, where: str = "camera") -> Camera:
    """Validate a scene's ``"camera"`` entry (Mitsuba's sensor conventions) into a
    :class:`~instancing.scene.camera.Camera`: ``perspective``, ``thinlens`` or
    ``orthographic``; ``where`` names it in errors."""
    if not isinstance(spec, dict) or not isinstance(spec.get("type"), str) or spec["type"] not in CAMERAS:
        kind = spec.get("type") if isinstance(spec, dict) else spec
        raise SceneError(f"{where}: unknown camera type {kind!r}; supported: {list(CAMERAS)}")
    kind = spec["type"]
    allowed = _CAMERA_KEYS | _CAMERA_TYPE_KEYS[kind]
    extra = sorted(set(spec) - allowed)
    if extra:
        raise SceneError(f"{where}: unknown keys {extra}; a {kind!r} camera has some of "
                         f"{sorted(allowed)}")
    values: dict[str, Any] = {key: spec[key] for key in (
        "fov", "near_clip", "aperture_radius", "focus_distance", "sample_border", "id", "spp", "sampler",
        "seed", "jitter", "pixel_format")
        if key in spec}
    if kind == "thinlens" and "aperture_radius" not in spec:
        raise SceneError(f"{where}: a {kind!r} camera needs 'aperture_radius'")
    size = [integer(key, spec.get(key, 256), 1, MAX_FILM_SIZE, where) for key in ("width", "height")]
    if "crop" in spec:
        size, values["window"] = _parse_crop(spec["crop"], *size, f"{where}: crop")
    if "principal_point" in spec:
        point = spec["principal_point"]
        values["principal_point"] = tuple(point) if isinstance(point, (list, tuple)) else point
    rfilter, rfilter_size, rfilter_bc = _parse_rfilter(spec.get("rfilter", "box"), f"{where}: rfilter")
    if "medium" in spec:
        if not isinstance(spec["medium"], str) or not spec["medium"]:
            raise SceneError(f"{where}: medium must name a medium of the scene's 'media', got "
                             f"{spec['medium']!r}")
        values["medium"] = spec["medium"]
    # The values are checked by the camera itself (instancing.scene.camera), named here.
    try:
        return CAMERAS[kind](world_from_camera=parse_transform(spec.get("to_world", []), f"{where}: to_world"),
                             width=size[0], height=size[1], rfilter=rfilter, rfilter_size=rfilter_size,
                             rfilter_bc=rfilter_bc, **values)
    except SceneError as err:
        raise SceneError(f"{where}: {err}") from None


def _parse_crop(spec: Any, width: int, height: int, where: str
                ) -> tuple[list[int], tuple[float, float, float, float]]:
    """A crop window ``{"x", "y", "width", "height"}`` in pixels of the film (Mitsuba's
    ``crop_offset_x`` and ``_y``, ``crop_width`` and ``crop_height``; by default from the
    film's corner to its far side): the image size and the window in fractions of the film."""
    if not isinstance(spec, dict):
        raise SceneError(f"{where} must be a dict with some of 'x', 'y', 'width', 'height', got {spec!r}")
    unknown = sorted(set(spec) - {"x", "y", "width", "height"})
    if unknown:
        raise SceneError(f"{where}: unknown keys {unknown}; a crop has some of 'x', 'y', 'width', 'height'")
    x = integer("x", spec.get("x", 0), 0, width - 1, where)
    y = integer("y", spec.get("y", 0), 0, height - 1, where)
    w = integer("width", spec.get("width", width - x), 1, width - x, where)
    h = integer("height", spec.get("height", height - y), 1, height - y, where)
    return [w, h], (x / width, y / height, (x + w) / width, (y + h) / height)


def _parse_rfilter(spec: Any, where: str) -> tuple[str, float | None, tuple | None]:
    """A reconstruction filter: its name, or ``{"type": name, size: value}`` with the size
    Mitsuba names (the Gaussian's ``stddev``, the tent's ``radius``; pixels), or
    ``{"type": "mitchell", "B": b, "C": c}``. Returns the name, the size and a mitchell
    filter's (B, C) (None where they are Mitsuba's defaults)."""
    spec = {"type": spec} if isinstance(spec, str) else spec
    if not isinstance(spec, dict) or spec.get("type") not in RFILTERS:
        kind = spec.get("type") if isinstance(spec, dict) else spec
        raise SceneError(f"{where}: must be one of {list(RFILTERS)} (or a dict with 'type' and "
                         f"its size), got {kind!r}")
    kind = spec["type"]
    size = RFILTER_SIZES[kind]
    shape = ("B", "C") if kind == "mitchell" else ()
    unknown = sorted(set(spec) - {"type", *(size[:1] if size else ()), *shape})
    if unknown:
        raise SceneError(f"{where}: unknown keys {unknown} for {kind!r}"
                         + (f" (its size is {size[0]!r})" if size else "")
                         + (" (its parameters are 'B' and 'C')" if shape else ""))
    # (The values are checked by the camera.)
    bc = None
    if shape:
        bc = tuple(spec.get(key, default) for key, default in zip(shape, CUBIC_FILTERS[kind]))
        bc = None if bc == CUBIC_FILTERS[kind] else bc
    if size is None or size[0] not in spec:
        return kind, None, bc
    value = spec[size[0]]
    return kind, value if not is_real(value) or float(value) != size[1] else None, bc


def _rigid(transform: tf.Transform, what: str) -> None:
    """:func:`~instancing.core.transform.require_rigid`, refused as a scene problem."""
    try:
        tf.require_rigid(transform, what)
    except TransformError as err:
        raise SceneError(str(err)) from None


def _expand(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per-instance copies of per-entry indices in the smallest unsigned type; a
    read-only broadcast (no memory per instance) when all entries agree."""
    if len(values) == 0:
        return np.zeros(0, np.uint8)
    low, high = int(values.min()), int(values.max())
    values = values.astype(np.min_scalar_type(high))
    if low == high:
        return np.broadcast_to(values[:1], (int(counts.sum()),))
    return np.repeat(values, counts)


def _is_batch(value: Any) -> bool:
    return isinstance(value, (str, os.PathLike)) or (isinstance(value, np.ndarray) and value.ndim == 3)


def shaded_mesh(mesh: MeshData, face_normals: bool = False, flip_normals: bool = False,
                flip_tex_coords: bool = False, normals_to_world: np.ndarray | None = None) -> MeshData:
    """The mesh as Mitsuba shades it: with its file's vertex normals, else smooth normals
    computed as Mitsuba does (:func:`~instancing.models.mesh.vertex_normals`), for the
    vertices moved by the linear map ``normals_to_world`` (3, 3) where given (mapped back
    by its transpose, so that the instance's inverse transpose gives them again, their
    side kept); flat with ``face_normals``; inside out with ``flip_normals``; its texture
    coordinates' v replaced by 1 - v with ``flip_tex_coords`` (Mitsuba's default for OBJ
    files)."""
    if flip_tex_coords and mesh.uvs is not None:
        mesh = mesh._replace(uvs=mesh.uvs * [1.0, -1.0] + [0.0, 1.0])
    if face_normals:
        mesh = mesh.with_normals(None)
    elif mesh.normals is None and normals_to_world is not None:
        linear = np.asarray(normals_to_world, np.float64)
        moved = vertex_normals(mesh.vertices @ linear.T, mesh.faces, mesh.weld)
        mesh = mesh.with_normals(np.sign(np.linalg.det(linear)) * moved @ linear)
    elif mesh.normals is None:
        mesh = mesh.with_normals(vertex_normals(mesh.vertices, mesh.faces, mesh.weld))
    return mesh.flipped() if flip_normals else mesh


def _parse_models(models: Any, base: Path) -> list[ModelSpec]:
    if not isinstance(models, dict):
        raise SceneError(f"'models' must be an object of name -> model, got {type(models).__name__}")
    out = []
    for name, spec in models.items():
        if not isinstance(spec, dict) or not isinstance(spec.get("type"), str):
            raise SceneError(f"model {name!r}: expected an object with a 'type' name, got {spec!r}")
        kind = spec["type"]
        if kind in ANALYTIC_MODELS:
            extra = sorted(set(spec) - {"type", "flip_normals"})
            if extra:
                raise SceneError(f"model {name!r}: unsupported keys {extra} for type {kind!r} "
                                 "(place and size it with the instance's to_world; 'flip_normals' "
                                 "turns its normals inward)")
            flipped = spec.get("flip_normals", False)
            if not isinstance(flipped, bool):
                raise SceneError(f"model {name!r}: 'flip_normals' must be true or false, got {flipped!r}")
            out.append(ModelSpec(name, kind, flipped=flipped))
        elif kind in MESH_FILE_TYPES:
            allowed = _MESH_MODEL_KEYS if kind == "serialized" else _MESH_MODEL_KEYS - {"shape_index"}
            extra = sorted(set(spec) - allowed)
            if extra:
                raise SceneError(f"model {name!r}: unknown keys {extra} for type {kind!r}; "
                                 f"expected some of {sorted(allowed)}")
            if "filename" not in spec:
                raise SceneError(f"model {name!r}: type {kind!r} needs a 'filename'")
            if not isinstance(spec["filename"], str):
                raise SceneError(f"model {name!r}: 'filename' must be a string (the mesh file's "
                                 f"path), got {spec['filename']!r}")
            path = (base / spec["filename"]).resolve()
            if path.suffix.lower() != "." + kind:
                raise SceneError(f"model {name!r}: type {kind!r} but file {str(path)!r} "
                                 f"has extension {path.suffix!r}")
            flags = {}
            for flag in ("face_normals", "flip_normals", "flip_tex_coords"):
                flags[flag] = spec.get(flag, _FLIP_TEX_COORDS[kind] if flag == "flip_tex_coords"
                                       else False)
                if not isinstance(flags[flag], bool):
                    raise SceneError(f"model {name!r}: {flag!r} must be true or false, "
                                     f"got {flags[flag]!r}")
            shape_index = integer("'shape_index'", spec.get("shape_index", 0), 0,
                                  where=f"model {name!r}")
            if "computed_normals_to_world" in spec:
                flags["normals_to_world"] = parse_transform(
                    spec["computed_normals_to_world"],
                    f"model {name!r}: computed_normals_to_world").to_numpy()[0][:3, :3]
            out.append(ModelSpec(name, kind, shaded_mesh(read_mesh(path, shape_index), **flags), path,
                                 flipped=flags["flip_normals"]))
        elif kind == GRID_KIND:
            out.append(_parse_grid_model(name, spec, base))
        elif kind in _CURVE_DATA:
            out.append(_parse_curve_model(name, kind, spec, base))
        else:
            raise SceneError(f"model {name!r}: unknown model type {kind!r}; supported types are "
                             f"{sorted(ANALYTIC_MODELS) + list(MESH_FILE_TYPES) + [GRID_KIND, *_CURVE_DATA]}")
    return out


def _file_or_data(name: str, spec: dict, kind: str, keys: frozenset, data_key: str,
                  file_what: str, data_what: str) -> Path | None:
    """The checks a model read from a file or given as data shares: no unknown key, exactly
    one of ``filename`` and ``data_key``; the file's resolved path, or None for data."""
    where = f"model {name!r}"
    extra = sorted(set(spec) - keys)
    if extra:
        raise SceneError(f"{where}: unknown keys {extra} for type {kind!r}; expected some of {sorted(keys)}")
    if ("filename" in spec) == (data_key in spec):
        raise SceneError(f"{where}: type {kind!r} needs either a 'filename' ({file_what}) or "
                         f"{data_key!r} ({data_what}), not both")
    if data_key in spec:
        return None
    if not isinstance(spec["filename"], str):
        raise SceneError(f"{where}: 'filename' must be a string ({file_what}'s path), got "
                         f"{spec['filename']!r}")
    return Path(spec["filename"])


def _numeric_array(value: Any, what: str) -> np.ndarray:
    """``value`` as an array of numbers (strings, booleans, ragged lists refused by name)."""
    try:
        array = np.asarray(value)
    except ValueError:
        array = np.asarray(None)
    if array.dtype.kind not in "iuf":
        raise SceneError(f"{what} must be an array of numbers, got {type(value).__name__} of dtype "
                         f"{array.dtype}")
    return array


def _parse_curve_model(name: str, kind: str, spec: dict, base: Path) -> ModelSpec:
    """Linear or B-spline curves (``kind``): from a Mitsuba curve file (``filename``) or given
    as a list of (n, 4) arrays of rows x, y, z, radius (``curves``), their control points
    moved by ``points_to_world`` (default: the identity; radii kept, as Mitsuba's plain
    curve's ``to_world``); see :mod:`instancing.models.linear_curve` and
    :mod:`instancing.models.bspline_curve`."""
    where = f"model {name!r}"
    data = _CURVE_DATA[kind]
    path = _file_or_data(name, spec, kind, _CURVE_MODEL_KEYS, "curves", "a curve file",
                         "a list of arrays of rows x, y, z, radius")
    if path is None:
        curves = spec["curves"]
        if not isinstance(curves, (list, tuple)):
            raise SceneError(f"{where}: 'curves' must be a list of arrays of rows x, y, z, radius, "
                             f"got {type(curves).__name__}")
        curve = data.from_curves(
            [_numeric_array(c, f"{where}: curves[{k}]") for k, c in enumerate(curves)], where)
    else:
        path = (base / path).resolve()
        curve = read_curve_file(path, where, data)
    points_to_world = None
    if "points_to_world" in spec:
        points_to_world = parse_transform(spec["points_to_world"], f"{where}: points_to_world").to_numpy()[0]
        curve = curve.moved(points_to_world, where)
    return ModelSpec(name, kind, filename=path, curve=curve, points_to_world=points_to_world)


def _parse_grid_model(name: str, spec: dict, base: Path) -> ModelSpec:
    """An SDF grid: its values from a one-channel volume grid file (``filename``) or given
    as a (z, y, x) array (``values``), and its shading ``normals`` ('smooth', the default,
    or 'analytic'; see :mod:`instancing.models.sdf_grid`)."""
    where = f"model {name!r}"
    path = _file_or_data(name, spec, GRID_KIND, _GRID_MODEL_KEYS, "values", "a volume grid file",
                         "a z, y, x array")
    normals = spec.get("normals", "smooth")
    if normals not in NORMAL_MODES:
        raise SceneError(f"{where}: 'normals' must be one of {list(NORMAL_MODES)}, got {normals!r}")
    if path is None:
        values = _numeric_array(spec["values"], f"{where}: 'values'")
        if values.ndim != 3:
            raise SceneError(f"{where}: 'values' must be a (z, y, x) array, got shape {values.shape}")
    else:
        path = (base / path).resolve()
        try:
            grid = read_volume_grid(path)
        except ImageFileError as err:
            raise SceneError(f"{where}: {err}") from None
        if grid.values.shape[-1] != 1:
            raise SceneError(f"{where}: volume grid file '{path}' has {grid.values.shape[-1]} "
                             "channels; an SDF grid reads 1")
        values = grid.values[..., 0]
    return ModelSpec(name, GRID_KIND, filename=path,
                     grid=SDFGridData.checked(values, normals == "smooth", where))


def _parse_materials(materials: Any, base: Path) -> dict[str, Material]:
    if not isinstance(materials, dict):
        raise SceneError("'materials' must be an object of name -> material")
    return {name: parse_material(name, spec, _image_reader(base, read_texture, f"material {name!r}"))
            for name, spec in materials.items()}


def _instance_where(k: int, inst: Any) -> str:
    """How errors name instance entry ``k``: "instance #k ('id')"."""
    return f"instance #{k}" + (f" ({inst.get('id')!r})" if isinstance(inst, dict) and "id" in inst else "")


def _is_matrix(value: Any) -> bool:
    """Whether an instance's ``to_world`` looks like one 4x4 matrix (a list of four lists, or
    a 4x4 array); the batch check in :func:`_plain_entries` checks the rest."""
    return ((type(value) is list and len(value) == 4 and type(value[0]) is list)
            or (type(value) is np.ndarray and value.shape == (4, 4)))


def _is_transform(value: Any) -> bool:
    """Whether an instance's ``to_world`` looks like one transform: a 4x4 matrix or a
    non-empty list of operations (objects)."""
    return _is_matrix(value) or (type(value) is list and len(value) > 0 and type(value[0]) is dict)


class _Entry(NamedTuple):
    """One instance entry parsed on its own: model and material index, its instances'
    matrices and inverses ((n, 4, 4) each), its id (None: named by index), whether it is a
    batch (ids ``name[k]``), and its emitter or None."""
    model: int
    material: int
    to_world: np.ndarray
    from_world: np.ndarray
    name: str | None
    batch: bool
    emitter: AreaEmitter | None
    media: tuple[str, str]


def _parse_instances(instances: list, models: list[ModelSpec], materials: dict[str, Material],
                     base: Path, media: dict[str, Medium]
                     ) -> tuple[InstanceIds, np.ndarray, np.ndarray, InstanceMatrices,
                                dict[int, AreaEmitter], dict[int, tuple[str, str]]]:
    """The instances' ids, model and material indices (per instance, see :func:`_expand`),
    float64 matrices, emitters and (interior, exterior) media (by instance index).

    Plain entries (at most an id, a model, a material and one transform, a 4x4 matrix or a
    list of operations: what a large scene is made of) are read field by field over all of
    them and their matrices built, checked and inverted as batches; the others are parsed one by one. When a batch check fails,
    every entry is parsed one by one, so that the error names the first culprit."""
    model_index = {m.name: i for i, m in enumerate(models)}
    named = [inst.get("model") if type(inst) is dict else None for inst in instances]
    for name in dict.fromkeys(n for n in named if type(n) is str):
        if name not in model_index and name in ANALYTIC_MODELS:
            # A built-in analytic type may be used without declaring it.
            model_index[name] = len(models)
            models.append(ModelSpec(name, name))
    material_index = {m: i for i, m in enumerate(materials)}
    plain = [type(inst) is dict and _PLAIN_KEYS.issuperset(inst) and _is_transform(inst.get("to_world"))
             for inst in instances]
    rows = [k for k, p in enumerate(plain) if p]
    columns = (_plain_entries([instances[k] for k in rows], [named[k] for k in rows], model_index,
                              material_index) if rows else None)
    if columns is None:
        rows = []
    rest = {k: _parse_entry(k, instances[k], model_index, material_index, base, media)
            for k in range(len(instances)) if columns is None or not plain[k]}

    # Instances per entry, in scene order.
    counts = np.ones(len(instances), np.int64)
    for k, entry in rest.items():
        counts[k] = len(entry.to_world)
    starts = np.cumsum(counts) - counts
    total = int(counts.sum())
    model_of, material_of = np.empty(len(instances), np.int64), np.empty(len(instances), np.int64)
    fwd, inv = np.empty((total, 4, 4)), np.empty((total, 4, 4))
    names: dict[int, tuple[str, bool]] = {}
    if rows:
        model_of[rows], material_of[rows] = columns.model, columns.material
        fwd[starts[rows]], inv[starts[rows]] = columns.to_world, columns.from_world
        names = {rows[j]: (name, False) for j, name in columns.names.items()}
    emitters, instance_media = {}, {}
    for k, entry in rest.items():
        model_of[k], material_of[k] = entry.model, entry.material
        start, n = int(starts[k]), len(entry.to_world)
        fwd[start:start + n], inv[start:start + n] = entry.to_world, entry.from_world
        if entry.name is not None or entry.batch:
            names[k] = (str(start) if entry.name is None else entry.name, entry.batch)
        if entry.emitter is not None:
            if models[entry.model].kind in (GRID_KIND, *_CURVE_DATA):
                raise SceneError(f"{_instance_where(k, instances[k])}: model "
                                 f"{models[entry.model].name!r} is an {models[entry.model].kind}, "
                                 "which cannot emit light (as in Mitsuba)")
            emitters.update(dict.fromkeys(range(start, start + n), entry.emitter))
        if any(entry.media):
            instance_media.update(dict.fromkeys(range(start, start + n), entry.media))

    # Ids in scene order: the named entries, and the runs of unnamed ones between them.
    ids, done = InstanceIds(), 0
    for k in sorted(names):
        if starts[k] > done:
            ids.add_unnamed(int(starts[k]) - done)
        name, batch = names[k]
        ids.add(name, int(counts[k]) if batch else None)
        done = int(starts[k] + counts[k])
    if total > done:
        ids.add_unnamed(total - done)
    # The entries parsed one by one (operation lists) are not checked for float32's range yet
    # (the plain ones were, as a batch).
    unchecked = np.ones(total, bool)
    unchecked[starts[rows]] = False
    where = np.flatnonzero(unchecked)
    bad, message = tf.float32_misfit(fwd[where], inv[where, :3, :3])
    if bad.any():
        i = int(where[np.argmax(bad)])
        raise SceneError(f"instance #{i} ({ids[i]!r}): to_world {message}")
    return (ids, _expand(model_of, counts), _expand(material_of, counts),
            InstanceMatrices(fwd, inv), emitters, instance_media)


class _Columns(NamedTuple):
    """Plain entries read as columns: model and material index per entry, matrices and
    inverses (n, 4, 4), and the ids given (entry -> name)."""
    model: list[int]
    material: list[int]
    to_world: np.ndarray
    from_world: np.ndarray
    names: dict[int, str]


def _plain_entries(entries: list[dict], models: list, model_index: dict[str, int],
                   material_index: dict[str, int]) -> _Columns | None:
    """The plain entries' columns (``models``: their model names as given), or None when one
    of them is malformed (its entry-by-entry parse then names it)."""
    try:  # (an unhashable name raises TypeError; one not found gives None)
        model = list(map(model_index.get, models))
        material = list(map(material_index.get, [inst.get("material", "default")
                                                 for inst in entries]))
    except TypeError:
        return None
    if None in model or None in material:
        return None
    names = {j: inst["id"] for j, inst in enumerate(entries) if "id" in inst}
    if not all(type(name) is str and name for name in names.values()):
        return None
    matrices = [inst["to_world"] for inst in entries]
    if not all(map(_is_matrix, matrices)):
        try:
            batch, inverse = parse_transforms(matrices, lambda k: "to_world")
        except SceneError:
            return None
        return None if tf.float32_misfit(batch, inverse[:, :3, :3])[0].any() else \
            _Columns(model, material, batch, inverse, names)
    try:
        batch = np.array(matrices)
        if batch.dtype.kind not in "iuf" or batch.shape != (len(entries), 4, 4) \
                or not _numbers_only(matrices):
            return None
        batch = batch.astype(np.float64)
        inverse = tf.checked_affine_inverse(batch)
    except (TransformError, ValueError):
        return None
    return _Columns(model, material, batch, inverse, names)


def _numbers_only(matrices: list) -> bool:
    """Whether the 4x4 matrices (nested lists or arrays, as NumPy stacked them into numbers)
    hold no booleans, which NumPy turns into 1 and 0 alongside numbers."""
    rows = [m for m in matrices if type(m) is list]
    types = set(map(type, itertools.chain.from_iterable(itertools.chain.from_iterable(rows))))
    return (not any(issubclass(t, (bool, np.bool_)) for t in types)
            and all(m.dtype.kind != "b" for m in matrices if type(m) is np.ndarray))


def _parse_entry(k: int, inst: Any, model_index: dict[str, int], material_index: dict[str, int],
                 base: Path, media: dict[str, Medium]) -> _Entry:
    """Instance entry ``k`` parsed on its own.

    Raises:
        SceneError: naming the entry and what is wrong with it.
    """
    where = _instance_where(k, inst)
    if not isinstance(inst, dict):
        raise SceneError(f"{where}: expected an object, got {inst!r}")
    if not _INSTANCE_KEYS.issuperset(inst):
        extra = sorted(set(inst) - _INSTANCE_KEYS)
        raise SceneError(f"{where}: unknown keys {extra}; expected some of {sorted(_INSTANCE_KEYS)}")
    name = inst.get("model")
    if not isinstance(name, str) or name not in model_index:
        raise SceneError(f"{where}: unknown model {name!r}; defined models are "
                         f"{sorted(model_index)}")
    material = inst.get("material", "default")
    if not isinstance(material, str) or material not in material_index:
        raise SceneError(f"{where}: unknown material {material!r}; defined materials are "
                         f"{sorted(material_index)}")
    instance_id = inst.get("id")
    if "id" in inst and (not isinstance(instance_id, str) or not instance_id):
        raise SceneError(f"{where}: 'id' must be a non-empty string, got {instance_id!r}")
    value = inst.get("to_world")
    if "to_world" in inst and value is None:
        raise SceneError(f"{where}: to_world is null; give a transform, or leave the key out for "
                         "the identity")
    fwd, inv = _parse_instance_transform(value, where, base)
    emitter = (_parse_emitter(inst["emitter"], f"{where}: emitter",
                              _image_reader(base, read_texture, f"{where}: emitter"))
               if "emitter" in inst else None)
    sides = []
    for side in ("interior", "exterior"):
        medium = inst.get(side, "")
        if side in inst and (not isinstance(medium, str) or medium not in media):
            raise SceneError(f"{where}: unknown {side} medium {medium!r}; defined media are "
                             f"{sorted(media)}")
        sides.append(medium)
    return _Entry(model_index[name], material_index[material], fwd, inv, instance_id,
                  _is_batch(value), emitter, (sides[0], sides[1]))


def _parse_instance_transform(value: Any, where: str, base: Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) world_from_object matrices and their inverses for one instance entry."""
    if value is None:
        return np.eye(4)[None], np.eye(4)[None]
    if isinstance(value, (str, os.PathLike)) or isinstance(value, np.ndarray) and value.ndim == 3:
        matrices = _load_matrix_file(value, where, base) if not isinstance(value, np.ndarray) else value
        if matrices.ndim != 3 or matrices.shape[1:] != (4, 4) or len(matrices) == 0:
            raise SceneError(f"{where}: to_world array must have shape (N, 4, 4), got {matrices.shape}")
        require_numbers(matrices, f"{where}: to_world")
        require_memory(len(matrices) * PEAK_BYTES_PER_INSTANCE, f"{where}: {len(matrices)} instances")
        matrices = matrices.astype(np.float64)
        try:
            inverse = tf.checked_affine_inverse(matrices, f"{where}: to_world matrix")
        except TransformError as err:
            raise SceneError(str(err)) from None
        return matrices, inverse
    transform = parse_transform(value, f"{where}: to_world")
    fwd, inv = transform.to_numpy()
    return fwd[None], inv[None]


def _load_matrix_file(value: Any, where: str, base: Path) -> np.ndarray:
    path = (base / value).resolve()
    if not path.is_file():
        raise SceneError(f"{where}: to_world file not found: {path}")
    try:
        # The header first: a file of more matrices than memory holds is refused unread.
        header = np.load(path, mmap_mode="r", allow_pickle=False)
        if not isinstance(header, np.ndarray):  # (an .npz archive of several arrays)
            raise ValueError("it holds several arrays; save the (N, 4, 4) matrices with numpy.save")
        count = len(header)
        require_memory(count * PEAK_BYTES_PER_INSTANCE, f"{where}: the {count} instances in {path}")
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, TypeError) as err:
        raise SceneError(f"{where}: cannot read {path} as a .npy array of matrices: {err}") from None


def write_scene_with_transforms(source: str | os.PathLike | dict, to_world: np.ndarray,
                                path: str | os.PathLike, materials: dict | None = None) -> None:
    """Write ``source`` as a JSON scene at ``path`` with every instance moved to ``to_world``
    (and material parameters changed).

    Args:
        source: the scene (file or dict) whose structure, models, materials,
            camera and lights are kept.
        to_world: (N, 4, 4) matrices, one per flattened instance of ``source``.
        path: the .json file to write; relative file names (meshes, textures, .npy
            instance sets) are rewritten relative to its folder. An instance
            set whose transforms changed is written next to it as
            ``<name>_<entry>.npy``.
        materials: material name -> {parameter: new value}: a constant, or for a
            parameter given by a bitmap the file name of its new image (relative to
            ``path``'s folder), or None to drop the key; a dict under a blend's or mask's
            BSDF key holds that BSDF's. A ``twosided`` material's front BSDF (its only one,
            or the first) takes them, and a ``normalmap``'s or ``bumpmap``'s BSDF all but its
            texture's (under ``normalmap``, ``bumpmap``).
    """
    data, base = read_scene_source(source)
    data = json.loads(json.dumps(data, default=_json_default))
    path = Path(path)
    out_dir = path.parent.resolve()

    def moved(name: str) -> str:
        return os.path.relpath((base / name).resolve(), out_dir)

    for model in data.get("models", {}).values():
        if isinstance(model, dict) and "filename" in model:
            model["filename"] = moved(model["filename"])

    def move_textures(spec: Any) -> None:
        """Bitmap textures' file names, at any depth of a material (twosided)."""
        if isinstance(spec, dict):
            if spec.get("type") == "bitmap" and isinstance(spec.get("filename"), str):
                spec["filename"] = moved(spec["filename"])
            for value in spec.values():
                move_textures(value)

    move_textures(data.get("materials", {}))
    def apply(spec: dict, changes: dict) -> None:
        """Set ``changes`` in a material dict (a twosided one's front, a normal map's
        BSDF but for its texture's changes; a dict of changes under a nested BSDF's or a
        texture's key: that BSDF's or texture's)."""
        while spec.get("type") in ("twosided", "normalmap", "bumpmap"):
            if spec["type"] == "twosided":
                spec = next(value for key, value in spec.items() if isinstance(value, dict))
            elif spec["type"] == "normalmap":
                put(spec, {key: value for key, value in changes.items() if key == "normalmap"})
                changes = {key: value for key, value in changes.items() if key != "normalmap"}
                spec = next(value for key, value in spec.items()
                            if key != "normalmap" and isinstance(value, dict))
            else:  # a bump map: its heights' new image; the rest its BSDF's
                if "bumpmap" in changes:
                    next(value for value in spec.values()
                         if is_texture_spec(value))["filename"] = changes["bumpmap"]
                changes = {key: value for key, value in changes.items() if key != "bumpmap"}
                spec = next(value for value in spec.values()
                            if isinstance(value, dict) and not is_texture_spec(value))
        put(spec, changes)

    def put(spec: dict, changes: dict) -> None:
        for key, value in changes.items():
            if value is None:
                spec.pop(key, None)
            elif isinstance(value, dict):  # a blend's or mask's BSDF, a checkerboard's colours
                apply(spec[key], value)
            elif isinstance(spec.get(key), dict):  # a bitmap: its new image
                spec[key]["filename"] = value
            else:
                spec[key] = list(value) if isinstance(value, tuple) else value

    for name, changes in (materials or {}).items():
        apply(data["materials"][name], changes)
    to_world = np.asarray(to_world, np.float64)
    first = 0
    for k, inst in enumerate(data["instances"]):
        fwd, _ = _parse_instance_transform(inst.get("to_world"), f"instance #{k}", base)
        n = len(fwd)
        new = to_world[first:first + n]
        first += n
        # Unchanged: the file's matrices, or their float32 rounding (a built scene's transforms).
        if np.array_equal(new, fwd) or np.array_equal(new, fwd.astype(np.float32)):
            if _is_batch(inst.get("to_world")):
                inst["to_world"] = moved(inst["to_world"])
            continue
        if _is_batch(inst.get("to_world")):
            name = f"{path.stem}_{k}.npy"
            with replaced(out_dir / name) as partial:
                np.save(partial, new.astype(np.float32))
            inst["to_world"] = name
        else:
            inst["to_world"] = [{"matrix": new[0].tolist()}]
    if first != len(to_world):
        raise SceneError(f"write_scene_with_transforms: {len(to_world)} matrices for {first} instances")
    with replaced(path) as partial:
        Path(partial).write_text(json.dumps(data, indent=1) + "\n")


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"not JSON serialisable: {value!r}")


def load_scene(source: str | os.PathLike | dict, accel: Accel = "auto",
               base_dir: str | os.PathLike | None = None, **parameters: Any) -> Scene:
    """Load a scene from a JSON file path or an equivalent Python dict.

    Args:
        source: path to a ``.json`` scene, or a dict in the same format
            (see :mod:`instancing.io.scene_file` and the README).
        accel: top-level acceleration: 'auto' ('unrolled' for at most
            UNROLL_MAX_INSTANCES instances, else the grid unless clustered; on the
            CUDA backend the BVH),
            'grid', 'bvh', 'unrolled' (every instance in a loop unrolled at trace
            time, behind a test of its world box; at most UNROLL_LIMIT instances),
            or 'brute' (test every instance in a loop; for validation).
        base_dir: the folder that relative file names (meshes, .npy instance sets) in a
            dict scene resolve against; default the current directory. (A scene file's
            names resolve against its own folder.)
        **parameters: ``$name`` values of a Mitsuba XML scene, overriding its
            ``<default>`` s, as ``mitsuba.load_file(path, spp=..., res=...)``.

    Raises:
        TypeError: ``source`` is neither a dict nor a path.
        SceneError: malformed scene, unknown type/model/material name, bad transform.
        MeshFileError: missing or malformed mesh file.
    """
    scene = Scene(parse_scene(source, base_dir, parameters), accel)
    _return_freed_memory()
    return scene


def _return_freed_memory() -> None:
    """Hand the freed parsing and build temporaries back to the operating system.

    glibc keeps freed heap blocks resident below its adaptive mmap threshold
    (up to 32 MiB), where the build's per-instance temporaries (bounds, grid
    references, float64 matrices) land once a first large block has been
    freed: at 1e6 instances that was ~135 bytes per instance of resident but
    free memory, more than the scene itself holds (benchmarks/scale.py).
    ``malloc_trim`` releases it; a no-op where the C library lacks it.
    """
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (AttributeError, OSError):
        pass
