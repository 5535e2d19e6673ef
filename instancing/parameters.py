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

An instance's ``to_world`` is split by :func:`instancing.transform.decompose`
into ``translate(t) @ rotate_quaternion(q) @ scale(s) @ H`` (H: the shear,
fixed unless ``to_world`` itself is set) the first time one of its
parameters is read or set. ``update()`` installs the instances whose
parameters changed or carry derivatives; every other instance keeps the
scene's stored matrices bit for bit. Transforms with derivatives are rebuilt
per lane from the parts; their inverse comes from the parts' inverses in
reverse order (or, for a grad-enabled ``to_world``, from ``dr.rcp`` of the
matrix), so gradients reach the parameters through the inverse matrix that
the intersection uses. World bounds and the acceleration structure are
rebuilt from the detached values.

State is kept per touched instance only: a scene with a million instances
costs nothing per instance here until its parameters are read or set (values
are created lazily, and the float64 matrices of untouched instances are the
scene's own).
"""

from __future__ import annotations

from collections.abc import Iterator, MutableMapping
from typing import Any

import numpy as np

from .backend import Array3f, Array4f, Bool, Float, Matrix4f, UInt32, device_arrays, dr
from .errors import SceneError
from .transform import (Transform, affine_inverse, check_affine_matrix, decompose, from_matrix,
                        rotate_quaternion, scale, translate)

#: Per-instance parameter names, in key order.
INSTANCE_PARAMETERS = ("translation", "rotation", "scale", "to_world")
#: Where each part sits in an instance's parts [t, q, s, H].
PART_INDEX = {"translation": 0, "rotation": 1, "scale": 2}


class SceneParameters(MutableMapping):
    """Differentiable parameters of a scene (see the module docstring)."""

    def __init__(self, scene):
        self.scene = scene
        self._ids = scene.instance_ids
        self._materials = list(scene.material_names)
        # Per touched instance: its float64 matrix and its parts [t, q, s, H].
        self._matrix: dict[int, np.ndarray] = {}
        self._parts: dict[int, list[np.ndarray]] = {}
        refl = np.array([scene.materials[m]["reflectance"] for m in self._materials], np.float64)
        self._reflectance = refl.reshape(-1, 3)
        self._values: dict[str, Any] = {}
        self._dirty: set[str] = set()
        # Instances installed with derivatives by the last update (re-installed from the
        # float64 state once they stop moving).
        self._attached: set[int] = set()

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
        changed = self._absorb_changes()
        self._dirty.clear()
        self._install_transforms(changed)
        self._install_reflectance()
        return self

    def _absorb_changes(self) -> set[int]:
        """Fold assigned values into the detached float64 state (validating them); returns
        the instances whose matrix changed."""
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
                changed.setdefault(self._ids.index(owner), set()).add(name)
        for i, names in changed.items():
            where = f"parameter {self._ids[i]!r}"
            parts = self._touch(i)
            if "to_world" in names:
                if len(names) > 1:
                    raise SceneError(f"{where}: set either to_world or its parts "
                                     f"({sorted(names - {'to_world'})}), not both")
                m = _detached_numpy(self._values[f"{self._ids[i]}.to_world"]).reshape(4, 4)
                check_affine_matrix(m, f"{where} to_world")
                self._matrix[i] = m
                parts[:] = decompose(m)
                for name in ("translation", "rotation", "scale"):
                    self._values.pop(f"{self._ids[i]}.{name}", None)
                continue
            for name in names:
                parts[PART_INDEX[name]] = _detached_numpy(self._values[f"{self._ids[i]}.{name}"])
            translation, rotation, scale_, shear = parts
            if not rotation.any():
                raise SceneError(f"{where}.rotation: the zero quaternion is not a rotation")
            if (scale_ == 0).any():
                raise SceneError(f"{where}.scale: a zero factor makes the transform singular")
            m = _compose_numpy(translation, rotation, scale_, shear)
            check_affine_matrix(m, f"{where} to_world")
            self._matrix[i] = m
            self._values.pop(f"{self._ids[i]}.to_world", None)
        return set(changed)

    def _grad_instances(self, name: str) -> list[int]:
        """Instances whose parameter ``name`` is present and grad-enabled."""
        return [self._ids.index(key.rsplit(".", 1)[0]) for key, v in self._values.items()
                if key.rsplit(".", 1)[1] == name and key.rsplit(".", 1)[0] in self._ids
                and dr.grad_enabled(v)]

    def _install_transforms(self, changed: set[int]) -> None:
        """Install the changed and the grad-enabled instances; the others keep their matrices."""
        parts = {name: self._grad_instances(name) for name in INSTANCE_PARAMETERS}
        moving = sorted(set().union(*parts.values()))
        table = self.scene.instances
        touched = sorted(changed | set(moving) | self._attached)
        self._attached = set(moving)
        if not (touched or dr.grad_enabled(table.inverse_rows)):
            return
        # Per lane, every instance's stored transform (gathered in the kernel, detached);
        # the touched instances' float64 state rounded once (with its float64 inverse)
        # spread over it, then the moving ones' AD-attached transforms.
        lanes = table.stored_transform()
        if touched:
            state = np.array([self._matrix[i] for i in touched])
            lanes = _spread(Transform(_owned_lanes(Matrix4f, state),
                                      _owned_lanes(Matrix4f, affine_inverse(state))), lanes, touched)
        if moving:
            lanes = _spread(self._moving_lanes(moving, parts), lanes, moving)
        # Only the touched instances change: the scene checks, bounds and re-files only
        # those, from their float64 state.
        matrices = np.array([self._matrix[i] for i in touched]).reshape(-1, 4, 4)
        self.scene.set_transforms(lanes, matrices=matrices, moving=np.array(moving, np.int64),
                                  changed=np.array(touched, np.int64))

    def _moving_lanes(self, moving: list[int], parts: dict[str, list[int]]) -> Transform:
        """Per-lane transforms of the ``moving`` instances (lane k: instance moving[k]):
        translate(t) @ rotate_quaternion(q) @ scale(s) @ H, with the grad-enabled
        parameters scattered into their instance's lane."""
        t = self._lanes(Array3f, moving, "translation", parts["translation"])
        q = self._lanes(Array4f, moving, "rotation", parts["rotation"])
        s = self._lanes(Array3f, moving, "scale", parts["scale"])
        # Evaluate the scattered lanes now, in one kernel of a fixed shape (left pending,
        # the scatters fuse differently with later work and force re-compilation).
        dr.eval(t, q, s)
        shear = np.zeros((len(moving), 4, 4))
        shear[:, :3, :3] = [self._parts[i][3] for i in moving]
        shear[:, 3, 3] = 1.0
        shear_lanes = Transform(_owned_lanes(Matrix4f, shear),
                                _owned_lanes(Matrix4f, affine_inverse(shear)))
        lanes = translate(t) @ rotate_quaternion(q) @ scale(s) @ shear_lanes
        if parts["to_world"]:
            # Instances optimised through their whole matrix: inverted per lane with AD.
            m = self._lanes(Matrix4f, moving, "to_world", parts["to_world"])
            whole = from_matrix(m, "to_world")
            use = dr.zeros(Bool, len(moving))
            dr.scatter(use, True, UInt32([moving.index(i) for i in parts["to_world"]]))
            lanes = Transform(dr.select(use, whole.matrix, lanes.matrix),
                              dr.select(use, whole.inverse_matrix, lanes.inverse_matrix))
        return lanes

    def _lanes(self, array_type: type, moving: list[int], name: str, grad: list[int]) -> Any:
        """One lane per moving instance from the float64 state, grad-enabled values scattered in."""
        if array_type is Matrix4f:
            lanes = _owned_lanes(Matrix4f, np.array([self._matrix[i] for i in moving]))
        else:
            base = np.array([self._parts[i][PART_INDEX[name]] for i in moving])
            lanes = _owned_lanes(array_type, base)
        for i in grad:
            dr.scatter(lanes, self._values[f"{self._ids[i]}.{name}"], UInt32(moving.index(i)))
        return lanes

    def _install_reflectance(self) -> None:
        lanes = _owned_lanes(Array3f, self._reflectance)
        for j, m in enumerate(self._materials):
            value = self._values.get(f"{m}.reflectance")
            if value is not None and dr.grad_enabled(value):
                dr.scatter(lanes, value, UInt32(j))
        self.scene.reflectance = lanes


def _owned_lanes(array_type: type, values: np.ndarray) -> Any:
    """Per-lane ``array_type`` (``Array3f``, ``Array4f`` or ``Matrix4f``) from (M, k) or
    (M, 4, 4) values, each component a :func:`~instancing.backend.device_array`, so that
    the per-step kernels are the same every step (one lane included).
    """
    values = np.asarray(values, np.float32)
    if array_type is Matrix4f:
        entries = device_arrays(Float, *[values[:, r, c] for r in range(4) for c in range(4)])
        return Matrix4f(*[Array4f(*entries[4 * r:4 * r + 4]) for r in range(4)])
    return array_type(*device_arrays(Float, *values.T))


def _spread(new: Transform, base: Transform, instances: list[int]) -> Transform:
    """Per-instance transforms: lane k of ``new`` for instance ``instances[k]``, ``base`` elsewhere.

    A gather and a select per entry (side-effect free, so the kernel is the same
    every step); the lane map is made in Dr.Jit's own memory for the same reason
    (see :func:`_owned_lanes`).
    """
    dr.eval(new.matrix, new.inverse_matrix)
    n = dr.width(base.matrix)
    index = UInt32(list(instances))
    slot, chosen = dr.zeros(UInt32, n), dr.zeros(Bool, n)
    dr.scatter(slot, dr.arange(UInt32, len(instances)), index)
    dr.scatter(chosen, True, index)
    dr.eval(slot, chosen)

    def entries(m_new: Matrix4f, m_base: Matrix4f) -> Matrix4f:
        def entry(r: int, c: int) -> Any:
            value = m_new[r][c]
            value = value if dr.width(value) == 1 else dr.gather(type(value), value, slot)
            return dr.select(chosen, value, m_base[r][c])

        return Matrix4f(*[Array4f(*[entry(r, c) for c in range(4)]) for r in range(4)])

    return Transform(entries(new.matrix, base.matrix), entries(new.inverse_matrix, base.inverse_matrix))


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
