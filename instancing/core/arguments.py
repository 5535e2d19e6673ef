"""Checks of the numbers callers pass: sample counts, film sizes, depths, iterations,
scene-file values.

Python and NumPy numbers are accepted alike (a sweep over ``np.arange`` or values read
from an array hand out NumPy scalars) and integers are returned as Python ints; anything
else, booleans included, is refused naming the argument.
"""

from __future__ import annotations

import numbers
from typing import Any

from .errors import SceneError


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number, Python's or NumPy's (a bool is not)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


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
