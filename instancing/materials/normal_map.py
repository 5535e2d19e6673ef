"""Normal maps: Mitsuba's ``normalmap`` BSDF, a texture that tilts the shading frame of the
BSDF it wraps.

The texture's colour ``c`` at the hit's ``uv`` gives the tilted normal ``n = 2 c - 1``
relative to the shading frame (+z the shading normal, +x the surface's dp/du), so that a
map of (0.5, 0.5, 1) changes nothing. As in Mitsuba's plugin:

* the tilted frame is ``n`` normalized, ``s`` = x made orthogonal to it, ``t = n x s``;
* with ``flip_invalid_normals`` (default), ``n`` is mirrored about the z axis (its x and y
  negated) where it faces away from ``wi`` on the side ``wi`` sees;
* the wrapped BSDF sees ``wi`` and ``wo`` in the tilted frame, and a direction counts only
  where it lies on the same side of both frames;
* with ``use_shadowing_function`` (default), values are attenuated by the shadowing term
  of Estevez et al. ("A Microfacet-Based Shadowing Function to Solve the Bump Terminator
  Problem", Ray Tracing Gems 2019) of the tilted normal and ``wo``.

A normal map wraps a plain BSDF (inside ``twosided`` and mixes too), whose row in the
material table (:mod:`instancing.materials.bsdf`) it tilts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..core.backend import Array3f, Bool, Float, dr
from ..core.errors import SceneError
from ..core.warp import to_frame, to_local
from .parameter import COLOR, FLAG, Parameter
from .texture import Texture, is_texture, parse_texture

#: The parameter name of a normal map's texture (Mitsuba's).
NORMAL_MAP = "normalmap"
#: Parameters of a ``normalmap`` besides its nested BSDF (Mitsuba's names and defaults):
#: its texture, whose values are colours, and two options.
PARAMETERS = {NORMAL_MAP: Parameter(COLOR, (0.5, 0.5, 1.0), texture=True),
              "flip_invalid_normals": Parameter(FLAG, True),
              "use_shadowing_function": Parameter(FLAG, True)}


@dataclass(frozen=True, eq=False)
class NormalMap:
    """A validated normal map: its texture and Mitsuba's two options."""

    texture: Texture
    flip_invalid_normals: bool = True
    use_shadowing_function: bool = True


def parse_normal_map(where: str, spec: dict, read_image: Callable | None) -> NormalMap:
    """The ``normalmap`` texture and options of a ``normalmap`` material dict (its nested
    BSDF is the caller's)."""
    if "normalmap" not in spec:
        raise SceneError(f"{where}: a 'normalmap' needs its texture under 'normalmap'")
    if not is_texture(spec["normalmap"]) or spec["normalmap"].get("type") not in ("bitmap", "checkerboard"):
        raise SceneError(f"{where}: 'normalmap' must be a texture (a bitmap or checkerboard "
                         f"dict), got {spec['normalmap']!r}")
    texture = parse_texture(f"{where}: 'normalmap'", spec["normalmap"],
                            PARAMETERS["normalmap"].parse, read_image)
    options = {key: PARAMETERS[key].parse(spec.get(key, PARAMETERS[key].default), f"{where}: {key!r}")
               for key in ("flip_invalid_normals", "use_shadowing_function")}
    return NormalMap(texture, **options)


def tilted_frame(color: Array3f, wi: Array3f, flip: Bool) -> tuple[Array3f, Array3f]:
    """(n, s) of the tilted frame that ``color`` encodes, in the shading frame, for a ray
    from ``wi``; mirrored where ``flip`` and it faces away from ``wi``."""
    n = dr.normalize(away_from(dr.fma(color, 2.0, -1.0), wi, flip))
    s = dr.normalize(Array3f(1.0, 0.0, 0.0) - n * n.x)
    return n, s


def away_from(n: Array3f, wi: Array3f, flip: Bool) -> Array3f:
    """``n`` mirrored about the z axis (x and y negated) where ``flip`` and it faces away
    from ``wi`` on the side ``wi`` sees (Mitsuba's ``flip_invalid_normals``)."""
    away = flip & (wi.z * dr.dot(wi, n) <= 0.0)
    return Array3f(dr.select(away, -n.x, n.x), dr.select(away, -n.y, n.y), n.z)


def into(frame: tuple[Array3f, Array3f], w: Array3f) -> Array3f:
    """Direction ``w`` (shading frame) in the tilted ``frame`` (n, s)."""
    return to_local(frame[0], w, frame[1])


def out_of(frame: tuple[Array3f, Array3f], w: Array3f) -> Array3f:
    """Direction ``w`` (tilted frame) in the shading frame."""
    return to_frame(frame[0], w, frame[1])


def shadowing(n: Array3f, wo: Array3f) -> Float:
    """Estevez et al.'s shadowing term of the tilted normal ``n`` for ``wo`` (both in the
    shading frame): 1 for an untilted normal, falling to 0 at grazing ``wo``.

    ``2 / (1 + sqrt(1 + a tan^2))`` with ``a = min(tan^2(n) / 8, 1)``, written with
    cosines, ``2 c / (c + sqrt(c^2 + a (1 - c^2)))`` (c = |cos(wo)|): finite with finite
    derivatives at c = 0 (a lane without a direction, wo = 0), where the tangents' form is
    inf / inf and its derivatives NaN, which a multiplication by the zero value spreads."""
    n_cos2 = dr.square(n.z)
    n_sin2 = dr.maximum(1.0 - n_cos2, 0.0)
    # a = min(sin^2 / (8 cos^2), 1): selected, so the quotient's derivatives at cos = 0 stay out.
    a = dr.select(n_sin2 >= 8.0 * n_cos2, 1.0, n_sin2 / (8.0 * n_cos2))
    c = dr.abs(wo.z)
    denominator = c + dr.sqrt(dr.fma(a, dr.maximum(1.0 - dr.square(c), 0.0), dr.square(c)))
    return dr.select(denominator > 0.0, 2.0 * c / denominator, 0.0)
