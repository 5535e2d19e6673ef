"""Starting secondary and shadow rays off a surface without self-intersection.

Each hit (and each point sampled on an area emitter) carries a componentwise
bound of its distance from the surface as later ray tests see it
(:mod:`instancing.core.error_bounds`). A new ray starts just outside that error box:
the point is moved along the normal, to the side the ray leaves towards, by
the box's extent along the normal, and each coordinate is then rounded one
float away from the point so that the addition cannot eat into the offset
(pbrt-v4's ``OffsetRayOrigin``). No fixed epsilon is involved: the offset
scales with the instance's transform, its distance from the world origin and
the shape.
"""

from __future__ import annotations

from .backend import Array3f, Float, UInt32, dr
from .error_bounds import gamma

#: Relative shortening of shadow rays: covers the rounding of their length and of
#: the occlusion test's t near the far end (both a few float32 roundings).
SHADOW_SHORTENING = gamma(16)


def _next_float_away(x: Float, direction: Float) -> Float:
    """The float next to x in the direction of ``direction``'s sign (x where it is 0)."""
    bits = dr.reinterpret_array(UInt32, x)
    larger = (x > 0) == (direction > 0)
    stepped = dr.reinterpret_array(Float, dr.select(larger, bits + 1, bits - 1))
    # From zero, step to the smallest subnormal of the direction's sign.
    stepped = dr.select(x == 0, dr.copysign(dr.reinterpret_array(Float, UInt32(1)), direction),
                        stepped)
    return dr.select(direction == 0, x, stepped)


def offset_origin(p: Array3f, n: Array3f, error: Array3f, w: Array3f) -> Array3f:
    """Move p off the surface (unit normal n) past its error bound, to the side w points to.

    Args:
        p: surface points (Array3f), e.g. ``SurfaceHit.p``.
        n: their unit normals (either orientation).
        error: componentwise error bounds of p, e.g. ``SurfaceHit.error``.
        w: the direction the new ray leaves in (any length).

    Returns the new ray origins (gradients flow as for ``p + offset``).
    """
    distance = dr.dot(dr.abs(n), error)
    offset = n * dr.select(dr.dot(w, n) < 0, -distance, distance)
    moved = p + offset
    # Round away from p, so that the rounding of the addition cannot undo part of the offset.
    rounded = Array3f(*[_next_float_away(dr.detach(moved[k]), dr.detach(offset[k])) for k in range(3)])
    return dr.replace_grad(rounded, moved)


def shadow_distance(origin: Array3f, target: Array3f) -> tuple[Array3f, Float]:
    """Unit direction from an (offset) origin to an (offset) target, and the ray length
    just short of the target (by SHADOW_SHORTENING)."""
    delta = target - origin
    dist = dr.norm(delta)
    return delta / dist, dist * (1.0 - SHADOW_SHORTENING)
