"""``instancing.traverse``: the differentiable parameters of a scene.

In the spirit of ``mitsuba.traverse``: a mutable mapping from names to Dr.Jit
values, with ``update()`` pushing changes into the scene. Keys:

* ``"<instance id>.translation"`` (``Array3f``), ``"<instance id>.rotation"``
  (``Array4f``, a quaternion (x, y, z, w), normalized where it is used, so an
  optimiser step can never leave the rotation group), ``"<instance id>.scale"``
  (``Array3f``, per axis; a reflection is a negative z scale), and
  ``"<instance id>.to_world"`` (``Matrix4f``, the whole affine matrix, for
  shear);
* ``"<material>.<parameter>"`` for the parameters Mitsuba's plugin reads per lookup and
  marks differentiable (:attr:`instancing.materials.parameter.Parameter.differentiable`:
  colours as ``Array3f``, ``alpha`` as ``Float``), given as constants, e.g.
  ``"red.reflectance"``, ``"gold.alpha"``, ``"gold.eta"``; where a ``bitmap`` gives one,
  ``"<material>.<parameter>.data"``, its linear texels as a ``TensorXf`` (H, W, 3). A
  ``twosided`` material with one BSDF has that BSDF's keys (both sides change together);
  one with two BSDFs, its front's;
* ``"<light id>.position"`` and ``".intensity"`` of point and spot lights, ``".direction"`` (the
  direction the light travels, normalized where it is used) and ``".irradiance"`` of
  directional lights (``Array3f``); a light's id is its scene file ``"id"``, by default
  ``"lights[k]"``.

An instance's ``to_world`` is split by :func:`instancing.core.transform.decompose`
into ``translate(t) @ rotate_quaternion(q) @ scale(s) @ H`` (H: the shear,
fixed unless ``to_world`` itself is set) the first time one of its
parameters is read or set. ``update()`` is two halves: ``install()`` (host)
stores the changed instances' float64 state, rounded once, detached (every
other instance keeps the scene's stored matrices bit for bit) and rebuilds
world bounds and the acceleration structure from it; ``attach()`` (Dr.Jit
only, so an optimisation step can be recorded, :mod:`instancing.ad.optimisation`)
adds the derivatives: transforms with derivatives are rebuilt per lane from
the parts, their inverse from the parts' inverses in reverse order (or, for a
grad-enabled ``to_world``, from ``dr.rcp`` of the matrix), and only their
derivatives are added to the stored values, so gradients reach the parameters
through the inverse matrix that the intersection uses.

State is kept per touched instance only: a scene with a million instances
costs nothing per instance here until its parameters are read or set (values
are created lazily, and the float64 matrices of untouched instances are the
scene's own).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, MutableMapping
from typing import Any

import numpy as np

from ..core.backend import (Array3f, Array4f, Bool, Float, Matrix4f, TensorXf, UInt32,
                            device_array, device_arrays, dr)
from ..core.errors import SceneError, TransformError
from ..core.transform import (Transform, affine_inverse, check_affine_matrix, decompose,
                              quaternion_rows, rotate_quaternion, scale, translate)
from ..materials.parameter import COLOR, NUMBER
from ..scene.description import DirectionalLight, PointLight, SpotLight

#: The kind of a material parameter given by a bitmap: its texels.
TEXELS = "texels"
#: Per-instance parameter names, in key order.
INSTANCE_PARAMETERS = ("translation", "rotation", "scale", "to_world")
#: Where each part sits in an instance's parts [t, q, s, H].
PART_INDEX = {"translation": 0, "rotation": 1, "scale": 2}
#: Light parameter names per light kind: (the vector kernels read, its power).
LIGHT_PARAMETERS = {PointLight: ("position", "intensity"), SpotLight: ("position", "intensity"),
                    DirectionalLight: ("direction", "irradiance")}


class SceneParameters(MutableMapping):
    """Differentiable parameters of a scene (see the module docstring)."""

    def __init__(self, scene):
        self.scene = scene
        self._ids = scene.instance_ids
        # Material parameters by key: (material index, parameter, kind: a colour, a number
        # or a bitmap's texels).
        self._material_keys = _material_keys(scene)
        # Per touched instance: its float64 matrix and its parts [t, q, s, H].
        self._matrix: dict[int, np.ndarray] = {}
        self._parts: dict[int, list[np.ndarray]] = {}
        self._values: dict[str, Any] = {}
        self._dirty: set[str] = set()
        # Point and directional lights by id: their index in scene.lights.
        self._lights = {light.id: i for i, light in enumerate(scene.lights)
                        if type(light) in LIGHT_PARAMETERS}

    def _touch(self, i: int) -> list[np.ndarray]:
        """The parts of instance ``i``, split from the scene's matrix on first use."""
        if i not in self._parts:
            self._matrix[i] = self.scene.instances.to_world_of(i)
            self._parts[i] = list(decompose(self._matrix[i]))
        return self._parts[i]

    # -- mapping interface ---------------------------------------------------------------------

    def _split(self, key: str) -> tuple[str, str]:
        if not isinstance(key, str) or "." not in key:
            raise KeyError(key)
        owner, name = key.rsplit(".", 1)
        if name in INSTANCE_PARAMETERS and owner in self._ids:
            return "instance", name
        if key in self._material_keys:
            return "material", name
        if owner in self._lights and name in LIGHT_PARAMETERS[type(self._light(owner))]:
            return "light", name
        raise KeyError(key)

    def material_parameter(self, key: str) -> tuple[str, str]:
        """(material name, parameter name) of material parameter ``key``."""
        if key not in self._material_keys:
            raise KeyError(key)
        i, name, _ = self._material_keys[key]
        return self.scene.material_names[i], name

    def kind(self, key: str) -> str:
        """What parameter ``key`` belongs to: ``"instance"``, ``"material"`` or ``"light"``
        (KeyError for an unknown key)."""
        return self._split(key)[0]

    def _light(self, owner: str) -> Any:
        return self.scene.lights[self._lights[owner]]

    def __getitem__(self, key: str) -> Any:
        if key not in self._values:
            kind, name = self._split(key)
            owner = key.rsplit(".", 1)[0]
            self._values[key] = self._initial_value(kind, name, owner)
        return self._values[key]

    def _initial_value(self, kind: str, name: str, owner: str) -> Any:
        if kind == "material":
            i, parameter, form = self._material_keys[f"{owner}.{name}"]
            table = self.scene.bsdfs
            if form == TEXELS:
                return TensorXf(table.textures.texels_of(table.texture(i, parameter)))
            value = table.rows[i].values[parameter]
            return Array3f(*value) if form == COLOR else Float(value)
        if kind == "light":
            return Array3f(*getattr(self._light(owner), name))
        i = self._ids.index(owner)
        translation, rotation, scale_, _ = self._touch(i)
        if name == "translation":
            return Array3f(*translation.tolist())
        if name == "rotation":
            return Array4f(*rotation.tolist())
        if name == "scale":
            return Array3f(*scale_.tolist())
        return Matrix4f(self._matrix[i].tolist())

    def __setitem__(self, key: str, value: Any) -> None:
        kind, name = self._split(key)
        expected = {"rotation": Array4f, "to_world": Matrix4f}.get(name, Array3f)
        if kind == "material":
            expected = {COLOR: Array3f, NUMBER: Float, TEXELS: TensorXf}[self._material_keys[key][2]]
        try:
            value = value if isinstance(value, expected) else expected(value)
        except (TypeError, RuntimeError) as exc:
            raise SceneError(f"parameter {key!r}: cannot convert {value!r} to "
                             f"{expected.__name__} ({exc})") from None
        if expected is TensorXf:
            shape = tuple(self[key].shape)
            if tuple(value.shape) != shape:
                raise SceneError(f"parameter {key!r}: expected texels of shape {shape}, got "
                                 f"{tuple(value.shape)}")
        elif dr.width(value) != 1:
            raise SceneError(f"parameter {key!r}: expected one value, got width {dr.width(value)}")
        self._values[key] = value
        self._dirty.add(key)

    def __delitem__(self, key: str) -> None:
        raise TypeError("scene parameters cannot be removed")

    def __iter__(self) -> Iterator[str]:
        for name in self._ids:
            for p in INSTANCE_PARAMETERS:
                yield f"{name}.{p}"
        yield from self._material_keys
        for owner in self._lights:
            for name in LIGHT_PARAMETERS[type(self._light(owner))]:
                yield f"{owner}.{name}"

    def __len__(self) -> int:
        return (len(self._ids) * len(INSTANCE_PARAMETERS) + len(self._material_keys)
                + 2 * len(self._lights))

    def __repr__(self) -> str:
        return (f"SceneParameters({len(self._ids)} instances, "
                f"{len(self.scene.material_names)} materials)")

    # -- update --------------------------------------------------------------------------------

    def update(self, values: Any = None) -> "SceneParameters":
        """Push changed and grad-enabled parameters into the scene.

        Args:
            values: optionally a mapping (e.g. a ``drjit.opt`` optimiser) whose
                entries are first assigned to the matching keys.

        Call it after every change and after every optimiser step: it also
        re-attaches the AD graph that ``dr.backward`` consumed. It is
        :meth:`install` (host work) followed by :meth:`attach` (Dr.Jit work only).

        Raises:
            SceneError: a non-finite or singular transform, a zero scale or
                quaternion, or ``to_world`` set together with its parts.
        """
        return self.attach(self.install(values))

    def install(self, values: Any = None) -> "Attachment":
        """The host half of :meth:`update`: assign ``values``, check the changed
        parameters, and install the changed instances' float64 state in the scene,
        detached (their world boxes, remap bounds and grid references follow).
        Returns what :meth:`attach` needs, as Dr.Jit arrays made here."""
        if values is not None:
            for key in values.keys():
                if key in self:
                    self[key] = values[key]
        changed = self._absorb_changes()
        self._dirty.clear()
        parts = {name: self._grad_instances(name) for name in INSTANCE_PARAMETERS}
        moving = sorted(set().union(*parts.values()))
        touched = sorted(changed)
        if touched:
            # The changed instances' float64 state rounded once (with its float64 inverse),
            # one lane each: only their rows are written, checked, bounded and re-filed.
            state = np.array([self._matrix[i] for i in touched])
            self.scene.set_transforms(Transform(_owned_lanes(Matrix4f, state),
                                                _owned_lanes(Matrix4f, affine_inverse(state))),
                                      matrices=state, moving=np.array(moving, np.int64),
                                      changed=np.array(touched, np.int64))
        else:
            self.scene.set_moving(np.array(moving, np.int64))
        lights = sorted({self._lights[key.rsplit(".", 1)[0]] for key in self.grad_enabled_keys()
                         if self._split(key)[0] == "light"})
        self.scene.set_moving_lights(np.array(lights, np.int64))
        return Attachment(self, moving, parts, lights)

    def attach(self, attachment: "Attachment", values: Any = None) -> "SceneParameters":
        """The Dr.Jit half of :meth:`update`: the grad-enabled parameters (read from
        ``values``, default this mapping) attached to the installed transforms and
        reflectances. Values stay those :meth:`install` stored; derivatives come from
        the parameters. Reads only Dr.Jit arrays, so it can run inside a recording
        (:mod:`instancing.ad.optimisation`)."""
        values = self if values is None else values
        a = attachment
        if a.moving:
            parts = a.parts
            lanes = {}
            for name, base in a.base.items():
                # A copy per step: the grad-enabled values scattered into their lanes.
                lanes[name] = dr.copy(base)
                for i in parts[name]:
                    dr.scatter(lanes[name], values[f"{self._ids[i]}.{name}"],
                               UInt32(a.moving.index(i)))
            # Evaluated now, in one kernel of a fixed shape (left pending, the scatters
            # fuse differently with later work and force re-compilation).
            dr.eval(lanes)
            new = translate(lanes["translation"]) @ rotate_quaternion(lanes["rotation"]) \
                @ scale(lanes["scale"]) @ a.shear
            if parts["to_world"]:
                # Instances optimised through their whole matrix: inverted per lane with AD.
                m = lanes["to_world"]
                new = Transform(dr.select(a.whole, m, new.matrix),
                                dr.select(a.whole, dr.rcp(m), new.inverse_matrix))
            self.scene.instances.set_transforms(new, a.index, derivatives_only=True)
        self.scene.bsdfs.restore(self._attached_materials(a, values))
        for i in a.lights:
            light = self.scene.lights[i]
            vector_name, power_name = LIGHT_PARAMETERS[type(light)]
            owner = light.id
            vector, power = (values[f"{owner}.{name}"] if f"{owner}.{name}" in a.grad_lights
                             else Array3f(0.0) for name in (vector_name, power_name))
            if vector_name == "direction":
                # A direction is normalized where it is used (the stored one is).
                vector = vector / dr.norm(vector)
            self.scene.light_set().attach_delta(i, vector, power)
        return self

    def _absorb_changes(self) -> set[int]:
        """Fold assigned values into the detached float64 state (validating them); returns
        the instances whose matrix changed. The instances set through their parts are
        composed and checked as one batch (per instance, this was 0.6 ms of host work:
        64 ms of an optimisation step moving 100 instances)."""
        changed: dict[int, set[str]] = {}
        materials: dict[int, dict[str, np.ndarray]] = {}
        read = {key: _detached_numpy(self._values[key]) for key in self._dirty}
        for key, value in read.items():
            kind, name = self._split(key)
            owner = key.rsplit(".", 1)[0]
            if not np.isfinite(value).all():
                raise SceneError(f"parameter {key!r} has non-finite entries {value.tolist()}")
            if kind == "material":
                materials.setdefault(self._material_keys[key][0], {})[key] = value
            elif kind == "light":
                self._install_light(owner, name, value)
            else:
                changed.setdefault(self._ids.index(owner), set()).add(name)
        for i, values in materials.items():
            self._install_material(i, values)
        composed = []
        for i, names in changed.items():
            where = f"parameter {self._ids[i]!r}"
            parts = self._touch(i)
            if "to_world" in names:
                if len(names) > 1:
                    raise SceneError(f"{where}: set either to_world or its parts "
                                     f"({sorted(names - {'to_world'})}), not both")
                m = read[f"{self._ids[i]}.to_world"].reshape(4, 4)
                check_affine_matrix(m, f"{where} to_world")
                self._matrix[i] = m
                parts[:] = decompose(m)
                for name in ("translation", "rotation", "scale"):
                    self._values.pop(f"{self._ids[i]}.{name}", None)
                continue
            for name in names:
                parts[PART_INDEX[name]] = read[f"{self._ids[i]}.{name}"]
            if not parts[1].any():
                raise SceneError(f"{where}.rotation: the zero quaternion is not a rotation")
            if (parts[2] == 0).any():
                raise SceneError(f"{where}.scale: a zero factor makes the transform singular")
            composed.append(i)
        if composed:
            t, q, s, shear = (np.array([self._parts[i][k] for i in composed]) for k in range(4))
            matrices = _compose_numpy(t, q, s, shear)
            try:
                check_affine_matrix(matrices)
            except TransformError:
                for i, m in zip(composed, matrices):
                    check_affine_matrix(m, f"parameter {self._ids[i]!r} to_world")
            for i, m in zip(composed, matrices):
                self._matrix[i] = m
                self._values.pop(f"{self._ids[i]}.to_world", None)
        return set(changed)

    def _install_material(self, i: int, values: dict[str, np.ndarray]) -> None:
        """Check new values of material ``i``'s parameters against their ranges and store
        them in the scene (constants in its table and material record, texels in its
        textures)."""
        table = self.scene.bsdfs
        lobe = table.rows[i].lobe
        constants = {}
        for key, value in values.items():
            _, name, form = self._material_keys[key]
            parameter = lobe.parameters[name]
            if value.size and (value.min() < parameter.low or value.max() > parameter.high):
                raise SceneError(f"parameter {key!r}: values must lie in [{parameter.low}, "
                                 f"{parameter.high}], got {value.min():g} .. {value.max():g} "
                                 "(clip them after an optimiser step)")
            if form == TEXELS:
                table.set_texels(table.texture(i, name), value)
            else:
                constants[name] = tuple(map(float, value)) if form == COLOR else float(value[0])
        if constants:
            self.scene.set_material_constants(self.scene.material_names[i], constants)

    def bounds(self, key: str) -> tuple[float, float]:
        """The valid range [low, high] of a material parameter's values (-inf, inf for other
        parameters), e.g. to clip an optimiser's values to."""
        if self._split(key)[0] != "material":
            return -math.inf, math.inf
        i, name, _ = self._material_keys[key]
        parameter = self.scene.bsdfs.rows[i].lobe.parameters[name]
        return parameter.low, parameter.high

    def _attached_materials(self, a: "Attachment", values: Any) -> dict:
        """The material table's arrays with the grad-enabled material parameters (read from
        ``values``) scattered into copies of the installed, detached ones."""
        state = dict(a.materials)
        table = self.scene.bsdfs
        for key in a.grad_materials:
            i, name, form = self._material_keys[key]
            column = "texels" if form == TEXELS else name
            if state[column] is a.materials[column]:
                state[column] = dr.copy(state[column])
            if form == TEXELS:
                start, (h, w) = table.textures.texel_range(table.texture(i, name))
                dr.scatter(state[column], values[key].array, dr.arange(UInt32, 3 * h * w) + start)
                continue
            back = table.shared_back(i)
            for row in [i] + ([] if back is None else [back]):
                dr.scatter(state[column], values[key], UInt32(row))
        return state

    def _install_light(self, owner: str, name: str, value: np.ndarray) -> None:
        """Store a light parameter's new (finite) value in the scene's light record."""
        where = f"parameter {owner + '.' + name!r}"
        if name in ("intensity", "irradiance") and (value < 0).any():
            raise SceneError(f"{where}: must not be negative, got {value.tolist()}")
        if name == "direction":
            norm = np.linalg.norm(value)
            if norm == 0:
                raise SceneError(f"{where}: the zero vector is not a direction")
            value = value / norm
        i = self._lights[owner]
        self.scene.set_light(i, dataclasses.replace(self.scene.lights[i],
                                                    **{name: tuple(map(float, value))}))

    def grad_enabled_keys(self) -> list[str]:
        """The parameters that carry derivatives."""
        return [key for key, value in self._values.items() if dr.grad_enabled(value)]

    def _grad_instances(self, name: str) -> list[int]:
        """Instances whose parameter ``name`` is present and grad-enabled."""
        return [self._ids.index(key.rsplit(".", 1)[0]) for key, v in self._values.items()
                if key.rsplit(".", 1)[1] == name and key.rsplit(".", 1)[0] in self._ids
                and dr.grad_enabled(v)]


