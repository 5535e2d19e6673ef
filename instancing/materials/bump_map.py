"""Bump maps: Mitsuba's ``bumpmap`` BSDF, a height texture whose slopes tilt the shading
frame of the BSDF it wraps.

The texture's luminance gradient by the surface coordinates, times ``scale``, replaces the
normal components of the surface's derivatives dp/du and dp/dv (given in the shading
frame, as :class:`SurfaceFrame`), and the tilted normal is their cross product, turned to
the side of the geometric normal. The frame's first axis is dp/du made orthogonal to it
(Mitsuba's plugin takes dp/du in world space there, against a normal in the shading frame:
the same frame where the shading frame is the world's, and the same tilted normal always),
and the rest is as a normal map's
(:mod:`instancing.materials.normal_map`): ``flip_invalid_normals``, the same-side test of
directions and Estevez et al.'s shadowing term (``use_shadowing_function``). Only bitmaps
have a gradient (Mitsuba's checkerboard has none).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from ..core.backend import Array2f, Array3f, Bool, dr
from ..core.errors import SceneError
from .normal_map import away_from
from .parameter import COLOR, FLAG, NUMBER, Parameter
from .texture import TEXTURE_KEYS, Texture, parse_texture

#: The parameter name a bump map's texture is filed under in the material table.
BUMP_MAP = "bumpmap"
#: The height texture as a scene parameter (``<material>.bumpmap.data``: any values).
HEIGHTS = Parameter(COLOR, (0.0, 0.0, 0.0), texture=True)
#: Parameters of a ``bumpmap`` besides its texture and nested BSDF (Mitsuba's names and
#: defaults).
PARAMETERS = {"scale": Parameter(NUMBER, 1.0),
              "flip_invalid_normals": Parameter(FLAG, True),
              "use_shadowing_function": Parameter(FLAG, True)}


@dataclass(frozen=True, eq=False)
class BumpMap:
    """A validated bump map: its height texture (a bitmap), scale and Mitsuba's options."""

    texture: Texture
    scale: float = 1.0
    flip_invalid_normals: bool = True
    use_shadowing_function: bool = True


@dataclass(frozen=True)
class SurfaceFrame:
    """What a bump map reads of the surface at a hit, in the shading frame: the derivatives
    dp/du and dp/dv (with their lengths) and the geometric normal."""

    dpdu: Array3f
    dpdv: Array3f
    n: Array3f


def is_texture_spec(value: Any) -> bool:
    """Whether a value of a ``bumpmap`` dict is its texture (a texture dict)."""
    return isinstance(value, dict) and value.get("type") in TEXTURE_KEYS


def parse_bump_map(where: str, key: str, spec: dict, read_image: Callable | None) -> BumpMap:
    """The texture (under ``key``) and options of a ``bumpmap`` material dict (its nested
    BSDF is the caller's)."""
    if spec[key].get("type") != "bitmap":
        raise SceneError(f"{where}: a 'bumpmap' needs a bitmap texture (its slopes tilt the "
                         f"frame; a {spec[key].get('type')!r} has none), got {key!r}")
    texture = parse_texture(f"{where}: {key!r}", spec[key], lambda value, at: value, read_image)
    options = {name: parameter.parse(spec.get(name, parameter.default), f"{where}: {name!r}")
               for name, parameter in PARAMETERS.items()}
    return BumpMap(texture, **options)


def bumped_frame(gradient: Array2f, surface: SurfaceFrame, wi: Array3f,
                 flip: Bool) -> tuple[Array3f, Array3f]:
    """(n, s) of the frame that the height gradient (already scaled) tilts, in the shading
    frame, for a ray from ``wi``; the normal mirrored where ``flip`` and it faces away from
    ``wi`` (as a normal map's)."""
    dpdu = Array3f(surface.dpdu.x, surface.dpdu.y, gradient.x)
    dpdv = Array3f(surface.dpdv.x, surface.dpdv.y, gradient.y)
    n = dr.normalize(dr.cross(dpdu, dpdv))
    n = dr.select(dr.dot(surface.n, n) < 0.0, -n, n)
    n = away_from(n, wi, flip)
    s = dr.normalize(dr.fma(n, -dr.dot(n, surface.dpdu), surface.dpdu))
    return n, s
