"""Analytic base models in object space, with Mitsuba's canonical shapes.

Each model intersects a ray ``o + t d`` given in its own object space (the
world ray mapped by the instance's inverse transform, ``d`` *not*
renormalized, so ``t`` is the same number as on the world ray), and returns
the nearest ``t`` with ``0 < t < t_max`` (``inf`` otherwise). A ray starting
inside a closed shape reports its exit point, as Mitsuba does.

The quadrics use the numerically careful float32 form of the quadratic
(Haines et al., "Precision Improvements for Ray/Sphere Intersection", Ray
Tracing Gems, 2019): the discriminant is computed from the distance of the
point of closest approach, which avoids the cancellation in ``b^2 - 4ac``
that costs Mitsuba's float32 sphere ~1e-4 relative error near grazing hits,
and the two roots are taken as ``c/q`` and ``q/a`` so that neither subtracts
nearly equal numbers.
"""

from __future__ import annotations

import numpy as np

from ..core.backend import Array3f, Bool, Float, UInt32, dr
from ..core.box import slab_interval
from ..core.error_bounds import gamma
from ..core.warp import frame, square_to_uniform_sphere
from .curves import (NORMAL_CYLINDER, NORMAL_SPHERE, NORMAL_STORED, CurveParts, EdgeTopology,
                     SectionParts, orthonormal_pair, parts_of, sections_of, square_chord)

INF = float("inf")


def _quadratic_roots(a: Float, half_b: Float, c: Float, disc: Float) -> tuple[Float, Float]:
    """Roots of ``a t^2 - 2 half_b t + c = 0`` in ascending order, given ``disc = half_b^2 - a c``.

    ``q = half_b + sign(half_b) sqrt(disc)`` has no cancellation, so both
    ``c / q`` and ``q / a`` are accurate.
    """
    q = half_b + dr.copysign(dr.sqrt(dr.maximum(disc, 0.0)), half_b)
    r0, r1 = c / q, q / a
    # Ordered by one compare (dr.minimum and dr.maximum each compile to several
    # instructions, to propagate NaN).
    swap = r1 < r0
    return dr.select(swap, r1, r0), dr.select(swap, r0, r1)


def _nearest_positive(t_near: Float, t_far: Float, ok_near: Bool, ok_far: Bool,
                      t_max: Float) -> Float:
    """The first of two candidate hits that is valid and lies in (0, t_max); inf if none."""
    ok_near = ok_near & (t_near > 0) & (t_near < t_max)
    ok_far = ok_far & (t_far > 0) & (t_far < t_max)
    return dr.select(ok_near, t_near, dr.select(ok_far, t_far, INF))


#: Instances whose linear part may stretch or shrink a unit direction past this factor
#: (either way) are traced by quadric tests of a unit-exponent direction: the squared
#: length of an object-space direction overflows or vanishes past about 2^63 (|d| is
#: 1 / scale), and the products of the test need a margin beyond that.
WIDE_SCALE = 2.0 ** 40


def wide_scales(matrices: np.ndarray) -> bool:
    """Whether any of the (N, 4, 4) affine maps may take a unit direction to object space
    at a length outside [1 / WIDE_SCALE, WIDE_SCALE]: bounded by the Frobenius norm F >=
    sigma_max and by |det| / F^2 <= sigma_min of the linear part, without inverting it."""
    a = np.asarray(matrices, np.float64)[:, :3, :3]
    norm = np.sqrt(np.einsum("nij,nij->n", a, a))
    with np.errstate(over="ignore", under="ignore", divide="ignore", invalid="ignore"):
        # The determinant as the triple product of the rows (no per-matrix LU).
        det = np.einsum("ni,ni->n", a[:, 0], np.cross(a[:, 1], a[:, 2]))
        smallest = np.abs(det) / (norm * norm)
    return bool((norm > WIDE_SCALE).any() or (smallest < 1.0 / WIDE_SCALE).any())


def _exponent_free(d: Array3f) -> tuple[Float, Float]:
    """(2^e, 2^-e) for the largest component of ``d`` in [2^e, 2^(e+1)) (e at least -126).

    A float32 quadric test of a scene with :func:`wide_scales` runs on ``d * 2^-e`` and
    ``t_max * 2^e`` and returns its ``t`` times ``2^-e``: every product is exact, and the
    squared length of the scaled direction stays in float32's range whatever the
    instance's scale.
    """
    m = dr.maximum(dr.maximum(dr.abs(d.x), dr.abs(d.y)), dr.abs(d.z))
    bits = dr.maximum(dr.reinterpret_array(UInt32, m) & 0x7F800000, 1 << 23)
    return dr.reinterpret_array(Float, bits), dr.reinterpret_array(Float, (254 << 23) - bits)