class Attachment:
    """What :meth:`SceneParameters.attach` reads: the moving instances' parameter lanes
    from the float64 state, their shears and indices, and the materials'
    reflectances; Dr.Jit arrays made by :meth:`SceneParameters.install`."""

    def __init__(self, params: SceneParameters, moving: list[int], parts: dict[str, list[int]],
                 lights: list[int]):
        self.moving = moving
        self.parts = parts
        # The lights with derivatives (indices into scene.lights) and their grad-enabled keys.
        self.lights = lights
        self.grad_lights = sorted(key for key in params.grad_enabled_keys()
                                  if params._split(key)[0] == "light")
        self.grad_materials = sorted(key for key in params.grad_enabled_keys()
                                     if params._split(key)[0] == "material")
        # The material table's installed arrays, detached: attach scatters into copies.
        self.materials = {key: dr.detach(value)
                          for key, value in params.scene.bsdfs.state().items()}
        if not moving:
            return
        state = [params._parts[i] for i in moving]
        self.base = {name: _owned_lanes(array_type, np.array([p[PART_INDEX[name]] for p in state]))
                     for name, array_type in (("translation", Array3f), ("rotation", Array4f),
                                              ("scale", Array3f))}
        if parts["to_world"]:
            self.base["to_world"] = _owned_lanes(Matrix4f, np.array([params._matrix[i] for i in moving]))
            self.whole = dr.zeros(Bool, len(moving))
            dr.scatter(self.whole, True, device_array(
                UInt32, np.array([moving.index(i) for i in parts["to_world"]], np.uint32)))
            dr.eval(self.whole)
        shear = np.zeros((len(moving), 4, 4))
        shear[:, :3, :3] = [p[3] for p in state]
        shear[:, 3, 3] = 1.0
        self.shear = Transform(_owned_lanes(Matrix4f, shear), _owned_lanes(Matrix4f, affine_inverse(shear)))
        self.index = device_array(UInt32, np.asarray(moving, np.uint32))

    def key(self) -> tuple:
        """The Python values :meth:`SceneParameters.attach` traces with."""
        return (tuple(self.moving), tuple((k, tuple(v)) for k, v in self.parts.items()),
                tuple(self.grad_materials), tuple(self.lights), tuple(self.grad_lights))


