"""``instancing.traverse``: the differentiable parameters of a scene.

In the spirit of ``mitsuba.traverse``: a mutable mapping from names to Dr.Jit
values, with ``update()`` pushing changes into the scene. Keys:

* ``"<instance id>.translation"`` (``Array3f64``: world values in float64, so that a step
  1e6 from the origin is not lost to float32's 0.0625 spacing there), ``"<instance id>.rotation"``
  (``Array4f``, a quaternion (x, y, z, w), normalized where it is used, so an
  optimiser step can never leave the rotation group), ``"<instance id>.scale"``
  (``Array3f``, per axis; a reflection is a negative z scale), and
  ``"<instance id>.to_world"`` (``Matrix4f64``, the whole affine matrix, for
  shear);
* ``"<group>.translation"``, ``".rotation"`` and ``".scale"``: the same parameters of a
  group of instances, one lane per member (``Array3f64`` / ``Array4f`` / ``Array3f`` of
  the group's width), so that optimising a thousand instances is one array per parameter, not a
  thousand keys. Every batch of the scene file (``"count"`` instances named
  ``"<prefix>[k]"``) is a group named by its prefix; :meth:`SceneParameters.group` makes
  others;
* ``"<material>.<parameter>"`` for the parameters Mitsuba's plugin reads per lookup and
  marks differentiable (:attr:`instancing.materials.parameter.Parameter.differentiable`:
  colours as ``Array3f``, ``alpha`` as ``Float``), given as constants, e.g.
  ``"red.reflectance"``, ``"gold.alpha"``, ``"gold.eta"``, and as Mitsuba's traverse a
  rough or thin glass's ``"<material>.eta"`` (int_ior / ext_ior; setting it sets int_ior);
  where a ``checkerboard`` gives one, ``"<material>.<parameter>.color0"`` and ``".color1"``
  (``Array3f``; ``Float`` for a number parameter); where a ``bitmap`` gives one,
  ``"<material>.<parameter>.data"``, its linear texels as a ``TensorXf`` (H, W, 3), and so
  a normal map's ``"<material>.normalmap.data"`` (or its checkerboard's colours) and a bump
  map's heights ``"<material>.bumpmap.data"``; where a ``volume`` gives one, none (its
  values are the grid file's); a mesh attribute that a material reads is a key of its mesh
  model (below). A
  ``twosided`` material with one BSDF has that BSDF's keys (both sides change together);
  one with two BSDFs, its front's; the BSDFs of a blend or mask have theirs under
  Mitsuba's part names, ``"<material>.bsdf_0.<parameter>"``, ``".bsdf_1."``,
  ``".nested_bsdf."``;
* ``"<light id>.position"`` and ``".intensity"`` of point, spot and projector lights (a
  projector's intensity: its scale times a constant irradiance), ``".direction"`` (the
  direction the light travels, normalized where it is used) and ``".irradiance"`` of
  directional lights (``Array3f``; a position ``Array3f64``, as a translation); a light's
  id is its scene file ``"id"``, by default ``"lights[k]"``; where a bitmap gives a spot's
  texture or a projector's irradiance, its texels ``"<light id>.texture.data"`` or
  ``"<light id>.irradiance.data"`` (``TensorXf`` (H, W, 3), Mitsuba's keys), where a
  checkerboard does, its ``".color0"`` and ``".color1"`` (``Array3f``);
* ``"<model>.<attribute>"`` (``TensorXf`` (N, dim): per vertex or face) of a mesh model's
  attribute that some material reads through a ``mesh_attribute`` texture, e.g.
  ``"bunny.vertex_color"`` (Mitsuba's ``"<shape>.vertex_color"``; every instance of the
  model shows it);
* ``"<instance id>.emitter.radiance"`` (``Array3f``) of an instance's area emitter whose
  radiance is a constant (Mitsuba's ``"<shape>.emitter.radiance.value"``), and
  ``"<instance id>.emitter.radiance.data"`` (``TensorXf`` (H, W, 3)) where a bitmap gives it
  (a bitmap several lamps share: one key, under the first of them, which sets them all), or
  ``".color0"`` and ``".color1"`` where a checkerboard gives it; the
  environment's ``"<light id>.radiance"`` (``Array3f``) where it is ``constant``, its
  ``"<light id>.data"`` (the map's linear texels, ``TensorXf`` (H, W, 3)) and ``".scale"``
  (``Float``) where it is an ``envmap``. Emitted light enters the estimates linearly;
  the environment's sampling density is rebuilt from changed texels at ``update()`` and
  carries no derivatives (it chooses samples, as in Mitsuba).

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

Translations, whole matrices and light positions are float64 world values, the rest float32
(their magnitudes are near 1). A value assigned back as it was read keeps the stored
float64 value, and so does a component equal to its float32 rounding (a value passed
through float32 code): writing parameters back never moves an instance or lamp far from
the origin onto the float32 grid.

An instance parameter is driven by one key at a time: a member of a group whose
parameter is set or grad-enabled through the group and through its own key (or its
``to_world``) at once is an error naming both keys.

State is kept per touched instance only, in float64 arrays (one row per instance,
matrices and parts): a scene with a million instances costs nothing per instance
here until its parameters are read or set (values are created lazily, and the
float64 matrices of untouched instances are the scene's own). A step's host work
is array work over the changed rows, with no Python loop over a group's members.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterator, MutableMapping
from typing import Any, NamedTuple

import numpy as np

from ..core.backend import (Array3f, Array3f64, Array4f, Bool, Float, Float64, Matrix4f, Matrix4f64,
                            TensorXf, UInt32, device_array, device_arrays, dr)
from ..core.errors import SceneError, TransformError
from ..core.transform import (Transform, affine_inverse, check_affine_matrix, decompose,
                              quaternion_rows, rotate_quaternion, scale, translate)
from ..materials.bump_map import BUMP_MAP, HEIGHTS
from ..materials.normal_map import NORMAL_MAP, PARAMETERS as NORMAL_MAP_PARAMETERS
from ..materials.parameter import COLOR, NUMBER
from ..materials.texture import Texture
from ..scene.description import (ENVIRONMENTS, ConstantLight, DirectionalLight, EnvironmentMap,
                                 PointLight, ProjectorLight, SpotLight)
from ..scene.scene import require_scene

#: The kind of a material parameter given by a bitmap: its texels.
TEXELS = "texels"
#: Per-instance parameter names, in key order.
INSTANCE_PARAMETERS = ("translation", "rotation", "scale", "to_world")
#: An instance's parts, as :func:`~instancing.core.transform.decompose` splits its matrix.
PARTS = ("translation", "rotation", "scale", "shear")
#: The parts a parameter may set (of an instance or a group), in key order.
PART_INDEX = {"translation": 0, "rotation": 1, "scale": 2}
#: The Dr.Jit type of each instance parameter's value (per lane), and of a light's position:
#: world places in float64, the rest in float32.
ARRAY_TYPE = {"translation": Array3f64, "rotation": Array4f, "scale": Array3f, "to_world": Matrix4f64,
              "position": Array3f64}
#: Light parameter names per light kind: (the vector kernels read, its power).
LIGHT_PARAMETERS = {PointLight: ("position", "intensity"), SpotLight: ("position", "intensity"),
                    ProjectorLight: ("position", "intensity"),
                    DirectionalLight: ("direction", "irradiance")}
#: The environment's parameter names per kind.
ENVIRONMENT_PARAMETERS = {ConstantLight: ("radiance",), EnvironmentMap: ("data", "scale")}
#: A checkerboard's colours, as their keys name them.
CHECKER_COLORS = ("color0", "color1")
#: The Dr.Jit type of each emitter and environment parameter's value.
EMITTER_TYPE = {"radiance": Array3f, "data": TensorXf, "scale": Float, "color0": Array3f, "color1": Array3f}


class SceneParameters(MutableMapping):
    """Differentiable parameters of a scene (see the module docstring)."""

    def __init__(self, scene):
        require_scene(scene, "traverse")
        self.scene = scene
        self._ids = scene.instance_ids
        # Material parameters by key: (material index, parameter, kind: a colour, a number
        # or a bitmap's texels).
        self._material_keys = _material_keys(scene)
        # The touched instances' float64 state, one row each: the instance index, its
        # matrix and its parts [t, q, s, H]; _row_of maps an instance to its row.
        self._row_of: dict[int, int] = {}
        self._state = {"instance": np.zeros(0, np.int64), "to_world": np.zeros((0, 4, 4)),
                       "translation": np.zeros((0, 3)), "rotation": np.zeros((0, 4)),
                       "scale": np.zeros((0, 3)), "shear": np.zeros((0, 3, 3))}
        # Groups by name: their member instances, in lane order (the batches of the scene
        # file first), and their members' state rows once touched.
        self._groups: dict[str, np.ndarray] = {
            name: np.arange(start, start + count, dtype=np.int64)
            for name, start, count in self._ids.batches() if name not in self._ids}
        self._group_rows: dict[str, np.ndarray] = {}
        self._values: dict[str, Any] = {}
        self._dirty: set[str] = set()
        # Point and directional lights by id: their index in scene.lights.
        self._lights = {light.id: i for i, light in enumerate(scene.lights)
                        if type(light) in LIGHT_PARAMETERS}
        # The mesh attributes that materials read, by key "<model>.<attribute>": (model, name).
        textures = scene.bsdfs.textures
        read = textures.attribute_names if textures is not None else []
        used = set(np.unique(scene.description.instance_model).tolist())
        self._scatters: dict[str, tuple[UInt32, UInt32]] = {}
        self._mesh_attributes = {f"{spec.name}.{name}": (m, name)
                                 for m, spec in enumerate(scene.description.models)
                                 if spec.mesh is not None and m in used
                                 for name in read if name in (spec.mesh.attributes or {})}
        # Spots' and projectors' bitmaps by their keys' owner ("<light id>.texture" or
        # "<light id>.irradiance", as Mitsuba names them): the light's index.
        self._light_texels, self._light_checks = (
            {f"{light.id}.{_texture_key(light)}": i for i, light in enumerate(scene.lights)
             if isinstance(light, (SpotLight, ProjectorLight)) and light.texture is not None
             and light.texture.type == kind} for kind in ("bitmap", "checkerboard"))
        # Area emitters of a constant radiance by their keys' owner "<instance id>.emitter"
        # (their instance's index), and the environment by its id (its index in scene.lights).
        self._emitters = {f"{self._ids[i]}.emitter": i
                          for i, emitter in scene.description.emitters.items() if emitter.texture is None}
        # Bitmap-textured area emitters by their keys' owner "<instance id>.emitter.radiance":
        # the instances sharing the bitmap, the first naming the key.
        # Checkerboard-textured ones likewise (their colours the keys).
        self._emitter_texels: dict[str, list[int]] = {}
        self._emitter_checks: dict[str, list[int]] = {}
        firsts: dict[int, str] = {}
        for i, emitter in sorted(scene.description.emitters.items()):
            if emitter.texture is not None and emitter.texture.type in ("bitmap", "checkerboard"):
                owner = firsts.setdefault(id(emitter.texture), f"{self._ids[i]}.emitter.radiance")
                lamps = self._emitter_texels if emitter.texture.type == "bitmap" else self._emitter_checks
                lamps.setdefault(owner, []).append(i)
        self._environment = {light.id: i for i, light in enumerate(scene.lights)
                             if isinstance(light, ENVIRONMENTS)}

    def _rows(self, instances: np.ndarray) -> np.ndarray:
        """The state rows of ``instances`` (indices), split from the scene's matrices on
        first use (one batched decomposition for the new ones)."""
        new = np.unique([i for i in instances.tolist() if i not in self._row_of]).astype(np.int64)
        if len(new):
            matrices = self.scene.to_world_of(new)
            start = len(self._state["instance"])
            for name, value in zip(("instance", "to_world", *PARTS),
                                   (new, matrices, *decompose(matrices))):
                self._state[name] = np.concatenate([self._state[name], value])
            self._row_of.update(zip(new.tolist(), range(start, start + len(new))))
        return np.array([self._row_of[i] for i in instances.tolist()], np.int64)

    def _members(self, owner: str) -> tuple[np.ndarray, np.ndarray]:
        """(instance indices, state rows) of an instance id or a group name."""
        if owner in self._groups:
            if owner not in self._group_rows:
                self._group_rows[owner] = self._rows(self._groups[owner])
            return self._groups[owner], self._group_rows[owner]
        instance = np.array([self._ids.index(owner)], np.int64)
        return instance, self._rows(instance)

    # -- groups --------------------------------------------------------------------------------

    @property
    def groups(self) -> dict[str, list[str]]:
        """Group name -> its members' instance ids, in lane order."""
        return {name: [self._ids[i] for i in members.tolist()]
                for name, members in self._groups.items()}

    def group(self, name: str, ids: list[str] | None = None) -> list[str]:
        """Make a group of instances whose parameters are optimised as one array each.

        Args:
            name: the group's name, used in its keys ``"<name>.translation"``,
                ``".rotation"``, ``".scale"``; it must not name an instance, a light, a
                material or another group, nor contain a dot.
            ids: the member instance ids, in lane order (default: every instance).

        The group's values start from its members' current values (also those set and
        not yet pushed by :meth:`update`; those then belong to the group). Returns the
        group's keys.

        Raises:
            SceneError: a bad or taken name, unknown or repeated ids (or ids given as one
                string), or a member whose own translation, rotation or scale carries
                derivatives.
        """
        taken = (name in self._groups or name in self._ids or name in self._lights
                 or name in self.scene.material_names)
        if not isinstance(name, str) or not name or "." in name or taken:
            raise SceneError(f"group name {name!r}: expected a new name without '.' (it must "
                             "not name an instance, light, material or group)")
        if isinstance(ids, str):
            raise SceneError(f"group {name!r}: ids must be a list of instance ids, not the "
                             f"string {ids!r}")
        ids = list(self._ids) if ids is None else list(ids)
        unknown = [x for x in ids if x not in self._ids]
        if unknown or not ids:
            raise SceneError(f"group {name!r}: {unknown[:5] or 'no'} instance ids "
                             f"{'are not in the scene' if unknown else 'given'}")
        members = np.array([self._ids.index(x) for x in ids], np.int64)
        if len(np.unique(members)) != len(members):
            raise SceneError(f"group {name!r}: an instance id is given twice")
        # The members' own cached part values: folded into the group's first values.
        rows = self._rows(members)
        lane = {int(i): k for k, i in enumerate(members.tolist())}
        own = [(key, lane[self._ids.index(key.rsplit(".", 1)[0])]) for key in self._values
               if self._split(key)[0] == "instance" and key.rsplit(".", 1)[1] in PART_INDEX
               and self._ids.index(key.rsplit(".", 1)[0]) in lane]
        carrying = [key for key, _ in own if dr.grad_enabled(self._values[key])]
        if carrying:
            raise SceneError(f"group {name!r}: {carrying[:5]} carry derivatives; disable "
                             "them before grouping (a parameter is driven by one key)")
        self._groups[name] = members
        self._group_rows[name] = rows
        for part in PARTS[:3]:
            value = self._state[part][rows]
            pending = False
            for key, k in own:
                if key.rsplit(".", 1)[1] == part:
                    value[k] = _detached_numpy(self._values[key])[0]
                    pending |= key in self._dirty
            group_key = f"{name}.{part}"
            self._values[group_key] = _owned_lanes(ARRAY_TYPE[part], value)
            if pending:
                self._dirty.add(group_key)
        for key, _ in own:
            self._values.pop(key)
            self._dirty.discard(key)
        return [f"{name}.{part}" for part in PARTS[:3]]

    def ungroup(self, name: str, discard: bool = False) -> None:
        """Remove group ``name`` (made by :meth:`group`); its members' own keys read the
        installed values again.

        Args:
            discard: drop the group's values set and not yet pushed by :meth:`update`
                (otherwise they are an error).

        Raises:
            SceneError: an unknown group, a batch of the scene file, or (without
                ``discard``) a group whose values are set and not yet pushed, or carry
                derivatives.
        """
        if name not in self._groups or name in {b[0] for b in self._ids.batches()}:
            raise SceneError(f"ungroup: {name!r} is not a group made by group()")
        keys = [f"{name}.{part}" for part in PARTS[:3]]
        busy = [key for key in keys if key in self._dirty
                or (key in self._values and dr.grad_enabled(self._values[key]))]
        if busy and not discard:
            raise SceneError(f"ungroup: {busy} are set but not updated, or carry derivatives")
        for key in keys:
            self._values.pop(key, None)
            self._dirty.discard(key)
        del self._groups[name]
        self._group_rows.pop(name, None)

    def _instance_part(self, key: str) -> bool:
        """Whether ``key`` is an instance's or a group's transform parameter."""
        return self._split(key)[0] in ("instance", "group")

    # -- mapping interface ---------------------------------------------------------------------

    def _split(self, key: str) -> tuple[str, str]:
        if not isinstance(key, str) or "." not in key:
            raise KeyError(key)
        owner, name = key.rsplit(".", 1)
        if name in INSTANCE_PARAMETERS and owner in self._ids:
            return "instance", name
        if name in PART_INDEX and owner in self._groups:
            return "group", name
        if key in self._material_keys:
            return "material", name
        if key in self._mesh_attributes:
            return "mesh", name
        if ((owner in self._lights and name in LIGHT_PARAMETERS[type(self._light(owner))])
                or (owner in self._light_texels and name == "data")
                or (owner in self._light_checks and name in CHECKER_COLORS)):
            return "light", name
        if ((owner in self._emitters and name == "radiance")
                or (owner in self._emitter_texels and name == "data")
                or (owner in self._emitter_checks and name in CHECKER_COLORS)):
            return "emitter", name
        if owner in self._environment and name in self._environment_names(owner):
            return "environment", name
        raise KeyError(key)

    def _environment_names(self, owner: str) -> tuple[str, ...]:
        return ENVIRONMENT_PARAMETERS[type(self.scene.lights[self._environment[owner]])]

    def material_parameter(self, key: str) -> tuple[str, str, int | None, str | None]:
        """(material name, parameter name, which part of a blend or mask holds it or None,
        which checkerboard colour it is or None) of material parameter ``key``."""
        if key not in self._material_keys:
            raise KeyError(key)
        entry = self._material_keys[key]
        return self.scene.material_names[entry.material], entry.parameter, entry.part, entry.field

    def kind(self, key: str) -> str:
        """What parameter ``key`` belongs to: ``"instance"``, ``"group"`` (of instances),
        ``"material"``, ``"mesh"`` (a mesh model's attribute), ``"light"`` (a point, spot,
        projector or directional light), ``"emitter"`` (an area emitter) or
        ``"environment"`` (KeyError for an unknown key)."""
        return self._split(key)[0]

    def instances_of(self, key: str) -> list[int]:
        """The instance indices an instance or group parameter moves, in lane order."""
        if self._split(key)[0] not in ("instance", "group"):
            raise SceneError(f"{key!r} is not an instance or group parameter")
        return self._members(key.rsplit(".", 1)[0])[0].tolist()

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
            entry = self._material_keys[f"{owner}.{name}"]
            table, row, parameter = self.scene.bsdfs, entry.row, entry.parameter
            if entry.form == TEXELS:
                return TensorXf(table.textures.texels_of(table.texture(row, parameter)))
            if entry.field is not None:
                value = getattr(table.textures.textures[table.texture(row, parameter)], entry.field)
                return Array3f(*value) if entry.form == COLOR else Float(value[0])
            column = _parameter(table.rows[row].lobe, parameter).column
            value = (table.host[column][row] if column is not None
                     else table.rows[row].values[parameter])
            return Array3f(*value) if entry.form == COLOR else Float(float(value))
        if kind == "mesh":
            model, attribute = self._mesh_attributes[f"{owner}.{name}"]
            return TensorXf(np.asarray(self.scene.description.models[model].mesh.attributes[attribute],
                                       np.float32))
        if kind == "light" and name == "data":
            return TensorXf(self.scene.lights[self._light_texels[owner]].texture.texels)
        if kind == "light" and name in CHECKER_COLORS:
            return Array3f(*getattr(self.scene.lights[self._light_checks[owner]].texture, name))
        if kind == "light":
            return ARRAY_TYPE.get(name, Array3f)(*getattr(self._light(owner), name))
        if kind == "emitter" and name == "data":
            return TensorXf(self.scene.description.emitters[self._emitter_texels[owner][0]].texture.texels)
        if kind == "emitter" and name in CHECKER_COLORS:
            lamp = self._emitter_checks[owner][0]
            return Array3f(*getattr(self.scene.description.emitters[lamp].texture, name))
        if kind == "emitter":
            return Array3f(*self.scene.description.emitters[self._emitters[owner]].radiance)
        if kind == "environment":
            light = self.scene.lights[self._environment[owner]]
            if name == "data":
                return TensorXf(np.asarray(light.texels, np.float32))
            return Float(light.scale) if name == "scale" else Array3f(*light.radiance)
        rows = self._members(owner)[1]
        if name == "to_world":
            return Matrix4f64(self._state["to_world"][rows[0]].tolist())
        return _owned_lanes(ARRAY_TYPE[name], self._state[name][rows])

    def __setitem__(self, key: str, value: Any) -> None:
        kind, name = self._split(key)
        expected = ARRAY_TYPE.get(name, Array3f)
        width = 1
        if kind == "material":
            expected = {COLOR: Array3f, NUMBER: Float, TEXELS: TensorXf}[self._material_keys[key].form]
        elif kind in ("emitter", "environment") or (kind == "light" and name in EMITTER_TYPE):
            expected = EMITTER_TYPE[name]
        elif kind == "mesh":
            expected = TensorXf
        elif kind == "group":
            width = len(self._groups[key.rsplit(".", 1)[0]])
            if _square_host_lanes(value, width, dr.size_v(expected)):
                raise SceneError(f"parameter {key!r}: a ({width}, {width}) array reads as members "
                                 f"by components and as components by members; give "
                                 f"{expected.__name__} (one lane per member)")
        try:
            value = value if isinstance(value, expected) else expected(value)
        except (TypeError, RuntimeError) as exc:
            raise SceneError(f"parameter {key!r}: cannot convert {value!r} to "
                             f"{expected.__name__} ({exc})") from None
        if expected is TensorXf:
            shape = tuple(self[key].shape)
            if tuple(value.shape) != shape:
                raise SceneError(f"parameter {key!r}: expected {'values' if kind == 'mesh' else 'texels'} "
                                 f"of shape {shape}, got "
                                 f"{tuple(value.shape)}")
        elif dr.width(value) != width:
            raise SceneError(f"parameter {key!r}: expected {width} value(s) (one per "
                             f"{'member' if kind == 'group' else 'parameter'}), got width "
                             f"{dr.width(value)}")
        self._values[key] = value
        self._dirty.add(key)

    def __delitem__(self, key: str) -> None:
        raise TypeError("scene parameters cannot be removed")

    def __iter__(self) -> Iterator[str]:
        for name in self._ids:
            for p in INSTANCE_PARAMETERS:
                yield f"{name}.{p}"
        for name in self._groups:
            for p in PART_INDEX:
                yield f"{name}.{p}"
        yield from self._material_keys
        yield from self._mesh_attributes
        for owner in self._lights:
            for name in LIGHT_PARAMETERS[type(self._light(owner))]:
                yield f"{owner}.{name}"
        for owner in self._light_texels:
            yield f"{owner}.data"
        for owner in (*self._light_checks, *self._emitter_checks):
            for name in CHECKER_COLORS:
                yield f"{owner}.{name}"
        for owner in self._emitters:
            yield f"{owner}.radiance"
        for owner in self._emitter_texels:
            yield f"{owner}.data"
        for owner in self._environment:
            for name in self._environment_names(owner):
                yield f"{owner}.{name}"

    def __len__(self) -> int:
        return (len(self._ids) * len(INSTANCE_PARAMETERS) + len(self._groups) * len(PART_INDEX)
                + len(self._material_keys) + len(self._mesh_attributes) + 2 * len(self._lights)
                + len(self._emitters)
                + len(self._emitter_texels) + len(self._light_texels)
                + len(CHECKER_COLORS) * (len(self._light_checks) + len(self._emitter_checks))
                + sum(len(self._environment_names(owner)) for owner in self._environment))

    def __repr__(self) -> str:
        return (f"SceneParameters({len(self._ids)} instances, {len(self._groups)} groups, "
                f"{len(self.scene.material_names)} materials)")

    # -- update --------------------------------------------------------------------------------

    def update(self, values: Any = None) -> "SceneParameters":
        """Push changed and grad-enabled parameters into the scene.

        Args:
            values: optionally a mapping whose entries are first assigned to their keys:
                a ``dict`` (each of its keys must be a parameter's), or a ``drjit.opt``
                optimiser (its entries that are no parameter's, e.g. latent variables,
                are skipped, as Mitsuba's ``update`` does).

        Call it after every change and after every optimiser step: it also
        re-attaches the AD graph that ``dr.backward`` consumed. It is
        :meth:`install` (host work) followed by :meth:`attach` (Dr.Jit work only).

        Raises:
            SceneError: a non-finite or singular transform, a zero scale or
                quaternion, or a parameter of an instance set (or grad-enabled)
                through two keys (``to_world`` and its parts, a group and a member).
                Every value is checked before any is stored: after a refused update
                the scene is as it was, and the values stay set until corrected.
        """
        return self.attach(self.install(values))

    def install(self, values: Any = None) -> "Attachment":
        """The host half of :meth:`update`: assign ``values``, check the changed
        parameters, and install the changed instances' float64 state in the scene,
        detached (their world boxes, remap bounds and grid references follow).
        Returns what :meth:`attach` needs, as Dr.Jit arrays made here."""
        if values is not None:
            if not hasattr(values, "keys"):
                raise TypeError(f"update: values must be a mapping from keys to values (an "
                                f"optimiser, a dict), got {type(values).__name__}")
            unknown = [key for key in values.keys() if key not in self]
            if unknown and isinstance(values, dict):
                close = difflib.get_close_matches(str(unknown[0]), [str(k) for k in self.keys()], 1)
                raise SceneError(f"update: no parameter {unknown[0]!r}"
                                 + (f" (did you mean {close[0]!r}?)" if close else "")
                                 + f"; {len(unknown)} unknown key(s) in all")
            for key in values.keys():
                if key in self:
                    self[key] = values[key]
        grad_keys = self.grad_enabled_keys()
        self._check_one_driver(sorted(self._dirty | set(grad_keys)))
        touched = self._absorb_changes()
        self._dirty.clear()
        drivers = [(key, self._members(key.rsplit(".", 1)[0])) for key in grad_keys
                   if self._instance_part(key)]
        moving, first = np.unique(np.concatenate(
            [np.zeros(0, np.int64)] + [m[0] for _, m in drivers]), return_index=True)
        moving_rows = np.concatenate([np.zeros(0, np.int64)] + [m[1] for _, m in drivers])[first]
        if len(touched):
            # The changed instances' float64 state rounded once (with its float64 inverse),
            # one lane each: only their rows are written, checked, bounded and re-filed.
            rows = self._rows(touched)
            state = self._state["to_world"][rows]
            self.scene.set_transforms(Transform(_owned_lanes(Matrix4f, state),
                                                _owned_lanes(Matrix4f, affine_inverse(state))),
                                      matrices=state, moving=moving, changed=touched)
        else:
            self.scene.set_moving(moving)
        lights = sorted({self._lights[key.rsplit(".", 1)[0]] for key in grad_keys
                         if self._split(key)[0] == "light" and key.rsplit(".", 1)[0] in self._lights})
        self.scene.set_moving_lights(np.array(lights, np.int64))
        for key in grad_keys:
            if self._split(key)[0] == "environment":
                # Both of a map's values are read when one carries derivatives: made here,
                # since attach may run inside a recording, which uploads nothing.
                owner = key.rsplit(".", 1)[0]
                for name in self._environment_names(owner):
                    self[f"{owner}.{name}"]
        return Attachment(self, moving, moving_rows,
                          [(key, np.searchsorted(moving, m[0])) for key, m in drivers], lights)

    def _check_one_driver(self, active: list[str]) -> None:
        """Refuse an instance parameter set or grad-enabled through two keys (its own,
        its ``to_world``, its groups')."""
        by_part: dict[str, list[tuple[str, np.ndarray]]] = {part: [] for part in PART_INDEX}
        for key in active:
            if not self._instance_part(key):
                continue
            owner, name = key.rsplit(".", 1)
            members = self._members(owner)[0]
            for part in (PART_INDEX if name == "to_world" else [name]):
                by_part[part].append((key, members))
        for part, entries in by_part.items():
            if len(entries) < 2:
                continue
            all_members = np.concatenate([m for _, m in entries])
            values, counts = np.unique(all_members, return_counts=True)
            if (counts > 1).any():
                i = int(values[np.argmax(counts > 1)])
                keys = [key for key, m in entries if i in m]
                raise SceneError(f"instance {self._ids[i]!r}: its {part} is set or carries "
                                 f"derivatives through {keys}; use one of them")

    def attach(self, attachment: "Attachment", values: Any = None) -> "SceneParameters":
        """The Dr.Jit half of :meth:`update`: the grad-enabled parameters (read from
        ``values``, default this mapping) attached to the installed transforms and
        reflectances. Values stay those :meth:`install` stored; derivatives come from
        the parameters. Reads only Dr.Jit arrays, so it can run inside a recording
        (:mod:`instancing.ad.optimisation`)."""
        values = self if values is None else values
        a = attachment
        if len(a.moving):
            lanes = {}
            for name, base in a.base.items():
                # A copy per step: the grad-enabled values scattered into their lanes
                # (one scatter per key: a group's members at once).
                lanes[name] = dr.copy(base)
                for key, index in a.sources[name]:
                    dr.scatter(lanes[name], values[key], index)
            # Evaluated now, in one kernel of a fixed shape (left pending, the scatters
            # fuse differently with later work and force re-compilation).
            dr.eval(lanes)
            # Derivatives only (the values stay the installed ones): float32 carries them.
            new = translate(Array3f(lanes["translation"])) @ rotate_quaternion(lanes["rotation"]) \
                @ scale(lanes["scale"]) @ a.shear
            if a.sources["to_world"]:
                # Instances optimised through their whole matrix: inverted per lane with AD.
                m = Matrix4f(lanes["to_world"])
                new = Transform(dr.select(a.whole, m, new.matrix),
                                dr.select(a.whole, dr.rcp(m), new.inverse_matrix))
            self.scene.instances.set_transforms(new, a.index, derivatives_only=True)
        self.scene.bsdfs.restore(self._attached_materials(a, values))
        emitting = [key for key in a.grad_emitters if self._split(key)[0] == "emitter"]
        for key in emitting:
            owner, name = key.rsplit(".", 1)
            if name == "data":
                self.scene.light_set().attach_emitter_texels(self._emitter_texels[owner][0], values[key])
            elif name in CHECKER_COLORS:
                self.scene.light_set().attach_emitter_color(self._emitter_checks[owner][0], name, values[key])
            else:
                self.scene.light_set().attach_emitter(self._emitters[owner], values[key])
        for owner in dict.fromkeys(key.rsplit(".", 1)[0] for key in a.grad_emitters
                                   if key not in emitting):
            given = {name: values[f"{owner}.{name}"] if f"{owner}.{name}" in a.grad_emitters
                     else dr.detach(self[f"{owner}.{name}"]) for name in self._environment_names(owner)}
            self.scene.light_set().environment.attach(
                given.get("radiance"), given.get("data"), given.get("scale"))
        for key in a.grad_lights:
            owner, name = key.rsplit(".", 1)
            if name == "data":
                self.scene.light_set().attach_profile_texels(self._light_texels[owner], values[key])
            elif name in CHECKER_COLORS:
                self.scene.light_set().attach_profile_color(self._light_checks[owner], name, values[key])
        for i in a.lights:
            light = self.scene.lights[i]
            vector_name, power_name = LIGHT_PARAMETERS[type(light)]
            owner = light.id
            vector, power = (values[f"{owner}.{name}"] if f"{owner}.{name}" in a.grad_lights
                             else Array3f(0.0) for name in (vector_name, power_name))
            if vector_name == "direction":
                # A direction is normalized where it is used (the stored one is).
                vector = vector / dr.norm(vector)
            self.scene.light_set().attach_delta(i, Array3f(vector), power)
        return self

    def _absorb_changes(self) -> np.ndarray:
        """Fold assigned values into the scene and the detached float64 state; returns the
        instances whose matrix changed (sorted indices). Every value is checked before any
        is stored, so a refused update leaves the scene and the state as they were (the
        values stay set, to be corrected). The instances set through their parts are
        composed and checked as one batch."""
        materials: dict[tuple[int, int | None], dict[str, np.ndarray]] = {}
        lights, wholes, parts, emitters, environment, meshes = [], [], [], [], {}, []
        for key in self._dirty:
            kind, name = self._split(key)
            owner = key.rsplit(".", 1)[0]
            value = self._finite_value(key, kind, owner)
            if kind == "material":
                entry = self._material_keys[key]
                materials.setdefault((entry.material, entry.part), {})[key] = \
                    value if entry.form == TEXELS else value.reshape(-1)
            elif kind == "light" and (name == "data" or name in CHECKER_COLORS):
                lights.append((owner, name, _not_negative(key, value)))
            elif kind == "light":
                stored = np.asarray(getattr(self._light(owner), name), np.float64)
                lights.append((owner, name, self._checked_light(owner, name,
                                                                _kept(value.reshape(-1), stored))))
            elif kind == "emitter":
                emitters.append((owner, name, _not_negative(key, value)))
            elif kind == "mesh":
                meshes.append((*self._mesh_attributes[key], value))
            elif kind == "environment":
                environment.setdefault(owner, {})[name] = _not_negative(key, value)
            elif name == "to_world":
                row = self._members(owner)[1][0]
                matrix = _kept(value[0], self._state["to_world"][row])
                check_affine_matrix(matrix, f"parameter {key!r}")
                wholes.append((key, row, matrix))
            else:
                parts.append((key, name, self._members(owner)[1], value))
        for (i, part), values in materials.items():
            self._check_material(i, part, values)
        rows, composed = self._composed(parts)
        # Every change checked: store them in the scene and the state.
        for (i, part), values in materials.items():
            self._install_material(i, part, values)
        for owner, name, value in lights:
            if name == "data" or name in CHECKER_COLORS:
                i = (self._light_texels if name == "data" else self._light_checks)[owner]
                texture = _changed(self.scene.lights[i].texture, name, value)
                self.scene.set_light(i, dataclasses.replace(self.scene.lights[i], texture=texture))
                continue
            i = self._lights[owner]
            self.scene.set_light(i, dataclasses.replace(self.scene.lights[i],
                                                        **{name: tuple(map(float, value))}))
        for model, name, value in meshes:
            self.scene.set_mesh_attribute(model, name, value.astype(np.float32))
        for owner, name, value in emitters:
            if name == "data" or name in CHECKER_COLORS:
                # One new texture, shared as the old one was.
                lamps = (self._emitter_texels if name == "data" else self._emitter_checks)[owner]
                emitted = self.scene.description.emitters
                texture = _changed(emitted[lamps[0]].texture, name, value)
                for i in lamps:
                    self.scene.set_emitter(i, dataclasses.replace(emitted[i], texture=texture))
                continue
            i = self._emitters[owner]
            self.scene.set_emitter(i, dataclasses.replace(self.scene.description.emitters[i],
                                                          radiance=tuple(map(float, value.reshape(-1)))))
        for owner, changes in environment.items():
            # (New texels are no file's: the map's file name is dropped.)
            fields = {"radiance": lambda v: {"radiance": tuple(map(float, v.reshape(-1)))},
                      "data": lambda v: {"texels": v.astype(np.float32), "filename": ""},
                      "scale": lambda v: {"scale": float(v.reshape(-1)[0])}}
            i = self._environment[owner]
            self.scene.set_light(i, dataclasses.replace(self.scene.lights[i], **{
                field: value for name, v in changes.items() for field, value in fields[name](v).items()}))
        changed = [rows]
        for key, row, m in wholes:
            self._state["to_world"][row] = m
            for part, value in zip(PARTS, decompose(m)):
                self._state[part][row] = value
            changed.append(np.array([row]))
        for name, value in composed.items():
            self._state[name][rows] = value
        changed_rows = np.unique(np.concatenate(changed))
        if len(changed_rows):
            self._forget_stale(changed_rows, [p[0] for p in parts] + [w[0] for w in wholes])
        return np.sort(self._state["instance"][changed_rows])

    def _finite_value(self, key: str, kind: str, owner: str) -> np.ndarray:
        """The assigned value of ``key`` as float64 NumPy (:func:`_detached_numpy`), refused
        when an entry is not finite (naming a group's member)."""
        value = _detached_numpy(self._values[key])
        if not np.isfinite(value).all():
            if kind == "group":
                bad = int(np.argmax(~np.isfinite(value).all(axis=1)))
                raise SceneError(f"parameter {key!r} (member {self._ids[self._groups[owner][bad]]!r})"
                                 f" has non-finite entries {value[bad].tolist()}")
            if value.size > 16:  # (texels: where, not the whole image)
                raise SceneError(f"parameter {key!r} has {_entries(~np.isfinite(value), value)}")
            raise SceneError(f"parameter {key!r} has non-finite entries "
                             f"{np.squeeze(value).tolist()}")
        return value

    def _composed(self, parts: list) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(state rows, their new parts and matrices) of the instances set through their
        parts (``(key, part, rows, values)`` each), composed in float64 and checked; the
        state itself is not written."""
        if not parts:
            return np.zeros(0, np.int64), {}
        rows = np.unique(np.concatenate([p[2] for p in parts]))
        new = {part: self._state[part][rows] for part in PARTS}
        for key, name, part_rows, value in parts:
            at = np.searchsorted(rows, part_rows)
            new[name][at] = _kept(value, new[name][at])
        # (attach normalizes the quaternion in float32: its squared norm must be a normal float32)
        norm2 = np.square(new["rotation"]).sum(axis=1)
        f32 = np.finfo(np.float32)
        for bad, what in ((~new["rotation"].any(axis=1), "rotation: the zero quaternion is not a rotation"),
                          ((norm2 < f32.tiny) | (norm2 > f32.max),
                           "rotation: the quaternion's squared norm is outside float32's range; "
                           "scale it towards 1"),
                          ((new["scale"] == 0).any(axis=1), "scale: a zero factor makes the transform "
                                                            "singular")):
            if bad.any():
                i = int(self._state["instance"][rows[np.argmax(bad)]])
                raise SceneError(f"parameter {self._ids[i]!r}.{what}")
        new["to_world"] = _compose_numpy(*(new[part] for part in PARTS))
        try:
            check_affine_matrix(new["to_world"])
        except TransformError:
            for row, m in zip(rows, new["to_world"]):
                i = int(self._state["instance"][row])
                check_affine_matrix(m, f"parameter {self._ids[i]!r} to_world")
        return rows, new

    def _forget_stale(self, rows: np.ndarray, sources: list[str]) -> None:
        """Drop the cached values of instance and group keys that the changes of ``rows``
        (made through the keys ``sources``) made stale; reading them again reads the state."""
        changed = set(self._state["instance"][rows].tolist())
        sources_by_part = {}
        for key in sources:
            owner, name = key.rsplit(".", 1)
            for part in (PART_INDEX if name == "to_world" else [name]):
                sources_by_part.setdefault(part, set()).add(key)
        changed_array = np.array(sorted(changed), np.int64)
        for key in [k for k in self._values if k not in self._dirty and self._instance_part(k)
                    and not dr.grad_enabled(self._values[k])]:
            # (A grad-enabled value is never stale: a change through another key is refused.)
            owner, name = key.rsplit(".", 1)
            if self._split(key)[0] == "group":
                members = self._groups[owner]
                stale = key not in sources and name in sources_by_part and \
                    bool(np.isin(members, changed_array).any())
            else:
                i = self._ids.index(owner)
                stale = i in changed and (name == "to_world" or name in sources_by_part)
            if stale:
                self._values.pop(key)

    def _check_material(self, i: int, part: int | None, values: dict[str, np.ndarray]) -> None:
        """Check new values of material ``i``'s parameters (or its ``part``'s) against their
        ranges and the material type's own rules (an ``eta`` of 1 for glass), storing
        nothing."""
        table = self.scene.bsdfs
        for key, value in values.items():
            entry = self._material_keys[key]
            parameter = _parameter(table.rows[entry.row].lobe, entry.parameter)
            if value.size and (value.min() < parameter.low or value.max() > parameter.high):
                raise SceneError(f"parameter {key!r}: values must lie in [{parameter.low}, "
                                 f"{parameter.high}], got {value.min():.9g} .. {value.max():.9g} "
                                 "(clip them after an optimiser step)")
        constants = self._material_constants(values)
        row = table.rows[i if part is None else table.part_rows[i][part]]
        if constants and hasattr(row.lobe, "changed"):
            # The type derives its values from a copy, as the table will when they are stored.
            try:
                row.lobe.changed({**row.values, **constants}, set(constants))
            except SceneError as err:
                raise SceneError(f"material {self.scene.material_names[i]!r}: {err}") from None

    def _material_constants(self, values: dict[str, np.ndarray]) -> dict[str, Any]:
        """The constant parameters among a material's new ``values``, as its record holds
        them (a colour as a tuple, a number as a float)."""
        constants = {}
        for key, value in values.items():
            entry = self._material_keys[key]
            if entry.form != TEXELS and entry.field is None:
                constants[entry.parameter] = (tuple(map(float, value)) if entry.form == COLOR
                                              else float(value[0]))
        return constants

    def _install_material(self, i: int, part: int | None, values: dict[str, np.ndarray]) -> None:
        """Store new (checked) values of material ``i``'s parameters (or its ``part``'s) in
        the scene: constants in its table and material record, texels and checkerboard
        colours in its textures."""
        table = self.scene.bsdfs
        for key, value in values.items():
            entry = self._material_keys[key]
            texture = table.texture(entry.row, entry.parameter)
            if entry.form == TEXELS:
                table.set_texels(texture, value)
            elif entry.field is not None:
                table.set_texture_color(texture, entry.field, np.broadcast_to(value, 3))
        constants = self._material_constants(values)
        if constants:
            self.scene.set_material_constants(self.scene.material_names[i], constants, part)

    def bounds(self, key: str) -> tuple[float, float]:
        """The valid range [low, high] of a parameter's values, e.g. to clip an optimiser's
        values to: a material parameter's range, [0, inf) for what lights emit (intensities,
        irradiances, radiances, an environment's texels and scale), (-inf, inf) for the rest."""
        kind, name = self._split(key)
        if kind in ("emitter", "environment") or name in ("intensity", "irradiance"):
            return 0.0, math.inf
        if kind != "material":
            return -math.inf, math.inf
        entry = self._material_keys[key]
        parameter = _parameter(self.scene.bsdfs.rows[entry.row].lobe, entry.parameter)
        return parameter.low, parameter.high

    def _attribute_scatter(self, key: str) -> tuple[UInt32, UInt32]:
        """Where mesh attribute ``key``'s values go in the material table's corner values:
        (float indices there, the float indices of the key's values they take); made once
        per key (the meshes' triangles and the table's layout stay)."""
        if key not in self._scatters:
            self._scatters[key] = self._attribute_indices(key)
        return self._scatters[key]

    def _attribute_indices(self, key: str) -> tuple[UInt32, UInt32]:
        model, name = self._mesh_attributes[key]
        corners, rows = self.scene.instances.meshes.attribute_sources(self.scene.mesh_index(model), name)
        dim = np.asarray(self.scene.description.models[model].mesh.attributes[name]).shape[1]
        start = self.scene.bsdfs.textures.attribute_offset(name)
        channel = np.arange(3)
        # (A one-value attribute is grey: its value in all three channels.)
        target = start + 3 * corners[:, None] + channel
        source = rows[:, None] * dim + np.minimum(channel, dim - 1)
        return (device_array(UInt32, target.ravel().astype(np.uint32)),
                device_array(UInt32, source.ravel().astype(np.uint32)))

    def _attached_materials(self, a: "Attachment", values: Any) -> dict:
        """The material table's arrays with the grad-enabled material parameters and mesh
        attributes (read from ``values``) scattered into copies of the installed, detached
        ones."""
        state = dict(a.materials)
        if a.grad_meshes:
            state["attributes"] = dr.copy(state["attributes"])
        for key, (target, source) in a.grad_meshes.items():
            dr.scatter(state["attributes"], dr.gather(Float, values[key].array, source), target)
        table = self.scene.bsdfs
        for key in a.grad_materials:
            entry = self._material_keys[key]
            row, name, form = entry.row, entry.parameter, entry.form
            if entry.field is not None:
                column = f"texture.{entry.field}"
            elif form == TEXELS:
                column = "texels"
            else:
                column = _parameter(table.rows[row].lobe, name).column or name
            if state[column] is a.materials[column]:
                state[column] = dr.copy(state[column])
            if entry.field is not None:
                # (A number parameter's checkerboard holds grey colours.)
                value = values[key] if form == COLOR else Array3f(values[key])
                dr.scatter(state[column], value, UInt32(table.texture(row, name)))
                continue
            if form == TEXELS:
                start, (h, w) = table.textures.texel_range(table.texture(row, name))
                dr.scatter(state[column], values[key].array, dr.arange(UInt32, 3 * h * w) + start)
                continue
            rows = table.rows_of(row)
            # Tables precomputed from the parameter follow it through their derivatives.
            table.tabulate_derivatives(rows, name)
            for row in rows:
                dr.scatter(state[column], values[key], UInt32(row))
        return state

    def _checked_light(self, owner: str, name: str, value: np.ndarray) -> np.ndarray:
        """A light parameter's new (finite) value as its record stores it (a direction
        normalized), refused where it must not be negative or is the zero direction."""
        where = f"parameter {owner + '.' + name!r}"
        if name in ("intensity", "irradiance") and (value < 0).any():
            raise SceneError(f"{where}: must not be negative, got {value.tolist()}")
        if name == "direction":
            norm = np.linalg.norm(value)
            if norm == 0:
                raise SceneError(f"{where}: the zero vector is not a direction")
            value = value / norm
        return value

    def grad_enabled_keys(self) -> list[str]:
        """The parameters that carry derivatives."""
        return [key for key, value in self._values.items() if dr.grad_enabled(value)]