def _circle(c: Array3f, a: Array3f, b: Array3f, u: Float) -> tuple[Array3f, Array3f]:
    """The point ``c + a cos 2 pi u + b sin 2 pi u`` and its derivative by u."""
    sin, cos = dr.sincos(2.0 * np.pi * u)
    return c + a * cos + b * sin, (b * cos - a * sin) * (2.0 * np.pi)


class AnalyticModel:
    """Common interface of the analytic models (see the module docstring)."""

    #: Scene-file type name, also Mitsuba's plugin name.
    name: str = ""
    #: Object-space bounding box (lo, hi).
    object_bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    def intersect(self, o: Array3f, d: Array3f, t_max: Float, wide: bool = False) -> Float:
        """Nearest hit parameter in (0, t_max) of the object-space ray, or inf; ``wide``:
        the scene has :func:`wide_scales` (the quadrics then test a unit-exponent
        direction; the planar models and the cube divide by components, unaffected)."""
        raise NotImplementedError

    def normal(self, p: Array3f, prim: UInt32) -> Array3f:
        """Outward object-space normal (not normalized) at the surface point ``p``."""
        raise NotImplementedError

    def surface_point(self, o: Array3f, d: Array3f, t: Float) -> Array3f:
        """Object-space hit point of the ray at t, re-projected onto the surface where the
        shape allows it (its error bound is :meth:`point_error`)."""
        return dr.fma(d, t, o)

    def uv(self, p: Array3f) -> tuple:
        """Mitsuba's surface coordinates (u, v) of the shape at the object-space surface
        point ``p`` (what textures are looked up by), in the precision of p."""
        raise NotImplementedError

    def derivatives(self, p: Array3f) -> tuple[Array3f, Array3f]:
        """Mitsuba's derivatives (dp/du, dp/dv) of the surface point by its surface
        coordinates at the object-space surface point ``p``, with their lengths: dp/du
        orients anisotropic BSDFs and normal maps, both tilt the frame of bump maps."""
        raise NotImplementedError

    def point_error(self, p: Array3f) -> Array3f:
        """Componentwise object-space error bound, along the normal, of a point returned by
        :meth:`surface_point` or :meth:`sample_area` (pbrt-v4's ``pError``).

        Only the error across the surface matters for spawned rays; error along it
        (tangential) is left out, as in pbrt-v4.
        """
        raise NotImplementedError

    #: Surface area in object space.
    object_area: float = 0.0
    #: True for flat shapes, whose object-space normal is +z everywhere.
    flat: bool = False
    #: True for curved surfaces with smooth silhouettes (the normal turns away there, so
    #: shading near a silhouette varies as the square root of the film distance to it).
    curved: bool = False

    def sample_area(self, u1: Float, u2: Float) -> Array3f:
        """A point distributed uniformly (by object-space area) on the surface."""
        raise NotImplementedError

    def world_bounds(self, matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World bounding boxes (N, 3) lo/hi of the model under (N, 4, 4) float64 matrices.

        Default: the transformed object box, exact for boxes and rectangles
        (lecture, "Grids and Transformed Objects": bounds from the transformed
        object-space box).
        """
        return transformed_box_bounds(matrices, *self.object_bounds)

    def discontinuity_curves(self, viewpoints: np.ndarray, creases: bool = True) -> CurveParts:
        """The curves across which the model's image can jump, seen from the object-space
        homogeneous viewpoints (M, 4): points (w = 1) or directions towards a viewer at
        infinity (w = 0); silhouettes and rims (:mod:`instancing.models.curves`), and
        with ``creases`` the edges where flat shading jumps (polyhedra)."""
        return parts_of(self._curve_pieces(viewpoints[:, :3], viewpoints[:, 3]))

    def _curve_pieces(self, cam: np.ndarray, w: np.ndarray) -> list[tuple]:
        """Per-viewpoint pieces ``(keep (M,), circle, c, u, v (M, 3))`` of
        :func:`~instancing.models.curves.parts_of` for homogeneous viewpoints (cam, w)."""
        raise NotImplementedError

    #: Whether no ray from a point on the surface can meet the surface again (no
    #: self-occlusion: its silhouettes never cast onto itself).
    convex: bool = True

    def sample_silhouette(self, view: Array3f, u: Float,
                          creases: bool = False) -> tuple[Array3f, Array3f, Bool]:
        """A point of the curves the model shows from the object-space points ``view``
        (per lane), across which what is seen from there can jump: silhouettes seen from
        the point and boundary rims, and with ``creases`` the edges of polyhedra where
        flat shading jumps between two faces of which one is seen. The curves are
        parameterised over u in [0, 1) (each piece an equal share); returns (point,
        d point / du, valid). Where ``valid`` is false (a piece that shows no jump from
        there) the sample counts zero, so that the density of u stays 1."""
        raise NotImplementedError

    def plane_sections(self, normal: np.ndarray, offset: np.ndarray) -> SectionParts:
        """The curves where the model meets the object-space planes ``normal . x = offset``
        (M unit normals (M, 3), offsets (M,)): where an instance touches or sinks into a
        flat surface (:mod:`instancing.models.curves`, :data:`SectionParts`)."""
        return sections_of(self._section_pieces(normal, offset))

    def _section_pieces(self, normal: np.ndarray, offset: np.ndarray) -> list[tuple]:
        raise NotImplementedError


def _turns(x, y):
    """The angle of (x, y) from +x counter-clockwise, in turns in [0, 1)."""
    turns = dr.atan2(y, x) * (0.5 / np.pi)
    return dr.select(turns < 0, turns + 1.0, turns)


def transformed_box_bounds(matrices: np.ndarray, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of an axis-aligned box under affine maps: centre image +- |A| half-extent."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    c = np.einsum("nij,j->ni", matrices[:, :3, :3], centre) + matrices[:, :3, 3]
    r = np.einsum("nij,j->ni", np.abs(matrices[:, :3, :3]), half)
    return c - r, c + r


def _ellipse_bounds(matrices: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact bounds of the image of the unit circle at height z: centre +- |(A_i0, A_i1)|."""
    a = matrices[:, :3, :3]
    c = a[:, :, 2] * z + matrices[:, :3, 3]
    r = np.sqrt(a[:, :, 0] ** 2 + a[:, :, 1] ** 2)
    return c - r, c + r


class _Quadric(AnalyticModel):
    """A model whose test squares the object-space direction (see :func:`_exponent_free`)."""

    def intersect(self, o, d, t_max, wide=False):
        if wide and dr.type_v(d) == dr.VarType.Float32:
            up, down = _exponent_free(d)
            return self._intersect(o, d * down, t_max * up) * down
        return self._intersect(o, d, t_max)

    def _intersect(self, o: Array3f, d: Array3f, t_max: Float) -> Float:
        raise NotImplementedError


class Sphere(_Quadric):
    """Unit sphere at the origin; outward normal = hit point."""

    name = "sphere"
    curved = True
    object_bounds = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))

    def _intersect(self, o, d, t_max):
        a = dr.squared_norm(d)
        half_b = -dr.dot(o, d)
        # Closest approach to the centre along the ray, then disc = a (1 - |closest|^2).
        closest = dr.fma(d, half_b / a, o)
        disc = a * (1.0 - dr.squared_norm(closest))
        c = dr.squared_norm(o) - 1.0
        t0, t1 = _quadratic_roots(a, half_b, c, disc)
        hit = disc >= 0
        return _nearest_positive(t0, t1, hit, hit, t_max)

    def normal(self, p, prim):
        return type(p)(p)

    def surface_point(self, o, d, t):
        # From the point of closest approach, step by the exact half chord: no
        # cancellation even when the origin is far away in object space (a small
        # sphere hit from afar), unlike o + t d.
        a = dr.squared_norm(d)
        t_closest = -dr.dot(o, d) / a
        closest = dr.fma(d, t_closest, o)
        half_chord = dr.sqrt(dr.maximum(a * (1.0 - dr.squared_norm(closest)), 0.0)) / a
        p = dr.fma(d, dr.select(t < t_closest, -half_chord, half_chord), closest)
        # Re-project onto the unit sphere (correctly rounded sqrt and division).
        return p / dr.sqrt(dr.squared_norm(p))

    def uv(self, p):
        # Longitude from +x counter-clockwise, colatitude from +z, each in [0, 1].
        return _turns(p.x, p.y), dr.safe_acos(p.z) * (1.0 / np.pi)

    def derivatives(self, p):
        # u: along the parallel, counter-clockwise about +z, a turn per unit (0 at the
        # poles); v: down the meridian, half a turn per unit (+x at the poles).
        rd = dr.sqrt(dr.fma(p.x, p.x, p.y * p.y))
        pole = rd == 0
        inv = dr.select(pole, 0.0, dr.rcp(rd))
        dpdv = type(p)(dr.select(pole, 1.0, p.z * p.x * inv), dr.select(pole, 0.0, p.z * p.y * inv),
                       dr.select(pole, 0.0, -rd))
        return type(p)(-p.y, p.x, 0.0) * (2.0 * np.pi), dr.select(pole, dpdv, dpdv * np.pi)

    def point_error(self, p):
        # pbrt-v4 (sphere): gamma(5) |p| after re-projection; uniform samples
        # (sqrt, sincos) stay within it too.
        return gamma(5) * dr.abs(p)

    object_area = 4.0 * np.pi

    def sample_area(self, u1, u2):
        return square_to_uniform_sphere(u1, u2)

    def world_bounds(self, matrices):
        # Exact ellipsoid bounds: centre +- the row norms of the linear part.
        linear = matrices[:, :3, :3]
        r = np.sqrt(np.einsum("kij,kij->ki", linear, linear))
        c = matrices[:, :3, 3]
        return c - r, c + r

    def _curve_pieces(self, cam, w):
        # The circle of tangency x . cam = w seen from (cam, w): centre w cam / |cam|^2,
        # radius sqrt(1 - w^2 / |cam|^2) (a great circle from infinity); none from inside.
        r2 = np.einsum("ij,ij->i", cam, cam)
        outside = r2 > w * w
        n = cam / np.sqrt(r2)[:, None]
        a, b = orthonormal_pair(n)
        radius = np.sqrt(np.maximum(1.0 - w * w / r2, 0.0))[:, None]
        return [(outside, True, cam * (w / r2)[:, None], a * radius, b * radius)]

    def sample_silhouette(self, view, u, creases=False):
        # The circle of tangency x . view = 1: centre view / |view|^2, radius
        # sqrt(1 - 1 / |view|^2), in the plane perpendicular to view (none from inside).
        r2 = dr.squared_norm(view)
        a, b = frame(view / dr.sqrt(r2))
        radius = dr.sqrt(dr.maximum(1.0 - 1.0 / r2, 0.0))
        return _circle(view / r2, a * radius, b * radius, u) + (r2 > 1.0,)

    def _section_pieces(self, normal, offset):
        # The circle x . n = c on the unit sphere: centre c n, radius sqrt(1 - c^2).
        a, b = orthonormal_pair(normal)
        radius = np.sqrt(np.maximum(1.0 - offset * offset, 0.0))[:, None]
        return [(np.abs(offset) < 1.0, True, normal * offset[:, None], a * radius, b * radius,
                 NORMAL_SPHERE, np.zeros_like(normal))]


