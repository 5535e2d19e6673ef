"""``instancing.traverse``: the differentiable parameters of a scene.

In the spirit of ``mitsuba.traverse``: a mutable mapping from names to Dr.Jit
values, with ``update()`` pushing changes into the scene. Keys:

* ``"<instance id>.translation"`` (``Array3f``), ``"<instance id>.rotation"``
  (``Array4f``, a quaternion (x, y, z, w), normalized where it is used, so an
  optimiser step can never leave the rotation group), ``"<instance id>.scale"``
  (``Array3f``, per axis; a reflection is a negative z scale), and
  ``"<instance id>.to_world"`` (``Matrix4f``, the whole affine matrix, for
  shear);
* ``"<material>.reflectance"`` (``Array3f``).

Each instance's ``to_world`` is split once by :func:`instancing.transform.decompose`
into ``translate(t) @ rotate_quaternion(q) @ scale(s) @ H`` (H: the shear,
fixed unless ``to_world`` itself is set). ``update()`` rebuilds the per-lane
transforms from the parts; their inverse comes from the parts' inverses in
reverse order (or, for a grad-enabled ``to_world``, from ``dr.rcp`` of the
matrix), so gradients reach the parameters through the inverse matrix that
the intersection uses. World bounds and the acceleration structure are
rebuilt from the detached values.

Values are created lazily: a scene with a million instances does not create
four million Dr.Jit arrays unless they are read.
"""

from __future__ import annotations

from collections.abc import Iterator, MutableMapping
from typing import Any

import numpy as np

from .backend import Array3f, Array4f, Bool, Matrix4f, UInt32, dr
from .errors import SceneError
from .transform import (Transform, affine_inverse, check_affine_matrix, decompose, from_matrix,
                        matrices_to_lanes, rotate_quaternion, scale, translate)

#: Per-instance parameter names, in key order.
INSTANCE_PARAMETERS = ("translation", "rotation", "scale", "to_world")