def _kept(assigned: np.ndarray, stored: np.ndarray) -> np.ndarray:
    """The float64 values to store for assigned ones: the stored value wherever the assigned
    (float32) one is what reading it gives, its float32 rounding. Writing back a value read
    moves nothing: a translation 1e6 from the origin would otherwise jump to the float32
    grid (0.0625 apart there), and the whole scene with it, where the rendering space keeps
    the float64 placement (:mod:`instancing.scene.rendering_space`)."""
    return np.where(assigned == np.asarray(stored, np.float32), stored, assigned)


def _changed(texture: Texture, name: str, value: np.ndarray) -> Texture:
    """A light's texture with new texels (``name`` "data") or a new checkerboard colour."""
    if name == "data":
        return texture.with_texels(value)
    return dataclasses.replace(texture, **{name: tuple(map(float, value.reshape(-1)))})


def _texture_key(light: SpotLight | ProjectorLight) -> str:
    """The name Mitsuba gives a spot's texture (``texture``) or a projector's
    (``irradiance``)."""
    return "irradiance" if isinstance(light, ProjectorLight) else "texture"


def _entries(bad: np.ndarray, value: np.ndarray) -> str:
    """Where the ``bad`` entries of a large value (texels) are: their count and the first."""
    first = tuple(int(i) for i in np.argwhere(bad)[0])
    kind = "negative" if value[first] < 0 else "non-finite"
    return f"{int(bad.sum())} {kind} entries of {value.size}, the first at index {first}: {value[first]}"