class Cylinder(_Quadric):
    """Radius 1 around +z, from z=0 to z=1, open ends; normal (x, y, 0) outward."""

    name = "cylinder"
    curved = True
    object_bounds = ((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0))

    def _intersect(self, o, d, t_max):
        a = dr.fma(d.x, d.x, d.y * d.y)
        half_b = -dr.fma(o.x, d.x, o.y * d.y)
        # Closest approach to the axis in the xy projection (as for the sphere).
        cx = dr.fma(d.x, half_b / a, o.x)
        cy = dr.fma(d.y, half_b / a, o.y)
        disc = a * (1.0 - dr.fma(cx, cx, cy * cy))
        c = dr.fma(o.x, o.x, o.y * o.y) - 1.0
        t0, t1 = _quadratic_roots(a, half_b, c, disc)
        hit = (disc >= 0) & (a > 0)
        z0 = dr.fma(d.z, t0, o.z)
        z1 = dr.fma(d.z, t1, o.z)
        return _nearest_positive(t0, t1, hit & (z0 >= 0) & (z0 <= 1),
                                 hit & (z1 >= 0) & (z1 <= 1), t_max)

    def normal(self, p, prim):
        return type(p)(p.x, p.y, 0.0)

    def uv(self, p):
        # Angle around the axis in turns, height.
        return _turns(p.x, p.y), p.z

    def derivatives(self, p):
        # u: around the axis, a turn per unit; v: along it.
        return type(p)(-p.y, p.x, 0.0) * (2.0 * np.pi), type(p)(0.0, 0.0, 1.0)

    def surface_point(self, o, d, t):
        # As the sphere, in the xy projection (the normal ignores z).
        a = dr.fma(d.x, d.x, d.y * d.y)
        t_closest = -dr.fma(o.x, d.x, o.y * d.y) / a
        cx = dr.fma(d.x, t_closest, o.x)
        cy = dr.fma(d.y, t_closest, o.y)
        half_chord = dr.sqrt(dr.maximum(a * (1.0 - dr.fma(cx, cx, cy * cy)), 0.0)) / a
        step = dr.select(t < t_closest, -half_chord, half_chord)
        x, y = dr.fma(d.x, step, cx), dr.fma(d.y, step, cy)
        # Re-project onto the unit circle in xy; z stays on the ray.
        r = dr.sqrt(dr.fma(x, x, y * y))
        return type(o)(x / r, y / r, dr.fma(d.z, t, o.z))

    def point_error(self, p):
        # pbrt-v4 (cylinder): gamma(3) |(x, y, 0)|; z is along the surface.
        return gamma(3) * type(p)(dr.abs(p.x), dr.abs(p.y), 0.0)

    object_area = 2.0 * np.pi

    def sample_area(self, u1, u2):
        s, c = dr.sincos(2.0 * np.pi * u2)
        return Array3f(c, s, u1)

    def world_bounds(self, matrices):
        lo0, hi0 = _ellipse_bounds(matrices, 0.0)
        lo1, hi1 = _ellipse_bounds(matrices, 1.0)
        return np.minimum(lo0, lo1), np.maximum(hi0, hi1)

    def _curve_pieces(self, cam, w):
        # The two tangent lines q . cam_xy = w (from outside the infinite cylinder) and
        # the rims at z = 0 and z = 1 (open ends).
        m = len(cam)
        cxy = cam.copy()
        cxy[:, 2] = 0.0
        r2 = np.einsum("ij,ij->i", cxy, cxy)
        outside = r2 > w * w
        perp = np.stack([-cxy[:, 1], cxy[:, 0], np.zeros(m)], axis=1)
        root = np.sqrt(np.maximum(r2 - w * w, 0.0))[:, None]
        axis = np.tile([0.0, 0.0, 1.0], (m, 1))
        ex, ey = np.tile([1.0, 0.0, 0.0], (m, 1)), np.tile([0.0, 1.0, 0.0], (m, 1))
        everywhere = np.ones(m, bool)
        pieces = []
        for sign in (1.0, -1.0):
            # (Kept only outside, where r2 > w^2 >= 0; elsewhere divided by 1, not 0.)
            q = (cxy * w[:, None] + sign * root * perp) / np.where(outside, r2, 1.0)[:, None]
            pieces.append((outside, False, q, axis, np.zeros((m, 3))))
        for z in (0.0, 1.0):
            pieces.append((everywhere, True, axis * z, ex, ey))
        return pieces

    convex = False

    def sample_silhouette(self, view, u, creases=False):
        # Four equal pieces: the two tangent lines q . view_xy = 1 (from outside the
        # infinite cylinder) and the rims at z = 0 and z = 1 (open ends).
        scaled = u * 4.0
        piece = dr.minimum(dr.floor(scaled), 3.0)
        s = scaled - piece
        r2 = dr.fma(view.x, view.x, view.y * view.y)
        root = dr.sqrt(dr.maximum(r2 - 1.0, 0.0))
        sign = dr.select(piece == 0.0, 1.0, -1.0)
        q = Array3f(view.x + sign * root * -view.y, view.y + sign * root * view.x, 0.0) / r2
        line = q + Array3f(0.0, 0.0, s)
        rim, rim_tangent = _circle(Array3f(0.0, 0.0, dr.select(piece == 3.0, 1.0, 0.0)),
                                   Array3f(1.0, 0.0, 0.0), Array3f(0.0, 1.0, 0.0), s)
        on_line = piece < 2.0
        point = dr.select(on_line, line, rim)
        tangent = dr.select(on_line, Array3f(0.0, 0.0, 1.0), rim_tangent) * 4.0
        return point, tangent, ~on_line | (r2 > 1.0)

    def _section_pieces(self, normal, offset):
        # Over the unit circle (cos, sin), the plane's height z = (c - n_x cos - n_y sin) / n_z:
        # an ellipse c + u cos + v sin, clipped to 0 <= z <= 1 where it is sampled. (A plane
        # along the axis meets the tube in lines; not sampled.)
        nz = normal[:, 2]
        upright = np.abs(nz) > 1e-6
        nz = np.where(upright, nz, 1.0)
        zero = np.zeros(len(normal))
        c = np.stack([zero, zero, offset / nz], axis=1)
        u = np.stack([zero + 1.0, zero, -normal[:, 0] / nz], axis=1)
        v = np.stack([zero, zero + 1.0, -normal[:, 1] / nz], axis=1)
        return [(upright, True, c, u, v, NORMAL_CYLINDER, np.zeros_like(normal))]


