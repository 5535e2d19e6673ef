"""The scene-file form of an affine transform: a 4x4 matrix, or a list of operations
(``translate``, ``scale``, ``rotate``, ``reflect``, ``matrix``, ``look_at``) composed left to
right, as Mitsuba's ``<transform>`` children. Read by the scene files' ``to_world`` entries
and by the textures' ``to_uv``; every malformed entry is a :class:`SceneError` naming it."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import drjit.scalar as ds
import numpy as np

from . import transform as tf
from .arguments import is_real
from .errors import SceneError, TransformError



#: Numbers each operation takes from an entry (reflect takes its axis in its name).
_WIDTHS = {"translate": 3, "scale": 3, "rotate": 4, "matrix": 16, "look_at": 9}


def _number_list(value: Any, n: int, what: str, i: int, key: str) -> list[float]:
    """``n`` numbers of operation ``i``'s ``key`` (named as ``what[i].key`` when malformed)."""
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or not all(type(c) is float or is_real(c) for c in value)):
        raise SceneError(f"{what}[{i}].{key}: expected {n} numbers, got {value!r}")
    return [float(c) for c in value]


def parse_transform(value: Any, what: str = "to_world") -> tf.Transform:
    """A float64 :class:`~instancing.core.transform.Transform` from a 4x4 matrix or a list of operations."""
    fwd, inv = parse_transforms([value], lambda i: what)
    return tf.Transform(ds.Matrix4f64(fwd[0]), ds.Matrix4f64(inv[0]))


def parse_transforms(values: Sequence[Any], what: Callable[[int], str]) -> tuple[np.ndarray, np.ndarray]:
    """Float64 matrices and inverses, (n, 4, 4) each, of n transforms, each a 4x4 matrix or a
    list of operations.

    Each entry is read into the names of its operations (its signature) and their numbers;
    the entries of one signature are then built and composed as one NumPy batch, every
    inverse assembled from the operations' inverses in reverse order.

    Raises:
        SceneError: naming the first malformed entry (``what(i)`` for entry i).
    """
    signatures: list[tuple[str, ...]] = []
    numbers: list[list[float]] = []
    for i, value in enumerate(values):
        try:
            signature, args = _read(value, what(i))
        except SceneError:
            parse_transforms(values[:i], what)  # (an earlier entry's value error comes first)
            raise
        signatures.append(signature)
        numbers.append(args)
    groups: dict[tuple[str, ...], list[int]] = {}
    for i, signature in enumerate(signatures):
        groups.setdefault(signature, []).append(i)
    fwd, inv = np.empty((len(values), 4, 4)), np.empty((len(values), 4, 4))
    refused = []
    for signature, rows in groups.items():
        try:
            fwd[rows], inv[rows] = _composed(signature, np.array([numbers[i] for i in rows], np.float64),
                                             "to_world")
        except TransformError:
            refused.extend(rows)
    for i in sorted(refused):
        # Entry by entry, in order, so that the error names the first culprit.
        try:
            fwd[i], inv[i] = _composed(signatures[i], np.array([numbers[i]], np.float64), what(i))
        except TransformError as err:
            msg = str(err)
            raise SceneError(msg if msg.startswith(what(i)) else f"{what(i)}: {msg}") from None
    return fwd, inv


def _read(value: Any, what: str) -> tuple[tuple[str, ...], list[float]]:
    """The signature and numbers of one transform entry (a whole matrix: signature
    ``("4x4",)``)."""
    operations = type(value) is list and (not value or type(value[0]) is dict)
    if not operations and (isinstance(value, np.ndarray) or (
            isinstance(value, (list, tuple)) and len(value) == 4
            and all(isinstance(r, (list, tuple)) for r in value))):
        return ("4x4",), _matrix_numbers(value, what)
    if not isinstance(value, (list, tuple)):
        raise SceneError(f"{what}: expected a 4x4 matrix or a list of operations, got {value!r}")
    signature, numbers = [], []
    for i, op in enumerate(value):
        name, args = _read_operation(op, what, i)
        signature.append(name)
        numbers.extend(args)
    return tuple(signature), numbers


def _matrix_numbers(value: Any, what: str) -> list[float]:
    """A 4x4 matrix's 16 entries, row by row (its invertibility is checked when it is built)."""
    require_numbers(value, what)
    try:
        return tf.matrix_array(value, what).ravel().tolist()
    except TransformError as err:
        raise SceneError(str(err)) from None


def _read_operation(op: Any, what: str, i: int) -> tuple[str, list[float]]:
    """Operation ``i``'s name (reflect: with its axis, ``reflect x``) and numbers."""
    if not isinstance(op, dict) or len(op) != 1:
        raise SceneError(f"{what}[{i}]: each operation is an object with exactly one key, got {op!r}")
    (name, arg), = op.items()
    if name == "translate":
        return name, _number_list(arg, 3, what, i, "translate")
    if name == "scale":
        if type(arg) is float or is_real(arg):
            return name, [float(arg)] * 3
        return name, _number_list(arg, 3, what, i, "scale")
    if name == "rotate":
        if not isinstance(arg, dict) or set(arg) != {"axis", "angle"}:
            raise SceneError(f"{what}[{i}].rotate: expected {{'axis': [x, y, z], 'angle': degrees}}, got {arg!r}")
        angle = arg["angle"]
        if not is_real(angle):
            raise SceneError(f"{what}[{i}].rotate: angle must be a number, got {angle!r}")
        return name, _number_list(arg["axis"], 3, what, i, "rotate.axis") + [float(angle)]
    if name == "reflect":
        if not isinstance(arg, str) or arg not in ("x", "y", "z"):
            raise SceneError(f"{what}[{i}].reflect: axis must be 'x', 'y' or 'z', got {arg!r}")
        return f"reflect {arg}", []
    if name == "matrix":
        return name, _matrix_numbers(arg, f"{what}[{i}].matrix")
    if name == "look_at":
        if not isinstance(arg, dict) or set(arg) != {"origin", "target", "up"}:
            raise SceneError(f"{what}[{i}].look_at: expected {{'origin', 'target', 'up'}}, got {arg!r}")
        return name, [c for k in ("origin", "target", "up")
                      for c in _number_list(arg[k], 3, what, i, f"look_at.{k}")]
    raise SceneError(f"{what}[{i}]: unknown operation {name!r}; expected one of translate, rotate, "
                     "scale, reflect, matrix, look_at")