def _not_negative(key: str, value: np.ndarray) -> np.ndarray:
    """An emitted radiance, an environment's texels or scale, refused where negative
    (naming the first negative entry of many)."""
    if (value < 0).any():
        if value.size > 16:
            raise SceneError(f"parameter {key!r} must not be negative: it has {_entries(value < 0, value)}")
        raise SceneError(f"parameter {key!r} must not be negative, got {np.squeeze(value).tolist()}")
    return value


class Attachment:
    """What :meth:`SceneParameters.attach` reads: the moving instances' parameter lanes
    from the float64 state, their shears and indices, which key drives which lanes, and
    the materials' reflectances; Dr.Jit arrays made by :meth:`SceneParameters.install`."""

    def __init__(self, params: SceneParameters, moving: np.ndarray, rows: np.ndarray,
                 drivers: list[tuple[str, np.ndarray]], lights: list[int]):
        self.moving = moving
        # Per instance parameter: (key, the lanes its values go to) for each grad-enabled key.
        self.sources = {name: [] for name in INSTANCE_PARAMETERS}
        for key, lanes in drivers:
            self.sources[key.rsplit(".", 1)[1]].append((key, device_array(UInt32, lanes.astype(np.uint32))))
        # The lights with derivatives (indices into scene.lights) and their grad-enabled keys.
        self.lights = lights
        self.grad_lights = sorted(key for key in params.grad_enabled_keys()
                                  if params._split(key)[0] == "light")
        self.grad_materials = sorted(key for key in params.grad_enabled_keys()
                                     if params._split(key)[0] == "material")
        # The mesh attributes' grad-enabled keys, each with where its values go in the
        # material table's corner values (float indices into them, and into the key's values).
        self.grad_meshes = {key: params._attribute_scatter(key) for key in params.grad_enabled_keys()
                            if params._split(key)[0] == "mesh"}
        # The area emitters' and the environment's grad-enabled keys.
        self.grad_emitters = sorted(key for key in params.grad_enabled_keys()
                                    if params._split(key)[0] in ("emitter", "environment"))
        # The material table's installed arrays, detached: attach scatters into copies.
        self.materials = {key: dr.detach(value)
                          for key, value in params.scene.bsdfs.state().items()}
        if not len(moving):
            return
        state = params._state
        self.base = {name: _owned_lanes(ARRAY_TYPE[name], state[name][rows]) for name in PART_INDEX}
        if self.sources["to_world"]:
            self.base["to_world"] = _owned_lanes(Matrix4f64, state["to_world"][rows])
            whole = np.concatenate([lanes for key, lanes in drivers if key.endswith(".to_world")])
            self.whole = dr.zeros(Bool, len(moving))
            dr.scatter(self.whole, True, device_array(UInt32, whole.astype(np.uint32)))
            dr.eval(self.whole)
        shear = np.zeros((len(moving), 4, 4))
        shear[:, :3, :3] = state["shear"][rows]
        shear[:, 3, 3] = 1.0
        self.shear = Transform(_owned_lanes(Matrix4f, shear), _owned_lanes(Matrix4f, affine_inverse(shear)))
        self.index = device_array(UInt32, moving.astype(np.uint32))

    def key(self) -> tuple:
        """The Python values :meth:`SceneParameters.attach` traces with."""
        return (self.moving.tobytes(),
                tuple((name, tuple(key for key, _ in entries)) for name, entries in self.sources.items()),
                tuple(self.grad_materials), tuple(self.lights), tuple(self.grad_lights),
                tuple(self.grad_emitters), tuple(self.grad_meshes))


