"""Starting secondary and shadow rays off a surface without self-intersection.

The hit point ``p = o + t d`` carries a rounding error bounded componentwise by
``(|o| + |t d|) * SPAWN_ERROR``; the new ray starts that far off the surface
along the normal, on the side it leaves towards (after pbrt-v4's
``OffsetRayOrigin``). SPAWN_ERROR covers the float32 error of t from the
object-space quadratics and triangle tests (measured below ~1e-5 relative at
the 99.9th percentile, tests/test_intersection.py) with margin; the
robustness issue replaces it with per-shape bounds.
"""

from __future__ import annotations

from .backend import Array3f, Float, dr

#: Relative error bound of a hit point's coordinates (2^-14 ~ 6.1e-5).
SPAWN_ERROR = 2.0 ** -14


def hit_error(o: Array3f, d: Array3f, t: Float) -> Array3f:
    """Componentwise error bound of the hit point o + t d."""
    return (dr.abs(o) + dr.abs(d * t)) * SPAWN_ERROR


def offset_origin(p: Array3f, n: Array3f, error: Array3f, w: Array3f) -> Array3f:
    """Move p off the surface (normal n) by the error bound, to the side w points to."""
    distance = dr.dot(dr.abs(n), error)
    offset = n * dr.select(dr.dot(w, n) < 0, -distance, distance)
    return p + offset


def shadow_distance(origin: Array3f, target: Array3f, target_error: Array3f) -> tuple[Array3f, Float]:
    """Unit direction to the target and the parameter just short of it (by its error bound)."""
    delta = target - origin
    dist = dr.norm(delta)
    slack = dr.norm(target_error) + dr.norm(dr.abs(origin)) * SPAWN_ERROR
    return delta / dist, dist - slack