class SceneParameters(MutableMapping):
    """Differentiable parameters of a scene (see the module docstring)."""

    def __init__(self, scene):
        self.scene = scene
        self._ids = list(scene.instance_ids)
        self._index = {name: i for i, name in enumerate(self._ids)}
        self._materials = list(scene.material_names)
        self._translation, self._rotation, self._scale, self._shear = \
            decompose(scene.description.to_world)
        self._to_world = np.array(scene.description.to_world, np.float64)
        refl = np.array([scene.materials[m]["reflectance"] for m in self._materials], np.float64)
        self._reflectance = refl.reshape(-1, 3)
        self._values: dict[str, Any] = {}
        self._dirty: set[str] = set()

    # -- mapping interface ---------------------------------------------------------------------

    def _split(self, key: str) -> tuple[str, str]:
        if not isinstance(key, str) or "." not in key:
            raise KeyError(key)
        owner, name = key.rsplit(".", 1)
        if name in INSTANCE_PARAMETERS and owner in self._index:
            return "instance", name
        if name == "reflectance" and owner in self._materials:
            return "material", name
        raise KeyError(key)

    def __getitem__(self, key: str) -> Any:
        if key not in self._values:
            kind, name = self._split(key)
            owner = key.rsplit(".", 1)[0]
            self._values[key] = self._initial_value(kind, name, owner)
        return self._values[key]

    def _initial_value(self, kind: str, name: str, owner: str) -> Any:
        if kind == "material":
            return Array3f(*self._reflectance[self._materials.index(owner)].tolist())
        i = self._index[owner]
        if name == "translation":
            return Array3f(*self._translation[i].tolist())
        if name == "rotation":
            return Array4f(*self._rotation[i].tolist())
        if name == "scale":
            return Array3f(*self._scale[i].tolist())
        return Matrix4f(self._to_world[i].tolist())

    def __setitem__(self, key: str, value: Any) -> None:
        kind, name = self._split(key)
        expected = {"translation": Array3f, "rotation": Array4f, "scale": Array3f,
                    "to_world": Matrix4f, "reflectance": Array3f}[name]
        try:
            value = value if isinstance(value, expected) else expected(value)
        except (TypeError, RuntimeError) as exc:
            raise SceneError(f"parameter {key!r}: cannot convert {value!r} to "
                             f"{expected.__name__} ({exc})") from None
        if dr.width(value) != 1:
            raise SceneError(f"parameter {key!r}: expected one value, got width {dr.width(value)}")
        self._values[key] = value
        self._dirty.add(key)

    def __delitem__(self, key: str) -> None:
        raise TypeError("scene parameters cannot be removed")

    def __iter__(self) -> Iterator[str]:
        for name in self._ids:
            for p in INSTANCE_PARAMETERS:
                yield f"{name}.{p}"
        for m in self._materials:
            yield f"{m}.reflectance"

    def __len__(self) -> int:
        return len(self._ids) * len(INSTANCE_PARAMETERS) + len(self._materials)

    def __repr__(self) -> str:
        return f"SceneParameters({len(self._ids)} instances, {len(self._materials)} materials)"

    # -- update --------------------------------------------------------------------------------

    def update(self, values: Any = None) -> "SceneParameters":
        """Push changed and grad-enabled parameters into the scene.

        Args:
            values: optionally a mapping (e.g. a ``drjit.opt`` optimiser) whose
                entries are first assigned to the matching keys.

        Call it after every change and after every optimiser step: it also
        re-attaches the AD graph that ``dr.backward`` consumed.

        Raises:
            SceneError: a non-finite or singular transform, a zero scale or
                quaternion, or ``to_world`` set together with its parts.
        """
        if values is not None:
            for key in values.keys():
                if key in self:
                    self[key] = values[key]
        self._absorb_changes()
        self._dirty.clear()
        self._install_transforms()
        self._install_reflectance()
        return self

    def _absorb_changes(self) -> None:
        """Fold assigned values into the detached float64 state (validating them)."""
        changed: dict[int, set[str]] = {}
        for key in self._dirty:
            kind, name = self._split(key)
            owner = key.rsplit(".", 1)[0]
            value = _detached_numpy(self._values[key])
            if not np.isfinite(value).all():
                raise SceneError(f"parameter {key!r} has non-finite entries {value.tolist()}")
            if kind == "material":
                self._reflectance[self._materials.index(owner)] = value
            else:
                changed.setdefault(self._index[owner], set()).add(name)
        for i, names in changed.items():
            where = f"parameter {self._ids[i]!r}"
            if "to_world" in names:
                if len(names) > 1:
                    raise SceneError(f"{where}: set either to_world or its parts "
                                     f"({sorted(names - {'to_world'})}), not both")
                m = _detached_numpy(self._values[f"{self._ids[i]}.to_world"]).reshape(4, 4)
                check_affine_matrix(m, f"{where} to_world")
                self._to_world[i] = m
                parts = decompose(m)
                self._translation[i], self._rotation[i], self._scale[i], self._shear[i] = parts
                for name in ("translation", "rotation", "scale"):
                    self._values.pop(f"{self._ids[i]}.{name}", None)
                continue
            for name in names:
                value = _detached_numpy(self._values[f"{self._ids[i]}.{name}"])
                getattr(self, f"_{name}")[i] = value
            if not self._rotation[i].any():
                raise SceneError(f"{where}.rotation: the zero quaternion is not a rotation")
            if (self._scale[i] == 0).any():
                raise SceneError(f"{where}.scale: a zero factor makes the transform singular")
            m = _compose_numpy(self._translation[i], self._rotation[i], self._scale[i], self._shear[i])
            check_affine_matrix(m, f"{where} to_world")
            self._to_world[i] = m
            self._values.pop(f"{self._ids[i]}.to_world", None)

    def _grad_instances(self, name: str) -> list[int]:
        """Instances whose parameter ``name`` is present and grad-enabled."""
        return [self._index[key.rsplit(".", 1)[0]] for key, v in self._values.items()
                if key.rsplit(".", 1)[1] == name and key.rsplit(".", 1)[0] in self._index
                and dr.grad_enabled(v)]

    def _install_transforms(self) -> None:
        """Per-lane transforms of every instance; AD-attached for the grad-enabled ones."""
        parts = {name: self._grad_instances(name) for name in INSTANCE_PARAMETERS}
        moving = sorted(set().union(*parts.values()))
        if not moving:
            lanes = Transform(matrices_to_lanes(self._to_world),
                              matrices_to_lanes(affine_inverse(self._to_world)))
            self.scene.set_transforms(lanes, matrices=self._to_world, moving=np.zeros(0, np.int64))
            return
        # translate(t) @ rotate_quaternion(q) @ scale(s) @ H, per lane, with the
        # grad-enabled parameters scattered into their instance's lane.
        t = self._lanes(Array3f, self._translation, "translation", parts["translation"])
        q = self._lanes(Array4f, self._rotation, "rotation", parts["rotation"])
        s = self._lanes(Array3f, self._scale, "scale", parts["scale"])
        # Evaluate the scattered lanes now, in one kernel of a fixed shape (left pending,
        # the scatters fuse differently with later work and force re-compilation).
        dr.eval(t, q, s)
        shear = np.zeros_like(self._to_world)
        shear[:, :3, :3], shear[:, 3, 3] = self._shear, 1.0
        shear_lanes = Transform(matrices_to_lanes(shear), matrices_to_lanes(affine_inverse(shear)))
        lanes = translate(t) @ rotate_quaternion(q) @ scale(s) @ shear_lanes
        if parts["to_world"]:
            # Instances optimised through their whole matrix: inverted per lane with AD.
            m = self._lanes(Matrix4f, self._to_world, "to_world", parts["to_world"])
            whole = from_matrix(m, "to_world")
            use = dr.zeros(Bool, len(self._ids))
            dr.scatter(use, True, UInt32(np.array(parts["to_world"], np.uint32)))
            lanes = Transform(dr.select(use, whole.matrix, lanes.matrix),
                              dr.select(use, whole.inverse_matrix, lanes.inverse_matrix))
        self.scene.set_transforms(lanes, matrices=self._to_world, moving=np.array(moving))

    def _lanes(self, array_type: type, base: np.ndarray, name: str, grad: list[int]) -> Any:
        """One lane per instance from the float64 state, grad-enabled values scattered in."""
        if array_type is Matrix4f:
            lanes = matrices_to_lanes(base)
        else:
            lanes = array_type(*[np.ascontiguousarray(base[:, k], np.float32)
                                 for k in range(base.shape[1])])
        for i in grad:
            dr.scatter(lanes, self._values[f"{self._ids[i]}.{name}"], UInt32(i))
        return lanes

    def _install_reflectance(self) -> None:
        refl = np.ascontiguousarray(self._reflectance.astype(np.float32))
        lanes = Array3f(*[refl[:, k] for k in range(3)])
        for j, m in enumerate(self._materials):
            value = self._values.get(f"{m}.reflectance")
            if value is not None and dr.grad_enabled(value):
                dr.scatter(lanes, value, UInt32(j))
        self.scene.reflectance = lanes


def _detached_numpy(value: Any) -> np.ndarray:
    """A width-1 Dr.Jit value as float64 NumPy (matrices as (4, 4))."""
    arr = np.array(dr.detach(value), np.float64)
    return arr.reshape(4, 4) if isinstance(value, Matrix4f) else arr.reshape(-1)


def _compose_numpy(t: np.ndarray, q: np.ndarray, s: np.ndarray, shear: np.ndarray) -> np.ndarray:
    """float64 matrix of translate(t) @ rotate_quaternion(q) @ scale(s) @ H."""
    m = (translate(t) @ rotate_quaternion(q) @ scale(s)).to_numpy()[0]
    m[:3, :3] = m[:3, :3] @ shear
    return m


def traverse(scene) -> SceneParameters:
    """The differentiable parameters of ``scene`` (see :mod:`instancing.parameters`).

    Example::

        params = instancing.traverse(scene)
        dr.enable_grad(params["bunny.translation"])
        params.update()
        image = instancing.render(scene, "direct", spp=16)
    """
    return SceneParameters(scene)
