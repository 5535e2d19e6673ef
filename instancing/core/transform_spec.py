"""The scene-file form of an affine transform: a 4x4 matrix, or a list of operations
(``translate``, ``scale``, ``rotate``, ``reflect``, ``matrix``, ``look_at``) composed left to
right, as Mitsuba's ``<transform>`` children. Read by the scene files' ``to_world`` entries
and by the textures' ``to_uv``; every malformed entry is a :class:`SceneError` naming it."""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from . import transform as tf
from .arguments import is_real
from .errors import SceneError, TransformError


def _number_list(value: Any, n: int, what: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != n or not all(map(is_real, value)):
        raise SceneError(f"{what}: expected {n} numbers, got {value!r}")
    return [float(c) for c in value]


def _scale_arg(value: Any, what: str) -> Any:
    if is_real(value):
        return float(value)
    return _number_list(value, 3, what)


def parse_transform(value: Any, what: str = "to_world") -> tf.Transform:
    """A float64 :class:`~instancing.core.transform.Transform` from a 4x4 matrix or a list of operations."""
    try:
        if isinstance(value, np.ndarray) or (isinstance(value, (list, tuple)) and len(value) == 4
                                             and all(isinstance(r, (list, tuple)) for r in value)):
            require_numbers(value, what)
            return tf.from_matrix(value, what)
        if not isinstance(value, (list, tuple)):
            raise SceneError(f"{what}: expected a 4x4 matrix or a list of operations, got {value!r}")
        result = tf.identity()
        for i, op in enumerate(value):
            result = result @ _parse_operation(op, f"{what}[{i}]")
        return result
    except TransformError as err:
        msg = str(err)
        raise SceneError(msg if msg.startswith(what) else f"{what}: {msg}") from None


def require_numbers(value: Any, what: str) -> None:
    """Refuse strings, booleans and complex numbers among a matrix's entries (nested lists,
    or an array of one or more matrices), which NumPy would turn into numbers ("1" and true
    into 1.0, 1+2j into 1); other malformed matrices are left to the matrix checks."""
    if isinstance(value, np.ndarray) and (value.dtype.kind != "O" or value.ndim != 2):
        if value.dtype.kind not in "iuf":
            raise SceneError(f"{what}: matrix entries must be numbers, got an array of {value.dtype}")
        return
    rows = value.tolist() if isinstance(value, np.ndarray) else value
    for i, row in enumerate(rows if isinstance(rows, (list, tuple)) else ()):
        for j, entry in enumerate(row.tolist() if isinstance(row, np.ndarray) else
                                  row if isinstance(row, (list, tuple)) else ()):
            if isinstance(entry, (bool, np.bool_)) or not isinstance(entry, (numbers.Real, list, tuple)):
                raise SceneError(f"{what}[{i}][{j}]: matrix entries must be numbers, got {entry!r}")


def _parse_operation(op: Any, what: str) -> tf.Transform:
    if not isinstance(op, dict) or len(op) != 1:
        raise SceneError(f"{what}: each operation is an object with exactly one key, got {op!r}")
    (name, arg), = op.items()
    if name == "translate":
        return tf.translate(_number_list(arg, 3, f"{what}.translate"))
    if name == "scale":
        return tf.scale(_scale_arg(arg, f"{what}.scale"))
    if name == "rotate":
        if not isinstance(arg, dict) or set(arg) != {"axis", "angle"}:
            raise SceneError(f"{what}.rotate: expected {{'axis': [x, y, z], 'angle': degrees}}, got {arg!r}")
        angle = arg["angle"]
        if not is_real(angle):
            raise SceneError(f"{what}.rotate: angle must be a number, got {angle!r}")
        return tf.rotate(_number_list(arg["axis"], 3, f"{what}.rotate.axis"), float(angle))
    if name == "reflect":
        return tf.reflect(arg)
    if name == "matrix":
        require_numbers(arg, f"{what}.matrix")
        return tf.from_matrix(arg, f"{what}.matrix")
    if name == "look_at":
        if not isinstance(arg, dict) or set(arg) != {"origin", "target", "up"}:
            raise SceneError(f"{what}.look_at: expected {{'origin', 'target', 'up'}}, got {arg!r}")
        return tf.look_at(*(_number_list(arg[k], 3, f"{what}.look_at.{k}")
                            for k in ("origin", "target", "up")))
    raise SceneError(f"{what}: unknown operation {name!r}; expected one of translate, rotate, "
                     "scale, reflect, matrix, look_at")