def _material_keys(scene) -> dict[str, tuple[int, str, str]]:
    """Every material parameter :func:`traverse` exposes (module docstring): key ->
    (material index, parameter name, COLOR, NUMBER or TEXELS)."""
    keys = {}
    table = scene.bsdfs
    for i, name in enumerate(scene.material_names):
        material = scene.materials[name]
        for parameter, spec in material.lobe.parameters.items():
            if not spec.differentiable:
                continue
            texture = table.texture(i, parameter)
            if texture is None:
                keys[f"{name}.{parameter}"] = (i, parameter, spec.kind)
            elif table.textures.textures[texture].type == "bitmap":
                keys[f"{name}.{parameter}.data"] = (i, parameter, TEXELS)
    return keys


def _owned_lanes(array_type: type, values: np.ndarray) -> Any:
    """Per-lane ``array_type`` (``Array3f``, ``Array4f`` or ``Matrix4f``) from (M, k) or
    (M, 4, 4) values, each component a :func:`~instancing.core.backend.device_array`, so that
    the per-step kernels are the same every step (one lane included).
    """
    values = np.asarray(values, np.float32)
    if array_type is Matrix4f:
        entries = device_arrays(Float, *[values[:, r, c] for r in range(4) for c in range(4)])
        return Matrix4f(*[Array4f(*entries[4 * r:4 * r + 4]) for r in range(4)])
    return array_type(*device_arrays(Float, *values.T))