class _Planar(AnalyticModel):
    """Shapes in the plane z = 0 with normal +z on both sides."""

    flat = True

    def intersect(self, o, d, t_max, wide=False):
        t = -o.z / d.z
        x = dr.fma(d.x, t, o.x)
        y = dr.fma(d.y, t, o.y)
        return _nearest_positive(t, t, self.inside(x, y), False, t_max)

    def inside(self, x: Float, y: Float) -> Bool:
        raise NotImplementedError

    def normal(self, p, prim):
        return type(p)(0.0, 0.0, 1.0)

    def surface_point(self, o, d, t):
        # Re-project onto the plane: z = 0 exactly.
        return type(o)(dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y), 0.0)

    def point_error(self, p):
        # z = 0 is exact (pbrt-v4's disk): no error across the plane.
        return type(p)(0.0)

    def _section_pieces(self, normal, offset):
        keep, start, along = self._chord(normal[:, :2], offset)
        flat = np.zeros_like(normal)
        up = flat + [0.0, 0.0, 1.0]
        return [(keep, False, np.concatenate([start, flat[:, :1]], axis=1),
                 np.concatenate([along, flat[:, :1]], axis=1), flat, NORMAL_STORED, up)]

    def _chord(self, normal, offset):
        """Where the lines ``normal . (x, y) = offset`` cross the shape in z = 0."""
        raise NotImplementedError


