"""Checks of the numbers callers pass: sample counts, film sizes, depths, iterations,
scene-file values.

Python and NumPy numbers are accepted alike (a sweep over ``np.arange`` or values read
from an array hand out NumPy scalars) and integers are returned as Python ints; anything
else, booleans included, is refused naming the argument.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from .errors import SceneError


#: The largest float32 number: what the kernels read in float32 must not exceed it.
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: The largest integer read as a number: every number is read as a float64, and a larger
#: Python integer (a JSON file may hold one of any length) has none.
_LARGEST_INTEGER = int(np.finfo(np.float64).max)


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number, Python's or NumPy's, that a float64 holds (a bool
    is not, nor an integer beyond float64's range)."""
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and (type(value) is not int or -_LARGEST_INTEGER <= value <= _LARGEST_INTEGER))


def integer(name: str, value: Any, low: int | None = None, high: int | None = None,
            where: str = "", error: type[SceneError] = SceneError) -> int:
    """``value`` as a Python int, if it is an integer (Python's or NumPy's, not a bool) in
    [low, high] (None: no bound); else ``error`` naming ``name`` (after ``where``, the
    caller, file or place in a scene, when given) and the range."""
    if (not isinstance(value, numbers.Integral) or isinstance(value, bool)
            or (low is not None and value < low) or (high is not None and value > high)):
        bound = ("" if low is None else f" >= {low}") if high is None else f" in [{low}, {high}]"
        raise error(f"{where + ': ' if where else ''}{name} must be an integer{bound}, "
                    f"got {value!r}")
    return int(value)


def indices(name: str, values: Any, count: int, where: str, negative: bool = False,
            unique: bool = False) -> np.ndarray:
    """``values`` (an index or a sequence or array of them) as an int64 array, if every one
    is an integer (Python's or NumPy's, not a bool) in [0, count) (from -count with
    ``negative``: counted from the end, as NumPy does) and, with ``unique``, none repeats;
    else :class:`IndexError` (out of range) or :class:`TypeError` naming ``name`` after
    ``where`` and the first culprit."""
    array = np.asarray(values)
    if array.dtype == object or array.dtype == bool or not (
            array.size == 0 or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"{where}: {name} must be integer indices, got {values!r}"[:300])
    array = array.astype(np.int64)
    low = -count if negative else 0
    outside = (array < low) | (array >= count)
    if outside.any():
        raise IndexError(f"{where}: {name} holds {int(array[outside].flat[0])}, outside "
                         f"[{low}, {count}) ({count} in all)")
    if unique and len(np.unique(array)) < array.size:
        values, counts = np.unique(array, return_counts=True)
        raise IndexError(f"{where}: {name} holds {int(values[counts > 1][0])} more than once")
    return array
