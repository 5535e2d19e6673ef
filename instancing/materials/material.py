"""A material as parsed from a scene: its BSDF type (Mitsuba's plugin name), its validated
parameters, and what its back side shows (Mitsuba's ``twosided``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..core.errors import SceneError
from .blend import Blend
from .conductor import Conductor, RoughConductor
from .dielectric import Dielectric, RoughDielectric, ThinDielectric
from .diffuse import Diffuse
from .mask import Mask, Null, Polarizer
from .bump_map import PARAMETERS as BUMP_MAP_PARAMETERS, BumpMap, is_texture_spec, parse_bump_map
from .normal_map import PARAMETERS as NORMAL_MAP_PARAMETERS, NormalMap, parse_normal_map
from .parameter import NUMBER, check_keys
from .plastic import Plastic, PolarizedPlastic, RoughPlastic
from .principled import Principled, PrincipledThin
from .texture import Texture, is_texture, parse_texture

#: BSDF type name -> its kernel class.
LOBES = {name: lobe for lobe in (Diffuse, Conductor, RoughConductor, Plastic, RoughPlastic, PolarizedPlastic,
                                 Dielectric, ThinDielectric, RoughDielectric, Blend, Mask, Null,
                                 Polarizer, Principled, PrincipledThin)
         for name in lobe.names}
#: Every material type a scene may name.
MATERIAL_TYPES = tuple(LOBES) + ("twosided", "normalmap", "bumpmap")
#: The wrappers around other BSDFs, which a normal or bump map cannot hold.
WRAPPERS = ("twosided", "blendbsdf", "mask", "normalmap", "bumpmap")


@dataclass(frozen=True)
class Material:
    """A validated material.

    Attributes:
        type: the BSDF type of its front side ('diffuse', 'roughconductor', ...).
        values: every parameter of that type (defaults filled in; colours as 3-tuples).
        back: what its back side shows: None for Mitsuba's one-sided BSDFs (black from
            behind), a Material for ``twosided`` (the front's own BSDF, or a second one).
        parts: the two BSDFs a ``blendbsdf`` mixes; for a ``mask``, the null lobe and its
            nested BSDF (None for other types).
        part_names: the keys the scene file gives the parts under (None for the null lobe).
        normal_map: the ``normalmap`` that tilts this BSDF's shading frame, or None.
        bump_map: the ``bumpmap`` that does, or None.
        outer: a ``normalmap`` or ``bumpmap`` around the whole material (a ``twosided`` or a
            mix), which tilts the frame before the wrapper sees wi; only a scene's materials
            themselves carry one (none nested inside another wrapper).
    """

    type: str
    values: dict[str, Any] = field(default_factory=dict)
    back: "Material | None" = None
    parts: "tuple[Material, Material] | None" = None
    part_names: "tuple[str | None, str | None] | None" = None
    normal_map: NormalMap | None = None
    bump_map: BumpMap | None = None
    outer: NormalMap | BumpMap | None = None

    @property
    def lobe(self):
        return LOBES[self.type]

    @property
    def both_sides(self) -> bool:
        """Whether its BSDF scatters on both sides itself (dielectrics, masks, a principled
        BSDF with a transmission lobe): no twosided around it, no frame flip below it."""
        flag = getattr(self.lobe, "both_sides", False)
        return flag(self.values) if callable(flag) else flag

    @property
    def plain_diffuse(self) -> bool:
        """Whether it is a ``diffuse`` of an untextured reflectance, without a normal or bump
        map, showing the same on its back if it has one: its shading turns only as far as the
        surface's normal does."""
        return (self.type == "diffuse" and isinstance(self.values.get("reflectance"), tuple)
                and self.normal_map is None and self.bump_map is None and self.outer is None
                and (self.back is None or self.back is self or self.back.values == self.values))

    @property
    def may_sample_delta(self) -> bool:
        """Whether it, or a part it mixes, may scatter by a delta lobe (a mirror, a smooth
        glass, a plastic's coating)."""
        return any(getattr(part.lobe, "samples_delta", False) for part in (self, *(self.parts or ())))

    def __getitem__(self, key: str) -> Any:
        return self.values[key]

    def file_entries(self, changed: set[str]) -> dict[str, Any]:
        """The scene-file entries that state this material's ``changed`` values (a value
        of None drops the entry: a named metal once its ``eta`` changed, say)."""
        if hasattr(self.lobe, "written"):
            return self.lobe.written(self.values, changed)
        return {key: self.values[key] for key in changed}


def attribute_reads(material: Material) -> list[tuple[str, bool, Texture]]:
    """The mesh attributes ``material`` reads, as (parameter, whether it is a number
    parameter, the mesh_attribute texture), over its BSDF, back side and parts."""
    reads, seen, todo = [], set(), [material]
    while todo:
        m = todo.pop()
        if m is None or id(m) in seen:
            continue
        seen.add(id(m))
        for key, value in m.values.items():
            if isinstance(value, Texture) and value.type == "mesh_attribute":
                reads.append((key, m.lobe.parameters[key].kind == NUMBER, value))
        todo.extend([m.back, *(m.parts or ())])
    return reads


def parse_material(name: str, spec: Any,
                   read_image: Callable[[str, bool], tuple[np.ndarray, str]] | None = None) -> Material:
    """Validate a material dict (Mitsuba's keys and defaults per type; ``twosided`` holds
    one or two nested BSDF dicts under any keys, front first). A texturable parameter may
    be a texture dict (:mod:`instancing.materials.texture`), whose image ``read_image``
    reads. Every problem names the material and the key."""
    where = f"material {name!r}"
    if not isinstance(spec, dict) or not isinstance(spec.get("type"), str) \
            or spec["type"] not in MATERIAL_TYPES:
        kind = spec.get("type") if isinstance(spec, dict) else spec
        raise SceneError(f"{where}: unknown material type {kind!r}; supported types are "
                         f"{list(MATERIAL_TYPES)}")
    if spec["type"] in ("blendbsdf", "mask"):
        return _parse_mix(name, spec, read_image)
    if spec["type"] in ("normalmap", "bumpmap"):
        return _parse_tilted(name, spec, read_image)
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
        sides.append(parse_material(f"{name}.{key}", value, read_image))
        _refuse_outer(inner, sides[-1], "a 'twosided' material")
        if sides[-1].both_sides:
            raise SceneError(f"{inner}: a 'twosided' material holds BSDFs that reflect on one "
                             f"side; {value['type']!r} scatters on both sides itself")
    front = sides[0]
    return Material(front.type, front.values, sides[-1] if len(sides) == 2 else front, front.parts,
                    front.part_names, front.normal_map, front.bump_map)


def _parse_tilted(name: str, spec: dict, read_image) -> Material:
    """A ``normalmap`` (its texture under ``normalmap``) or ``bumpmap`` (its texture under any
    key), its options and one nested BSDF dict under any other key, which it returns carrying
    the map: a plain BSDF's frame (its row's), or around a twosided BSDF or a mix (``outer``)."""
    where, kind = f"material {name!r}", spec["type"]
    own = NORMAL_MAP_PARAMETERS if kind == "normalmap" else BUMP_MAP_PARAMETERS
    textures = [k for k, v in spec.items() if kind == "bumpmap" and is_texture_spec(v)]
    nested = [(k, v) for k, v in spec.items() if k not in ("type", *own, *textures)]
    if len(nested) != 1 or not isinstance(nested[0][1], dict) or (kind == "bumpmap" and len(textures) != 1):
        holds = list(own) if kind == "normalmap" else ["a texture (under any key)", *own]
        raise SceneError(f"{where}: a {kind!r} holds {holds} and one BSDF (as a dict under any "
                         f"other key), got keys {[k for k in spec if k != 'type']}")
    key, inner = nested[0]
    if inner.get("type") in ("normalmap", "bumpmap"):
        raise SceneError(f"material {name + '.' + key!r}: a {kind!r} cannot hold another map "
                         f"({inner['type']!r})")
    nested_material = parse_material(f"{name}.{key}", inner, read_image)
    tilt = (parse_normal_map(where, spec, read_image) if kind == "normalmap"
            else parse_bump_map(where, textures[0], spec, read_image))
    if inner.get("type") in WRAPPERS:
        # Around a twosided BSDF or a mix: the frame tilts before the wrapper sees wi.
        return dataclasses.replace(nested_material, outer=tilt)
    return dataclasses.replace(nested_material, **{"normal_map" if kind == "normalmap" else "bump_map": tilt})


def _refuse_outer(where: str, material: Material, wrapper: str) -> None:
    """Refuse a map around a wrapper nested in another wrapper (only a scene's materials
    themselves may carry one)."""
    if material.outer is not None:
        raise SceneError(f"{where}: a normal or bump map around a twosided BSDF or a mix is "
                         f"supported as a whole material, not inside {wrapper}")


#: The pass-through part of every mask.
NULL = Material("null")


def _parse_mix(name: str, spec: dict, read_image) -> Material:
    """A ``blendbsdf`` (its ``weight`` and two nested BSDF dicts under any other keys: first,
    second) or a ``mask`` (its ``opacity``, default 0.5, and one nested BSDF dict: the null
    lobe is its first part). The nested BSDFs are plain or ``twosided`` ones, no mixes."""
    where, kind = f"material {name!r}", spec["type"]
    key = LOBES[kind].weight_key
    count = 2 if kind == "blendbsdf" else 1
    nested = [(k, value) for k, value in spec.items() if k not in ("type", key)]
    # A value that is no BSDF dict is a misspelt parameter.
    check_keys(where, kind, {k: v for k, v in spec.items() if not isinstance(v, dict)}, {"type", key})
    if len(nested) != count or not all(isinstance(v, dict) for _, v in nested):
        raise SceneError(f"{where}: a {kind!r} holds a {key!r} and {count} BSDF"
                         f"{'s' if count > 1 else ''} (as dicts under any other keys), got keys "
                         f"{[k for k, _ in nested]}")
    if kind == "blendbsdf" and "weight" not in spec:
        raise SceneError(f"{where}: a 'blendbsdf' needs a 'weight' (a number in [0, 1] or a "
                         "texture), as Mitsuba's")
    parts, names = ([], []) if count == 2 else ([NULL], [None])
    for k, value in nested:
        inner = f"material {name + '.' + k!r}"
        if value.get("type") in ("blendbsdf", "mask"):
            raise SceneError(f"{inner}: a {kind!r} holds plain or 'twosided' BSDFs here, not "
                             f"{value['type']!r}")
        parts.append(parse_material(f"{name}.{k}", value, read_image))
        _refuse_outer(inner, parts[-1], f"a {kind!r}")
        names.append(k)
    own = {"type": kind, **({key: spec[key]} if key in spec else {})}
    return Material(kind, _parse_lobe(where, own, read_image).values, None, tuple(parts), tuple(names))


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