def _composed(signature: tuple[str, ...], block: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Matrices and inverses (k, 4, 4) of k entries of one signature (their numbers: the
    rows of ``block``), composed left to right: ``A @ B`` applies B first, and its inverse is
    B^-1 @ A^-1.

    Raises:
        TransformError: an entry's operation is singular or non-finite (its message names
            the operation; ``what``: the entry, for a matrix).
    """
    fwd = inv = None
    offset = 0
    for p, name in enumerate(signature):
        width = _WIDTHS.get(name, 16 if name == "4x4" else 0)
        op_fwd, op_inv = _built(name, block[:, offset:offset + width],
                                what if name == "4x4" else f"{what}[{p}].matrix")
        offset += width
        # (Overflowing products are refused later, where float32 cannot hold them.)
        with np.errstate(over="ignore", invalid="ignore"):
            fwd = op_fwd if fwd is None else fwd @ op_fwd
            inv = op_inv if inv is None else op_inv @ inv
    if fwd is None:
        fwd = inv = _identities(len(block))
    return fwd, inv


def _identities(k: int) -> np.ndarray:
    return np.repeat(np.eye(4)[None], k, axis=0)


def _built(name: str, args: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """One operation's matrices and inverses for the rows of ``args``. Rows that the batch
    formulas do not take (non-finite numbers, zero scales or axes, and every look_at) are
    built by the scalar builder of :mod:`instancing.core.transform`, which refuses the
    invalid ones."""
    k = len(args)
    fwd, inv = _identities(k), _identities(k)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        finite = np.isfinite(args).all(axis=1)
        if name == "translate":
            fwd[:, :3, 3], inv[:, :3, 3] = args, -args
            single = ~finite
        elif name == "scale":
            reciprocal = 1.0 / args
            single = ~finite | ~np.isfinite(reciprocal).all(axis=1)
            rows = np.arange(k)[:, None]
            fwd[rows, range(3), range(3)], inv[rows, range(3), range(3)] = args, reciprocal
        elif name == "rotate":
            axis, angle = args[:, :3], args[:, 3]
            length = np.sqrt((axis * axis).sum(axis=1))
            # (Lengths whose squares over- or underflow are the scalar builder's.)
            single = ~finite | ~((length > 1e-150) & (length < 1e150))
            x, y, z = (axis / length[:, None]).T
            radians = np.deg2rad(np.fmod(angle, 360.0))
            rows = np.stack([np.stack(r, axis=-1) for r in tf.rotation_rows(x, y, z, np.sin(radians),
                                                                            np.cos(radians))], axis=1)
            fwd[:, :3, :3], inv[:, :3, :3] = rows, np.swapaxes(rows, 1, 2)
        elif name.startswith("reflect"):
            fwd[:, "xyz".index(name[-1]), "xyz".index(name[-1])] = -1.0
            inv = fwd
            single = np.zeros(k, bool)
        elif name in ("matrix", "4x4"):
            fwd = args.reshape(k, 4, 4)
            try:
                inv = tf.checked_affine_inverse(fwd if k > 1 else fwd[0], what).reshape(k, 4, 4)
                single = np.zeros(k, bool)
            except TransformError:
                if k == 1:
                    raise
                single = np.ones(k, bool)
        else:
            single = np.ones(k, bool)
    for j in np.flatnonzero(single):
        fwd[j], inv[j] = _scalar_builder(name, args[j].tolist(), what).to_numpy()
    return fwd, inv


def _scalar_builder(name: str, args: list[float], what: str) -> tf.Transform:
    """One operation built by :mod:`instancing.core.transform`'s builder."""
    if name == "translate":
        return tf.translate(args)
    if name == "scale":
        return tf.scale(args)
    if name == "rotate":
        return tf.rotate(args[:3], args[3])
    if name == "look_at":
        return tf.look_at(args[:3], args[3:6], args[6:])
    return tf.from_matrix(np.reshape(args, (4, 4)), what)


def require_numbers(value: Any, what: str) -> None:
    """Refuse strings, booleans, complex numbers and integers beyond float64's range among a
    matrix's entries (nested lists, or an array of one or more matrices), which NumPy would
    turn into numbers ("1" and true into 1.0, 1+2j into 1) or fail to; other malformed
    matrices are left to the matrix checks."""
    if isinstance(value, np.ndarray) and (value.dtype.kind != "O" or value.ndim != 2):
        if value.dtype.kind not in "iuf":
            raise SceneError(f"{what}: matrix entries must be numbers, got an array of {value.dtype}")
        return
    rows = value.tolist() if isinstance(value, np.ndarray) else value
    for i, row in enumerate(rows if isinstance(rows, (list, tuple)) else ()):
        for j, entry in enumerate(row.tolist() if isinstance(row, np.ndarray) else
                                  row if isinstance(row, (list, tuple)) else ()):
            if not (is_real(entry) or isinstance(entry, (list, tuple))):
                raise SceneError(f"{what}[{i}][{j}]: matrix entries must be numbers, got {entry!r}")