class MaterialKey(NamedTuple):
    """What a material parameter key names: the scene's material (index), its parameter,
    its form (COLOR, NUMBER or TEXELS), which part of a blend or mask holds it (None: the
    material's own), the table row holding it, and for a checkerboard's colour which."""

    material: int
    parameter: str
    form: str
    part: int | None
    row: int
    #: For a checkerboard's colour: "color0" or "color1" (None for other keys).
    field: str | None = None


def _material_keys(scene) -> dict[str, MaterialKey]:
    """Every material parameter :func:`traverse` exposes (module docstring), the parameters
    of a blend's or mask's BSDFs as ``<material>.<part>.<parameter>`` with Mitsuba's part
    names (``bsdf_0``, ``bsdf_1``, ``nested_bsdf``)."""
    keys = {}
    table = scene.bsdfs
    for i, name in enumerate(scene.material_names):
        material = scene.materials[name]
        places = [(name, material, None, i)]
        if material.parts is not None:
            places += [(f"{name}.{part_key}", part, k, table.part_rows[i][k])
                       for k, (part, part_key) in enumerate(zip(material.parts, material.lobe.part_keys))
                       if part_key is not None]
        for prefix, owner, part, row in places:
            # (A normal map's texture is filed as a parameter of the BSDF it tilts.)
            maps = ({NORMAL_MAP: NORMAL_MAP_PARAMETERS[NORMAL_MAP]} if owner.normal_map is not None else
                    {BUMP_MAP: HEIGHTS} if owner.bump_map is not None else {})
            for parameter, spec in {**owner.lobe.parameters, **getattr(owner.lobe, "traversed", {}),
                                    **maps}.items():
                if parameter not in maps and (not spec.differentiable or not getattr(
                        owner.lobe, "exposed", _always)(owner.values, parameter)):
                    continue
                texture = table.texture(row, parameter)
                if texture is None:
                    keys[f"{prefix}.{parameter}"] = MaterialKey(i, parameter, spec.kind, part, row)
                elif table.textures.textures[texture].type == "bitmap":
                    keys[f"{prefix}.{parameter}.data"] = MaterialKey(i, parameter, TEXELS, part, row)
                elif table.textures.textures[texture].type == "checkerboard":
                    # (A mesh attribute's or volume's values belong to their file: no parameter.)
                    for field in ("color0", "color1"):
                        keys[f"{prefix}.{parameter}.{field}"] = MaterialKey(i, parameter, spec.kind,
                                                                            part, row, field)
    return keys


