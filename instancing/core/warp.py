"""Sample warps: uniform [0, 1)^2 -> directions and surface points, with their densities."""

from __future__ import annotations

import math

from .backend import Array3f, Float, dr

INV_PI = 1.0 / math.pi
INV_FOUR_PI = 1.0 / (4.0 * math.pi)


def square_to_cosine_hemisphere(u1: Float, u2: Float) -> Array3f:
    """Cosine-weighted direction around +z (Malley's method: disk point lifted up); pdf cos/pi."""
    r = dr.sqrt(u1)
    s, c = dr.sincos(2.0 * math.pi * u2)
    return Array3f(r * c, r * s, dr.sqrt(dr.maximum(0.0, 1.0 - u1)))


def square_to_uniform_sphere(u1: Float, u2: Float) -> Array3f:
    """Uniform direction on the unit sphere; pdf 1 / (4 pi)."""
    z = 1.0 - 2.0 * u1
    r = dr.sqrt(dr.maximum(0.0, 1.0 - z * z))
    s, c = dr.sincos(2.0 * math.pi * u2)
    return Array3f(r * c, r * s, z)


def unit_sphere_cone_pdf(p: Array3f) -> Float:
    """Solid-angle density of :func:`unit_sphere_cone_sample` from a point ``p`` outside the
    unit sphere: uniform over the cone of directions the sphere subtends,
    1 / (2 pi (1 - cos theta_max)) with sin^2 theta_max = 1 / |p|^2."""
    sin2_max = 1.0 / dr.squared_norm(p)
    # 1 - cos theta_max without cancellation for distant spheres.
    one_minus_cos_max = sin2_max / (1.0 + dr.safe_sqrt(1.0 - sin2_max))
    return 1.0 / (2.0 * math.pi * one_minus_cos_max)


def unit_sphere_cone_sample(p: Array3f, u1: Float, u2: Float) -> Array3f:
    """A point on the unit sphere seen from ``p`` (outside it) in a direction drawn
    uniformly from the cone the sphere subtends (as pbrt-v4's sphere sampling and Mitsuba's
    ``sphere`` emitter): the direction's angle theta from the axis by u1, its azimuth by u2,
    and the sphere point at the nearer root t of t^2 - 2 D cos(theta) t + D^2 - 1 = 0
    (D = |p|): t = (D^2 - 1) / (D cos(theta) + r), r = sqrt(1 - D^2 sin^2(theta)), which
    puts the point at angle alpha from the axis towards p with cos(alpha) = D - t cos(theta)
    = (D r + cos(theta)) / (D cos(theta) + r) and sin(alpha) = t sin(theta): sums of
    positive terms, exact to float32 rounding for near and distant spheres alike."""
    d2 = dr.squared_norm(p)
    distance = dr.sqrt(d2)
    sin2_max = 1.0 / d2
    one_minus_cos_max = sin2_max / (1.0 + dr.safe_sqrt(1.0 - sin2_max))
    one_minus_cos = u1 * one_minus_cos_max
    sin2 = one_minus_cos * (2.0 - one_minus_cos)
    cos = 1.0 - one_minus_cos
    r = dr.safe_sqrt(1.0 - d2 * sin2)
    denominator = distance * cos + r
    # The sphere point in the frame of the axis from the centre towards p.
    cos_alpha = (distance * r + cos) / denominator
    sin_alpha = (d2 - 1.0) * dr.sqrt(sin2) / denominator
    axis = p / distance
    s, t = frame(axis)
    sin_phi, cos_phi = dr.sincos(2.0 * math.pi * u2)
    return s * (sin_alpha * cos_phi) + t * (sin_alpha * sin_phi) + axis * cos_alpha


def frame(n: Array3f) -> tuple[Array3f, Array3f]:
    """Two unit tangents (s, t) completing unit n to a right-handed orthonormal frame
    (Duff et al. 2017, "Building an Orthonormal Basis, Revisited")."""
    sign = dr.copysign(1.0, n.z)
    a = -1.0 / (sign + n.z)
    b = n.x * n.y * a
    return (Array3f(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
            Array3f(b, sign + n.y * n.y * a, -n.y))


def tangent_frame(n: Array3f, s: Array3f | None) -> tuple[Array3f, Array3f]:
    """The unit tangents (s, t) of the right-handed frame around unit n whose first axis is
    the unit tangent ``s`` (t = n x s, Mitsuba's shading frame), or :func:`frame`'s
    where ``s`` is None."""
    return frame(n) if s is None else (s, dr.cross(n, s))


def to_frame(n: Array3f, local: Array3f, s: Array3f | None = None) -> Array3f:
    """Rotate a direction given around +z into the frame around unit n (first axis the
    unit tangent ``s``, or :func:`frame`'s)."""
    s, t = tangent_frame(n, s)
    return s * local.x + t * local.y + n * local.z


def to_local(n: Array3f, w: Array3f, s: Array3f | None = None) -> Array3f:
    """The inverse of :func:`to_frame`: direction w in the frame around unit n."""
    s, t = tangent_frame(n, s)
    return Array3f(dr.dot(s, w), dr.dot(t, w), dr.dot(n, w))


def shading_tangent(sn: Array3f, dpdu: Array3f) -> Array3f:
    """Mitsuba's shading tangent: the surface's derivative dp/du made orthogonal to the unit
    shading normal ``sn`` and normalized; where dp/du is 0 (a pole, uvs that do not span a
    triangle), the first tangent of :func:`frame` of ``sn`` takes its place."""
    dpdu = dr.select(dr.all(dpdu == 0), frame(sn)[0], dpdu)
    return dr.normalize(dr.fma(sn, -dr.dot(sn, dpdu), dpdu))


def power_heuristic(pdf_a: Float, pdf_b: Float) -> Float:
    """MIS weight of strategy a against b (Veach's power heuristic, beta = 2). Where the
    squares leave float32's range (a grazing emitter sample's density reaches 1e20 and
    more, a point of a medium in the plane of a lamp: a^2 / (a^2 + b^2) was inf / inf), from
    the densities scaled by the larger; an infinite density gives 0, as Mitsuba's."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    in_range = dr.isfinite(a2 + b2) & ((a2 > 0) | (pdf_a == 0))
    larger = dr.maximum(pdf_a, pdf_b)
    a_scaled, b_scaled = dr.square(pdf_a / larger), dr.square(pdf_b / larger)
    weight = dr.select(in_range, a2 / (a2 + b2), a_scaled / (a_scaled + b_scaled))
    return dr.select((pdf_a > 0) & dr.isfinite(weight), weight, 0.0)
