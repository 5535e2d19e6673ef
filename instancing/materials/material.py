"""A material as parsed from a scene: its BSDF type (Mitsuba's plugin name), its validated
parameters, and what its back side shows (Mitsuba's ``twosided``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..core.errors import SceneError
from .blend import Blend
from .conductor import Conductor, RoughConductor
from .dielectric import Dielectric, RoughDielectric, ThinDielectric
from .diffuse import Diffuse
from .parameter import check_keys
from .plastic import Plastic, RoughPlastic
from .texture import is_texture, parse_texture

#: BSDF type name -> its kernel class.
LOBES = {name: lobe for lobe in (Diffuse, Conductor, RoughConductor, Plastic, RoughPlastic,
                                 Dielectric, ThinDielectric, RoughDielectric, Blend)
         for name in lobe.names}
#: Every material type a scene may name.
MATERIAL_TYPES = tuple(LOBES) + ("twosided",)


@dataclass(frozen=True)
class Material:
    """A validated material.

    Attributes:
        type: the BSDF type of its front side ('diffuse', 'roughconductor', ...).
        values: every parameter of that type (defaults filled in; colours as 3-tuples).
        back: what its back side shows: None for Mitsuba's one-sided BSDFs (black from
            behind), a Material for ``twosided`` (the front's own BSDF, or a second one).
        parts: the two BSDFs a ``blendbsdf`` mixes (None for other types).
    """

    type: str
    values: dict[str, Any] = field(default_factory=dict)
    back: "Material | None" = None
    parts: "tuple[Material, Material] | None" = None

    @property
    def lobe(self):
        return LOBES[self.type]

    def __getitem__(self, key: str) -> Any:
        return self.values[key]

    def file_entries(self, changed: set[str]) -> dict[str, Any]:
        """The scene-file entries that state this material's ``changed`` values (a value
        of None drops the entry: a named metal once its ``eta`` changed, say)."""
        if hasattr(self.lobe, "written"):
            return self.lobe.written(self.values, changed)
        return {key: self.values[key] for key in changed}


def parse_material(name: str, spec: Any,
                   read_image: Callable[[str, bool], tuple[np.ndarray, str]] | None = None) -> Material:
    """Validate a material dict (Mitsuba's keys and defaults per type; ``twosided`` holds
    one or two nested BSDF dicts under any keys, front first). A texturable parameter may
    be a texture dict (:mod:`instancing.materials.texture`), whose image ``read_image``
    reads. Every problem names the material and the key."""
    where = f"material {name!r}"
    if not isinstance(spec, dict) or spec.get("type") not in MATERIAL_TYPES:
        kind = spec.get("type") if isinstance(spec, dict) else spec
        raise SceneError(f"{where}: unknown material type {kind!r}; supported types are "
                         f"{list(MATERIAL_TYPES)}")
    if spec["type"] == "blendbsdf":
        return _parse_blend(name, spec, read_image)
    if spec["type"] != "twosided":
        return _parse_lobe(where, spec, read_image)
    nested = [(key, value) for key, value in spec.items() if key != "type"]
    if not 1 <= len(nested) <= 2 or not all(isinstance(v, dict) for _, v in nested):
        raise SceneError(f"{where}: a 'twosided' material holds one or two BSDFs (as dicts "
                         f"under any keys), got keys {[k for k, _ in nested]}")
    sides = []
    for key, value in nested:
        inner = f"material {name + '.' + key!r}"
        if value.get("type") == "twosided":
            raise SceneError(f"{inner}: a 'twosided' material cannot hold another")
        if getattr(LOBES.get(value.get("type")), "both_sides", False):
            raise SceneError(f"{inner}: a 'twosided' material holds BSDFs that reflect on one "
                             f"side; {value['type']!r} scatters on both sides itself")
        sides.append(parse_material(f"{name}.{key}", value, read_image))
    front = sides[0]
    return Material(front.type, front.values, sides[-1] if len(sides) == 2 else front, front.parts)


def _parse_blend(name: str, spec: dict, read_image) -> Material:
    """A ``blendbsdf``: its ``weight`` and two nested BSDF dicts under any other keys (first,
    second), neither ``twosided`` nor a blend, both scattering on the same sides."""
    where = f"material {name!r}"
    nested = [(key, value) for key, value in spec.items() if key not in ("type", "weight")]
    if len(nested) != 2 or not all(isinstance(v, dict) for _, v in nested):
        raise SceneError(f"{where}: a 'blendbsdf' holds a 'weight' and two BSDFs (as dicts under "
                         f"any other keys), got keys {[k for k, _ in nested]}")
    if "weight" not in spec:
        raise SceneError(f"{where}: a 'blendbsdf' needs a 'weight' (a number in [0, 1] or a "
                         "texture), as Mitsuba's")
    parts = []
    for key, value in nested:
        inner = f"material {name + '.' + key!r}"
        if value.get("type") in ("twosided", "blendbsdf"):
            raise SceneError(f"{inner}: a 'blendbsdf' mixes plain BSDFs here, not "
                             f"{value['type']!r} (wrap the blend in 'twosided' instead)")
        parts.append(parse_material(f"{name}.{key}", value, read_image))
    if len({getattr(p.lobe, "both_sides", False) for p in parts}) != 1:
        raise SceneError(f"{where}: a 'blendbsdf' mixes BSDFs that scatter on the same sides "
                         f"(both one-sided or both dielectrics), got {[p.type for p in parts]}")
    blend = _parse_lobe(where, {"type": "blendbsdf", "weight": spec["weight"]}, read_image)
    return Material("blendbsdf", blend.values, None, tuple(parts))


def _parse_lobe(where: str, spec: dict, read_image) -> Material:
    lobe = LOBES[spec["type"]]
    check_keys(where, spec["type"], spec, {"type", *lobe.parameters})
    given = set(spec) - {"type"}
    values = {}
    for key, parameter in lobe.parameters.items():
        value, at = spec.get(key, parameter.default), f"{where}: {key!r}"
        if not is_texture(value):
            values[key] = parameter.parse(value, at)
        elif parameter.texture:
            values[key] = parse_texture(at, value, parameter.parse, read_image)
        else:
            raise SceneError(f"{at} takes a constant, not a texture")
    if hasattr(lobe, "resolve"):
        values = lobe.resolve(where, values, given)
    return Material(spec["type"], values)