def _always(values: dict, key: str) -> bool:
    """Every differentiable parameter of a type without an ``exposed`` rule is exposed."""
    return True


def _parameter(lobe, name: str):
    """The Parameter of a key traverse exposes: a material's parameter, or where the lobe
    exposes a key of its own (a derived value) by that name, that one."""
    traversed = {**getattr(lobe, "traversed", {}), NORMAL_MAP: NORMAL_MAP_PARAMETERS[NORMAL_MAP],
                 BUMP_MAP: HEIGHTS}
    return traversed[name] if name in traversed else lobe.parameters[name]


def _owned_lanes(array_type: type, values: np.ndarray) -> Any:
    """Per-lane ``array_type`` (a vector or 4x4 matrix type, float32 or float64) from (M, k)
    or (M, 4, 4) values, each component a :func:`~instancing.core.backend.device_array`, so
    that the per-step kernels are the same every step (one lane included).
    """
    wide = array_type in (Array3f64, Matrix4f64)
    component, dtype = (Float64, np.float64) if wide else (Float, np.float32)
    values = np.asarray(values, dtype)
    if array_type in (Matrix4f, Matrix4f64):
        entries = device_arrays(component, *[values[:, r, c] for r in range(4) for c in range(4)])
        return array_type(*[dr.value_t(array_type)(*entries[4 * r:4 * r + 4]) for r in range(4)])
    return array_type(*device_arrays(component, *values.T))


def _square_host_lanes(value: Any, width: int, components: int) -> bool:
    """Whether ``value`` for a group of ``width`` members is a NumPy array or nested list
    of shape (width, width) with width == ``components``: Dr.Jit would read it as
    components by members, silently transposing a members-by-components array."""
    if dr.is_array_v(value) or width != components:
        return False
    try:
        return np.shape(value) == (width, width)
    except ValueError:  # (a ragged nested list: Dr.Jit's conversion refuses it)
        return False


def _detached_numpy(value: Any) -> np.ndarray:
    """A Dr.Jit value as float64 NumPy, one row per lane: vectors (n, k), matrices
    (n, 4, 4), numbers (n, 1); texels as their (H, W, C) tensor."""
    arr = np.array(dr.detach(value), np.float64)
    if isinstance(value, TensorXf):
        return arr
    if isinstance(value, (Matrix4f, Matrix4f64)):
        return arr.reshape(4, 4, -1).transpose(2, 0, 1)
    return arr.reshape(-1, dr.width(value)).T


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