def _detached_numpy(value: Any) -> np.ndarray:
    """A width-1 Dr.Jit value as float64 NumPy (matrices as (4, 4))."""
    arr = np.array(dr.detach(value), np.float64)
    return arr.reshape(4, 4) if isinstance(value, Matrix4f) else arr.reshape(-1)


def _compose_numpy(t: np.ndarray, q: np.ndarray, s: np.ndarray, shear: np.ndarray) -> np.ndarray:
    """float64 matrices (N, 4, 4) of translate(t) @ rotate_quaternion(q) @ scale(s) @ H
    for (N, 3), (N, 4), (N, 3) and (N, 3, 3) parts (the rotation as
    :func:`~instancing.core.transform.rotate_quaternion` builds it, q normalized)."""
    rotation = np.stack([np.stack(row, -1) for row in quaternion_rows(*q.T)], 1)
    m = np.zeros((len(t), 4, 4))
    m[:, :3, :3] = np.einsum("nij,njk->nik", rotation * s[:, None, :], shear)
    m[:, :3, 3] = t
    m[:, 3, 3] = 1.0
    return m


def traverse(scene) -> SceneParameters:
    """The differentiable parameters of ``scene`` (see :mod:`instancing.ad.parameters`).

    Example::

        params = instancing.traverse(scene)
        dr.enable_grad(params["bunny.translation"])
        params.update()
        image = instancing.render(scene, "direct", spp=16)
    """
    return SceneParameters(scene)
