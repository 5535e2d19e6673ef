"""The parameters a BSDF type takes, as Mitsuba's plugin of the same name takes them: kind,
default and valid range, and their validation (every problem names the key)."""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any

from ..core.arguments import FLOAT32_MAX, is_real
from ..core.backend import mitsuba_module
from ..core.errors import SceneError

#: Parameter kinds: an RGB colour (a number is grey), a number, a flag, one of named choices,
#: a name that the BSDF type resolves itself (a conductor's ``material``), an index of
#: refraction (a positive number or one of Mitsuba's named media, e.g. ``"water"``).
COLOR, NUMBER, FLAG, CHOICE, NAME, IOR = "color", "number", "flag", "choice", "name", "ior"


@dataclass(frozen=True)
class Parameter:
    """One parameter of a BSDF type: ``kind``, ``default``, and for colours and numbers the
    closed range [low, high] it must lie in; for choices the allowed ``choices``."""

    kind: str
    default: Any
    low: float = -math.inf
    high: float = math.inf
    choices: tuple[str, ...] = ()
    #: Whether a texture may give the value (colours and numbers that Mitsuba's plugin
    #: reads per lookup; not those its precomputation depends on).
    texture: bool = False
    #: Whether it is differentiable although no texture may give it (a conductor's
    #: complex index of refraction, as Mitsuba's traverse marks it).
    differentiable_constant: bool = False
    #: For a key that :func:`instancing.traverse` exposes but scene files do not take (a
    #: dielectric's relative index of refraction ``eta``): the derived column the kernels
    #: read it from; for a parameter whose name another BSDF type gives a value of another
    #: kind (principledthin's number ``eta``, the conductors' colour): the column that
    #: holds it.
    column: str | None = None

    @property
    def differentiable(self) -> bool:
        """Whether :func:`instancing.traverse` exposes it: Mitsuba's differentiable
        parameters that its plugin reads per lookup (those it precomputes from, such as
        indices of refraction of dielectrics and a rough plastic's roughness, are not)."""
        return self.texture or self.differentiable_constant

    def parse(self, value: Any, where: str) -> Any:
        """The validated value: colours as 3 floats, numbers as a float."""
        if self.kind == FLAG:
            if not isinstance(value, bool):
                raise SceneError(f"{where} must be true or false, got {value!r}")
            return value
        if self.kind == IOR:
            if isinstance(value, str):
                return named_ior(value, where)
            if not (is_real(value) and math.isfinite(value) and value > 0):
                raise SceneError(f"{where} must be a positive number or a named medium, got {value!r}")
            _require_float32(value, where)
            return float(value)
        if self.kind == NAME:
            if not isinstance(value, str) or not value:
                raise SceneError(f"{where} must be a name, got {value!r}")
            return value
        if self.kind == CHOICE:
            if not isinstance(value, str) or value.lower() not in self.choices:
                raise SceneError(f"{where} must be one of {list(self.choices)}, got {value!r}")
            return value.lower()
        numbers = [value] * 3 if self.kind == COLOR and is_real(value) else value
        if self.kind == NUMBER:
            numbers = [value]
        if (not isinstance(numbers, (list, tuple)) or len(numbers) != (3 if self.kind == COLOR else 1)
                or not all(is_real(c) and math.isfinite(c) and self.low <= c <= self.high
                           for c in numbers)):
            shape = "a number or 3 numbers" if self.kind == COLOR else "a number"
            if math.isinf(self.low) and math.isinf(self.high):
                shape = "a finite number or 3 finite numbers" if self.kind == COLOR else "a finite number"
                raise SceneError(f"{where} must be {shape}, got {value!r}")
            raise SceneError(f"{where} must be {shape} in [{self.low}, {self.high}], got {value!r}")
        for c in numbers:
            _require_float32(c, where)
        return tuple(float(c) for c in numbers) if self.kind == COLOR else float(numbers[0])



def _require_float32(value: float, where: str) -> None:
    """A finite number that float32, in which the kernels read it, can hold."""
    if abs(value) > FLOAT32_MAX:
        raise SceneError(f"{where} must fit in float32 (magnitude at most {FLOAT32_MAX:.4g}), got {value!r}")


def named_ior(name: str, where: str) -> float:
    """The index of refraction of one of Mitsuba's named media (its own table)."""
    mi = mitsuba_module()
    props = mi.Properties()
    props["ior"] = name
    try:
        return float(mi.lookup_ior(props, "ior", "air"))
    except Exception as err:  # Mitsuba lists the valid names
        raise SceneError(f"{where}: {str(err).split('] ', 1)[-1]}") from None


def check_keys(where: str, kind: str, spec: dict, allowed: set[str], what: str = "material") -> None:
    """An error naming every key of ``spec`` not in ``allowed``, with the closest valid one
    (``what`` the spec is: a material, a texture)."""
    unknown = sorted(set(spec) - allowed)
    if unknown:
        hints = [f"{key!r} (did you mean {close[0]!r}?)" if close else repr(key)
                 for key in unknown
                 for close in [difflib.get_close_matches(key, sorted(allowed), 1)]]
        raise SceneError(f"{where}: unknown keys {', '.join(hints)}; a {kind!r} {what} has "
                         f"{sorted(allowed)}")