class Rectangle(_Planar):
    """[-1, 1]^2 in the plane z = 0, normal +z."""

    name = "rectangle"
    object_bounds = ((-1.0, -1.0, 0.0), (1.0, 1.0, 0.0))

    def inside(self, x, y):
        return (dr.abs(x) <= 1) & (dr.abs(y) <= 1)

    def uv(self, p):
        return dr.fma(p.x, 0.5, 0.5), dr.fma(p.y, 0.5, 0.5)

    def derivatives(self, p):
        return type(p)(2.0, 0.0, 0.0), type(p)(0.0, 2.0, 0.0)

    object_area = 4.0

    def sample_area(self, u1, u2):
        return Array3f(2.0 * u1 - 1.0, 2.0 * u2 - 1.0, 0.0)

    def sample_silhouette(self, view, u, creases=False):
        # The four sides, from every viewpoint, a quarter of u each: corner k to corner k + 1
        # counter-clockwise from (-1, -1).
        scaled = u * 4.0
        side = dr.minimum(dr.floor(scaled), 3.0)
        s = 2.0 * (scaled - side) - 1.0
        x = dr.select(side == 0.0, s, dr.select(side == 1.0, 1.0, dr.select(side == 2.0, -s, -1.0)))
        y = dr.select(side == 0.0, -1.0, dr.select(side == 1.0, s, dr.select(side == 2.0, 1.0, -s)))
        tx = dr.select(side == 0.0, 1.0, dr.select(side == 2.0, -1.0, 0.0))
        ty = dr.select(side == 1.0, 1.0, dr.select(side == 3.0, -1.0, 0.0))
        return Array3f(x, y, 0.0), Array3f(tx, ty, 0.0) * 8.0, Bool(True)

    def _chord(self, normal, offset):
        return square_chord(normal, offset)

    def _curve_pieces(self, cam, w):
        # The four sides, from every viewpoint.
        m = len(cam)
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        pieces = []
        for k in range(4):
            (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
            pieces.append((np.ones(m, bool), False, np.tile([x0, y0, 0.0], (m, 1)),
                           np.tile([x1 - x0, y1 - y0, 0.0], (m, 1)), np.zeros((m, 3))))
        return pieces


class Disk(_Planar):
    """Unit disk in the plane z = 0, normal +z."""

    name = "disk"
    object_bounds = ((-1.0, -1.0, 0.0), (1.0, 1.0, 0.0))

    def inside(self, x, y):
        return dr.fma(x, x, y * y) <= 1

    def uv(self, p):
        # Radius, angle in turns.
        return dr.sqrt(dr.fma(p.x, p.x, p.y * p.y)), _turns(p.x, p.y)

    def derivatives(self, p):
        # u: outwards along the radius; v: around the centre, a turn per unit (both 0 at
        # the centre, as Mitsuba's).
        r = dr.sqrt(dr.fma(p.x, p.x, p.y * p.y))
        inv = dr.select(r == 0, 0.0, dr.rcp(r))
        cos_phi, sin_phi = p.x * inv, p.y * inv
        return type(p)(cos_phi, sin_phi, 0.0), type(p)(-sin_phi, cos_phi, 0.0) * (2.0 * np.pi * r)

    object_area = np.pi

    def sample_area(self, u1, u2):
        r = dr.sqrt(u1)
        s, c = dr.sincos(2.0 * np.pi * u2)
        return Array3f(r * c, r * s, 0.0)

    def world_bounds(self, matrices):
        return _ellipse_bounds(matrices, 0.0)

    def _chord(self, normal, offset):
        length2 = np.maximum(np.einsum("ij,ij->i", normal, normal), 1e-300)
        point = normal * (offset / length2)[:, None]
        half = np.sqrt(np.maximum(1.0 - np.einsum("ij,ij->i", point, point), 0.0) / length2)
        direction = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        keep = np.einsum("ij,ij->i", point, point) < 1.0
        return keep, point - direction * half[:, None], 2.0 * direction * half[:, None]

    def sample_silhouette(self, view, u, creases=False):
        # The rim, from every viewpoint.
        return _circle(Array3f(0.0), Array3f(1.0, 0.0, 0.0), Array3f(0.0, 1.0, 0.0), u) + (Bool(True),)

    def _curve_pieces(self, cam, w):
        # The rim, from every viewpoint.
        m = len(cam)
        return [(np.ones(m, bool), True, np.zeros((m, 3)), np.tile([1.0, 0.0, 0.0], (m, 1)),
                 np.tile([0.0, 1.0, 0.0], (m, 1)))]


class Cube(AnalyticModel):
    """The box [-1, 1]^3 (Mitsuba's ``cube``), intersected by the slab method.

    Mitsuba builds its cube from 12 triangles; the analytic slab test gives
    the same surface at a fraction of the cost. ``prim`` is always 0.
    """

    name = "cube"
    object_bounds = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))

    def intersect(self, o, d, t_max, wide=False):
        # Entering parameter: last slab entered; exiting: first slab left.
        t_enter, t_exit = slab_interval(type(o)(-1.0), type(o)(1.0), o, dr.rcp(d))
        hit = t_enter <= t_exit
        return _nearest_positive(t_enter, t_exit, hit, hit, t_max)

    def normal(self, p, prim):
        on_x, on_y, on_z = self._face_axis(p)
        return type(p)(dr.select(on_x, dr.sign(p.x), 0.0),
                       dr.select(on_y, dr.sign(p.y), 0.0),
                       dr.select(on_z, dr.sign(p.z), 0.0))

    #: Per face (axis, sign of the coordinate), the coordinates that u and v follow as
    #: (axis, sign): u = (sign p[axis] + 1) / 2; Mitsuba's cube mesh maps each face onto
    #: [0, 1]^2 so (read from its texture coordinates, checked in the tests).
    FACE_UV = {(0, -1): ((1, 1), (2, 1)), (0, 1): ((1, 1), (2, -1)),
               (1, -1): ((2, 1), (0, 1)), (1, 1): ((0, -1), (2, -1)),
               (2, -1): ((1, -1), (0, 1)), (2, 1): ((1, 1), (0, 1))}

    def uv(self, p):
        faces = self._face_axis(p)
        coordinate = (p.x, p.y, p.z)
        u, v = type(p.x)(0.0), type(p.x)(0.0)
        for (axis, sign), ((ua, us), (va, vs)) in self.FACE_UV.items():
            on = faces[axis] & ((coordinate[axis] < 0) if sign < 0 else (coordinate[axis] >= 0))
            u = dr.select(on, dr.fma(coordinate[ua], 0.5 * us, 0.5), u)
            v = dr.select(on, dr.fma(coordinate[va], 0.5 * vs, 0.5), v)
        return u, v

    def derivatives(self, p):
        # On each face, twice the unit vectors along the coordinates that u and v follow
        # (FACE_UV), in their directions.
        faces = self._face_axis(p)
        coordinate = (p.x, p.y, p.z)
        axes, signs = [type(p.x)(0.0), type(p.x)(0.0)], [type(p.x)(0.0), type(p.x)(0.0)]
        for (face, side), along in self.FACE_UV.items():
            on = faces[face] & ((coordinate[face] < 0) if side < 0 else (coordinate[face] >= 0))
            for k, (axis, sign) in enumerate(along):
                axes[k] = dr.select(on, axis, axes[k])
                signs[k] = dr.select(on, sign, signs[k])
        return tuple(type(p)(*[dr.select(axis == a, 2.0 * sign, 0.0) for a in range(3)])
                     for axis, sign in zip(axes, signs))

    @staticmethod
    def _face_axis(p: Array3f) -> tuple[Bool, Bool, Bool]:
        """The face hit: the axis of largest |p_i| (all others are <= 1 on the surface)."""
        a = dr.abs(p)
        on_x = (a.x >= a.y) & (a.x >= a.z)
        on_y = ~on_x & (a.y >= a.z)
        return on_x, on_y, ~on_x & ~on_y

    def surface_point(self, o, d, t):
        # Re-project onto the face hit: its coordinate is exactly +-1.
        p = dr.fma(d, t, o)
        on_x, on_y, on_z = self._face_axis(p)
        return type(p)(dr.select(on_x, dr.sign(p.x), p.x), dr.select(on_y, dr.sign(p.y), p.y),
                       dr.select(on_z, dr.sign(p.z), p.z))

    def point_error(self, p):
        # The face coordinate is exact; the others lie along the face.
        return type(p)(0.0)

    object_area = 24.0

    def sample_area(self, u1, u2):
        # Pick one of the six faces with u1, reuse its fraction as the first face coordinate.
        scaled = u1 * 6.0
        face = dr.minimum(dr.floor(scaled), 5.0)
        a = 2.0 * (scaled - face) - 1.0
        b = 2.0 * u2 - 1.0
        axis = dr.floor(face * 0.5)
        side = dr.select(face == 2.0 * axis, 1.0, -1.0)
        return Array3f(dr.select(axis == 0, side, a),
                       dr.select(axis == 1, side, dr.select(axis == 0, a, b)),
                       dr.select(axis == 2, side, b))

    def sample_silhouette(self, view, u, creases=False):
        # The 12 edges, a twelfth of u each: edge k runs along axis k // 4 at the signs
        # (k % 2, k // 2 % 2) of the other two axes. It is a silhouette where exactly one
        # of its two faces (x_i = sigma_i: seen from where sigma_i view_i > 1) is seen, a
        # crease where either is.
        scaled = u * 12.0
        k = dr.minimum(dr.floor(scaled), 11.0)
        s = 2.0 * (scaled - k) - 1.0
        axis = dr.floor(k * 0.25)
        rest = k - 4.0 * axis
        sign_i = dr.select(rest - 2.0 * dr.floor(rest * 0.5) == 0.0, -1.0, 1.0)
        sign_j = dr.select(rest < 2.0, -1.0, 1.0)
        # The other two axes in cyclic order (i, j) = (axis + 1, axis + 2) mod 3.
        coords = [None, None, None]
        seen = []
        for a in range(3):
            i, j = (a + 1) % 3, (a + 2) % 3
            mine = axis == float(a)
            view_i, view_j = view[i], view[j]
            seen.append((mine, sign_i * view_i > 1.0, sign_j * view_j > 1.0))
            for c, value in ((a, s), (i, sign_i), (j, sign_j)):
                coords[c] = dr.select(mine, value, 0.0 if coords[c] is None else coords[c])
        face_i = dr.select(seen[0][0], seen[0][1], dr.select(seen[1][0], seen[1][1], seen[2][1]))
        face_j = dr.select(seen[0][0], seen[0][2], dr.select(seen[1][0], seen[1][2], seen[2][2]))
        tangent = Array3f(*[dr.select(axis == float(c), 24.0, 0.0) for c in range(3)])
        return Array3f(*coords), tangent, (face_i | face_j) if creases else face_i != face_j

    def discontinuity_curves(self, viewpoints, creases=True):
        # Mitsuba's cube is 12 triangles: its edges (see EdgeTopology).
        return _CUBE_EDGES.discontinuity_curves(viewpoints, creases)

    def _section_pieces(self, normal, offset):
        # Face by face (x_k = side), the plane is a line in the face's other two axes.
        pieces = []
        for k in range(3):
            i, j = [a for a in range(3) if a != k]
            for side in (-1.0, 1.0):
                keep, start, along = square_chord(normal[:, [i, j]], offset - normal[:, k] * side)
                c, u = np.zeros_like(normal), np.zeros_like(normal)
                c[:, [i, j]], c[:, k], u[:, [i, j]] = start, side, along
                face = np.zeros_like(normal)
                face[:, k] = side
                pieces.append((keep, False, c, u, np.zeros_like(normal), NORMAL_STORED, face))
        return pieces


#: The cube's 12 triangles as Mitsuba builds them, for its edges.
_CUBE_EDGES = EdgeTopology.of_mesh(
    np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)]),
    np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
              [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]))


ANALYTIC_MODELS: dict[str, AnalyticModel] = {
    m.name: m for m in (Sphere(), Cube(), Rectangle(), Disk(), Cylinder())}
