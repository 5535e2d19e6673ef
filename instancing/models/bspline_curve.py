"""Cubic B-spline curves (Mitsuba's ``bsplinecurve``): round tubes along uniform cubic B-splines.

A curve of n >= 4 control points (each with a radius) has n - 3 segments; segment s is the
uniform cubic B-spline of points s .. s + 3, its centre line c(v) and radius r(v) for v in
[0, 1], so that consecutive segments join with continuous tangent and curvature. The
surface is Embree's round B-spline curve, which Mitsuba's plugin traces: the union of the
circles of radius r(v) about c(v) in the planes normal to the tangent c'(v). It is open (no
caps at a curve's ends) and seen from outside only: a hit whose normal faces along the ray
is culled, as Embree and Mitsuba cull curve backfaces. Mitsuba's ``to_world`` of a plain
curve moves its control points, not its radii, so a model holds its points already moved;
instances place it by their affine maps, as for any model.

The test, on pieces of the segments (BVH items): each segment is split in halves until
every piece's control polygon stays within a tenth of its chord's length of the chord
(:data:`STRAIGHTNESS`; Embree calls a piece well behaved at a fifth), at most 2^5 pieces. In
a frame where the ray runs along +z from a point near the piece (a rotation and a shift
along the ray), a ray that passes farther than the piece's largest radius from the box of
its Bezier points misses it; otherwise the ray meets the plane normal to a = c'(s) at
z = (c . a) / a_z, and that point lies on the circle exactly where

    G(s) = a_z^2 (c_x^2 + c_y^2 - r^2) + (a_x c_x + a_y c_y)^2 = 0,

a polynomial of the piece's parameter s. On a nearly straight piece G has at most one
extremum (on a straight tube it is a quadratic: convex, or concave where the radius changes
faster than the tube runs across the ray). Step 1 finds it by Newton's method on G' kept
inside a bracket (bisection where a step leaves it); step 2 finds the root of G on either
side of it the same way, where G changes sign there; step 3 keeps the nearest root in front
of the ray whose normal faces the ray. The normal is Mitsuba's: the gradient of the squared
distance to the centre within the circle's plane,
``(|c'|^2 - (p - c) . c'') (p - c) - r r' c'``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..accel.bvh import BVHKernel, build_forest
from ..core.backend import (Array2f, Array2f64, Array3f, Array3f64, Array4f, Array4f64, Bool, Float, Float64,
                            UInt32, device_array, dr)
from ..core.error_bounds import gamma
from .linear_curve import ControlPointCurves, checked_rows, local_frame

#: Pieces per BVH leaf at most.
PIECE_LEAF_SIZE = 2
#: Halvings of a segment at most (2^5 pieces).
MAX_SPLITS = 5
#: A piece is well behaved when each leg of its control polygon, times 3, differs from its
#: chord by at most this fraction of the chord's length (Embree's criterion at half its bound).
STRAIGHTNESS = 0.1
#: Newton steps of each search (G's extremum, then each root) in float32 (phase 1) and in
#: float64 (phase 2, one piece per ray).
SEARCH_STEPS = 6
SEARCH_STEPS_FLOAT64 = 12

#: Uniform cubic B-spline to Bezier: Bezier point i = sum_j BSPLINE_TO_BEZIER[i, j] P_j.
BSPLINE_TO_BEZIER = np.array([[1, 4, 1, 0], [0, 4, 2, 0], [0, 2, 4, 0], [0, 1, 4, 1]]) / 6.0
#: Bezier to power basis: coefficient k of s^k = sum_i BEZIER_TO_POWER[k, i] B_i.
BEZIER_TO_POWER = np.array([[1, 0, 0, 0], [-3, 3, 0, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], np.float64)
#: Uniform cubic B-spline to power basis: coefficient k of v^k = sum_j BSPLINE_TO_POWER[k, j] P_j.
BSPLINE_TO_POWER = BEZIER_TO_POWER @ BSPLINE_TO_BEZIER


@dataclass(frozen=True, eq=False)
class BSplineCurveData(ControlPointCurves):
    """B-spline curves (see :class:`~instancing.models.linear_curve.ControlPointCurves`):
    segment s is the spline of points first[s] .. first[s] + 3."""

    @staticmethod
    def from_rows(rows: np.ndarray, curve: np.ndarray, where: str) -> "BSplineCurveData":
        """The curves of control points ``rows`` (K, 4), point k in curve ``curve[k]``."""
        return BSplineCurveData(rows[:, :3].copy(), rows[:, 3].copy(),
                                checked_rows(rows, curve, where, 4, "B-spline curve"))

    def curve_starts(self) -> np.ndarray:
        """The first control point of each curve (a segment not following its predecessor's)."""
        return self.first[np.concatenate([[True], self.first[1:] != self.first[:-1] + 1])]

    def rows32(self) -> np.ndarray:
        """(K, 4) the control points (x, y, z, radius) rounded to float32, as stored for tracing
        (as Mitsuba stores them)."""
        return np.concatenate([self.points, self.radii[:, None]], axis=1).astype(np.float32)

    def bezier(self) -> np.ndarray:
        """(S, 4, 4): per segment its four Bezier control points (x, y, z, radius), in float64
        from the float32 control points."""
        return BSPLINE_TO_BEZIER @ self.rows32().astype(np.float64)[self.first[:, None] + np.arange(4)]


def split_pieces(bezier: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The segments' well-behaved pieces: (piece Bezier points (P, 4, 4), segment (P,), the
    piece's range (v0, v1) (P, 2) of its segment's parameter), each segment's pieces in
    order. Halves a piece (de Casteljau at 1/2) until its control polygon follows its chord
    (:data:`STRAIGHTNESS`) or it has been halved :data:`MAX_SPLITS` times."""
    pending = (bezier, np.arange(len(bezier)), np.zeros(len(bezier)), np.ones(len(bezier)))
    done = []
    for round_ in range(MAX_SPLITS + 1):
        pieces, segment, v0, v1 = pending
        xyz = pieces[:, :, :3]
        chord = xyz[:, 3] - xyz[:, 0]
        legs = 3.0 * np.diff(xyz, axis=1) - chord[:, None]
        bent = np.abs(legs).max(axis=(1, 2)) > STRAIGHTNESS * np.linalg.norm(chord, axis=1)
        if round_ == MAX_SPLITS:
            bent[:] = False
        done.append(tuple(x[~bent] for x in pending))
        if not bent.any():
            break
        b, middle = pieces[bent], 0.5 * (v0[bent] + v1[bent])
        m01, m12, m23 = 0.5 * (b[:, 0] + b[:, 1]), 0.5 * (b[:, 1] + b[:, 2]), 0.5 * (b[:, 2] + b[:, 3])
        m012, m123 = 0.5 * (m01 + m12), 0.5 * (m12 + m23)
        mid = 0.5 * (m012 + m123)
        pending = (np.concatenate([np.stack([b[:, 0], m01, m012, mid], axis=1),
                                   np.stack([mid, m123, m23, b[:, 3]], axis=1)]),
                   np.tile(segment[bent], 2), np.concatenate([v0[bent], middle]),
                   np.concatenate([middle, v1[bent]]))
    pieces, segment, v0, v1 = (np.concatenate(parts) for parts in zip(*done))
    order = np.lexsort((v0, segment))
    return pieces[order], segment[order], np.stack([v0, v1], axis=1)[order]


# -- a piece's geometry, in the precision of its arguments --------------------------------

def _dot(a, b):
    return dr.fma(a.x, b.x, dr.fma(a.y, b.y, a.z * b.z))


def _ray_basis(dn):
    """Two unit vectors completing the unit ``dn`` to an orthonormal frame (Duff et al. 2017)."""
    sign = dr.copysign(1.0, dn.z)
    a = -1.0 / (sign + dn.z)
    b = dn.x * dn.y * a
    vector = type(dn)
    return (vector(dr.fma(sign * dn.x * dn.x, a, 1.0), sign * b, -sign * dn.x),
            vector(b, dr.fma(dn.y * dn.y, a, sign), -dn.y))


class _Polynomial:
    """A piece's centre line and radius as cubics of s in the ray's frame: value, first,
    second and third derivatives at s."""

    def __init__(self, coefficients):
        self.k = coefficients  # four (x, y, z, r) tuples of power coefficients

    def at(self, s):
        k0, k1, k2, k3 = self.k
        value = [dr.fma(dr.fma(dr.fma(c3, s, c2), s, c1), s, c0) for c0, c1, c2, c3 in zip(k0, k1, k2, k3)]
        first = [dr.fma(dr.fma(3.0 * c3, s, 2.0 * c2), s, c1) for c1, c2, c3 in zip(k1, k2, k3)]
        second = [dr.fma(6.0 * c3, s, 2.0 * c2) for c2, c3 in zip(k2, k3)]
        third = [6.0 * c3 for c3 in k3]
        return value, first, second, third


def _in_ray_frame(o, d, k):
    """The piece of power coefficients ``k`` (four (x, y, z, r) tuples) in a frame where the
    ray runs along +z from its point nearest the piece's middle (so that the cubics see
    coordinates of the piece's size): (its :class:`_Polynomial`, the distance to that point
    along the unit direction, |d|)."""
    vector = type(o)
    length = dr.norm(d)
    dn = d / length
    e1, e2 = _ray_basis(dn)
    k0, k1, k2, k3 = (vector(c[0], c[1], c[2]) for c in k)
    shift = _dot(k0 + 0.5 * k1 + 0.25 * k2 + 0.125 * k3 - o, dn)
    k0 = k0 - dr.fma(dn, shift, o)
    return (_Polynomial([(_dot(e1, v), _dot(e2, v), _dot(dn, v), c[3]) for v, c in zip((k0, k1, k2, k3), k)]),
            shift, length)


def _g(poly, s):
    """(G, G', G'') at s (see the module docstring)."""
    (cx, cy, _, r), (ax, ay, az, r1), (bx, by, bz, r2), (ex, ey, ez, _) = poly.at(s)
    p = dr.fma(cx, cx, dr.fma(cy, cy, -r * r))
    q = dr.fma(ax, cx, ay * cy)
    p1 = 2.0 * (q - r * r1)
    q1 = dr.fma(bx, cx, dr.fma(by, cy, dr.fma(ax, ax, ay * ay)))
    p2 = 2.0 * (q1 - dr.fma(r1, r1, r * r2))
    q2 = dr.fma(ex, cx, dr.fma(ey, cy, 3.0 * dr.fma(bx, ax, by * ay)))
    az2 = az * az
    g = dr.fma(az2, p, q * q)
    g1 = dr.fma(2.0 * az * bz, p, dr.fma(az2, p1, 2.0 * q * q1))
    g2 = (2.0 * dr.fma(bz, bz, az * ez) * p + 4.0 * az * bz * p1 + az2 * p2
          + 2.0 * dr.fma(q1, q1, q * q2))
    return g, g1, g2


def _bracketed_newton(f, lo, hi, s, rising, steps):
    """The zero in [lo, hi] of the function ``f(s) -> (value, slope)`` whose sign goes from
    negative to positive (``rising``) or the reverse across the bracket, from ``s``: Newton
    steps, bisection where a step leaves the bracket, the bracket narrowed by each value's
    sign (a converged s, at an end of its bracket, stays)."""
    for _ in range(steps):
        value, slope = f(s)
        below = (value < 0) == rising
        lo, hi = dr.select(below, s, lo), dr.select(below, hi, s)
        step = s - value / slope
        s = dr.select((step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
    return s


def piece_hit(o, d, k, steps: int = SEARCH_STEPS):
    """Nearest front-facing hit of the rays ``o + t d`` on the tube of the piece whose power
    coefficients ``k`` are four (x, y, z, r) tuples: (t, s) with t = inf where none is (t in
    units of d, s the piece's parameter); ``steps`` Newton steps per search."""
    poly, shift, length = _in_ray_frame(o, d, k)
    # The ray can meet the tube only where it passes within the largest radius of the piece's
    # Bezier points' box in the ray's frame (tighter than the BVH's box of a slanted piece):
    # the search runs in a branch that a packet none of whose rays does skips.
    k0, k1, k2, k3 = poly.k
    bezier = [k0, [a + b / 3.0 for a, b in zip(k0, k1)],
              [a + (2.0 * b + c) / 3.0 for a, b, c in zip(k0, k1, k2)],
              [a + b + c + e for a, b, c, e in zip(k0, k1, k2, k3)]]
    reach = dr.maximum(dr.maximum(bezier[0][3], bezier[1][3]), dr.maximum(bezier[2][3], bezier[3][3]))
    near = Bool(True)
    for axis in (0, 1):
        values = [b[axis] for b in bezier]
        lowest = dr.minimum(dr.minimum(values[0], values[1]), dr.minimum(values[2], values[3]))
        highest = dr.maximum(dr.maximum(values[0], values[1]), dr.maximum(values[2], values[3]))
        near &= (lowest <= reach) & (highest >= -reach)
    scalar = type(o.x)
    return dr.if_stmt((poly.k, shift, length), near, lambda *args: _search(*args, steps),
                      lambda k, shift, length: (scalar(dr.inf), scalar(0.0)))


def _search(k, shift, length, steps):
    """:func:`piece_hit`'s steps on the piece of power coefficients ``k`` in the ray's frame
    (the ray from ``shift`` along its unit direction; |d| ``length``)."""
    poly = _Polynomial(k)
    scalar = type(shift)

    # Step 1: G's extremum where G' changes sign in the piece (at most once on a piece this
    # straight), else none (s = 1): it parts the piece into two pieces on which G is monotone.
    g_lo, g1_lo, _ = _g(poly, scalar(0.0))
    g_hi, g1_hi, _ = _g(poly, scalar(1.0))
    turns = (g1_lo < 0) != (g1_hi < 0)
    # (From where G' would vanish if it were linear: G's extremum on a straight tube.)
    s_turn = _bracketed_newton(lambda s: _g(poly, s)[1:], scalar(0.0), scalar(1.0), g1_lo / (g1_lo - g1_hi),
                               g1_lo < 0, steps)
    s_turn = dr.select(turns, s_turn, 1.0)
    g_turn, _, g2_turn = _g(poly, s_turn)

    # Step 2: a root in each part whose ends' G differ in sign, from where G's parabola at a
    # minimum has its zero (a thin tube's dip is narrow), else from the chord's zero; step
    # 3: the nearest front-facing one.
    reach = dr.sqrt(dr.maximum(-2.0 * g_turn / g2_turn, 0.0))
    best_t, best_s = scalar(dr.inf), scalar(0.0)
    for lo, hi, g_a, g_b, start in ((scalar(0.0), s_turn, g_lo, g_turn, s_turn - reach),
                                    (s_turn, scalar(1.0), g_turn, g_hi, s_turn + reach)):
        chord = dr.fma(hi - lo, g_a / (g_a - g_b), lo)
        start = dr.select(turns & (g2_turn > 0) & (start >= lo) & (start <= hi), start, chord)
        s = _bracketed_newton(lambda s: _g(poly, s)[:2], lo, hi, start, g_a < 0, steps)
        (cx, cy, cz, r), (ax, ay, az, r1), (bx, by, bz, _), _ = poly.at(s)
        q = dr.fma(ax, cx, ay * cy)
        # Along the ray from the circle's centre's foot: the sign of q / a_z, the length
        # from the circle (stable where a_z and q both vanish).
        h = dr.copysign(dr.sqrt(dr.maximum(r * r - dr.fma(cx, cx, cy * cy), 0.0)), q * az)
        # The normal's component along the ray (+z): front-facing where it is negative.
        bend = dr.fma(ax, ax, dr.fma(ay, ay, az * az)) - dr.fma(-cx, bx, dr.fma(-cy, by, h * bz))
        facing = dr.fma(bend, h, -r * r1 * az) < 0
        t = (shift + cz + h) / length
        ok = ((g_a < 0) != (g_b < 0)) & facing & (t > 0) & (t < best_t)
        best_t, best_s = dr.select(ok, t, best_t), dr.select(ok, s, best_s)
    return best_t, best_s


class BSplineCurveLibrary:
    """The scene's B-spline curve models, their pieces in one BVH forest.

    Per leaf (a piece, in leaf order): the float32 power coefficients of its centre line and
    radius as four float4 packets (x, y, z, r) for phase 1, its segment's first control point
    (the models' float32 control points, one float4 packet each, are phase 2's data), its
    segment's index among its model's segments (Mitsuba's primitive index), its range (v0, v1)
    of the segment's parameter, and its model's segment count (for v).
    """

    def __init__(self, curves: list[BSplineCurveData]):
        lo_parts, hi_parts, sizes, coefficients, prim, span, count, first = [], [], [], [], [], [], [], []
        offset = 0
        #: Per model, the object-space box of its pieces.
        self.object_bounds: list[tuple[np.ndarray, np.ndarray]] = []
        for curve in curves:
            bezier, segment, piece_span = split_pieces(curve.bezier())
            # A piece lies within its Bezier points' hull, its tube within the largest of
            # their radii (the Bernstein weights are positive and sum to 1).
            reach = bezier[:, :, 3].max(axis=1)[:, None]
            lo = bezier[:, :, :3].min(axis=1) - reach
            hi = bezier[:, :, :3].max(axis=1) + reach
            lo_parts.append(lo)
            hi_parts.append(hi)
            self.object_bounds.append((lo.min(axis=0), hi.max(axis=0)))
            sizes.append(len(bezier))
            coefficients.append((BEZIER_TO_POWER @ bezier).reshape(-1, 16))
            prim.append(segment)
            span.append(piece_span)
            count.append(np.full(len(bezier), len(curve.first)))
            first.append(offset + curve.first[segment])
            offset += len(curve.points)
        trees, self.root_refs = build_forest(np.concatenate(lo_parts), np.concatenate(hi_parts), sizes,
                                             PIECE_LEAF_SIZE)
        order = trees.order
        self.kernel = BVHKernel(trees, frontier=0, nested=True)
        self.coefficients = device_array(Float, np.concatenate(coefficients)[order].astype(np.float32).ravel())
        self.prim = device_array(UInt32, np.concatenate(prim)[order].astype(np.uint32))
        self.span = device_array(Float, np.concatenate(span)[order].astype(np.float32).ravel())
        self.segment_count = device_array(Float64, np.concatenate(count)[order].astype(np.float64))
        self.first = device_array(UInt32, np.concatenate(first)[order].astype(np.uint32))
        self.points = device_array(Float, np.concatenate([curve.rows32() for curve in curves]).ravel())
        #: Curves shade by their geometric normal.
        self.smooth = [False] * len(curves)

    def _coefficients(self, position: UInt32):
        """The float32 power coefficients of the piece at leaf ``position``: four (x, y, z, r)
        tuples."""
        packets = [dr.gather(Array4f, self.coefficients, 4 * position + k) for k in range(4)]
        return [(p.x, p.y, p.z, p.w) for p in packets]

    def _coefficients64(self, position: UInt32, span: Array2f64):
        """The piece's power coefficients in float64 from its segment's float32 control points:
        the segment's cubic in v, re-parameterized to the piece's range v0 + (v1 - v0) s."""
        first = dr.gather(UInt32, self.first, position)
        points = [Array4f64(dr.gather(Array4f, self.points, first + j)) for j in range(4)]
        a = [sum(float(BSPLINE_TO_POWER[k, j]) * points[j] for j in range(4)) for k in range(4)]
        v0, width = span.x, span.y - span.x
        value = dr.fma(dr.fma(dr.fma(a[3], v0, a[2]), v0, a[1]), v0, a[0])
        slope = dr.fma(dr.fma(3.0 * a[3], v0, 2.0 * a[2]), v0, a[1])
        bend = dr.fma(3.0 * a[3], v0, a[2])
        k = [value, width * slope, width * width * bend, width * width * width * a[3]]
        return [(c.x, c.y, c.z, c.w) for c in k]

    def intersect(self, o: Array3f, d: Array3f, t_max: Float, active, root_ref: UInt32,
                  any_hit: bool = False) -> tuple[Float, UInt32]:
        """Nearest piece hit of object-space rays through the model whose root is
        ``root_ref``: ``(t, position)`` with t = inf where nothing is hit in (0, t_max);
        ``position`` is the leaf-order piece. With ``any_hit``, the walk stops at the first
        piece hit."""
        def distance(position, t_best):
            t = piece_hit(o, d, self._coefficients(position))[0]
            return dr.select(t < t_best, t, dr.inf)

        return self.kernel.nearest(o, d, t_max, active, root_ref, any_hit, distance)

    def surface_point(self, o, d, position: UInt32, t_first, uv: bool, tangents: bool):
        """Differentiable float64 (t, object-space point, normal (not normalized), the point's
        error bound, uv, dp/du, dp/dv) of the rays' hits on the piece at ``position`` (uv
        and the tangents 0 unless asked for); where the second test misses (a grazing ray),
        t is inf and the point lies at ``t_first``.

        The piece's test again in float64 (detached) gives the circle's parameter s; one
        Newton step of the circle's equation with the rays attached moves s with them, and
        t is then where the ray crosses that circle's plane (the implicit function theorem's
        first derivatives)."""
        span = Array2f64(dr.gather(Array2f, self.span, position))
        k = self._coefficients64(position, span)
        with dr.suspend_grad():
            t_detached, s = piece_hit(dr.detach(o), dr.detach(d), k, SEARCH_STEPS_FLOAT64)
        curve = _Polynomial(k)

        def crossing(s):
            (cx, cy, cz, r), (ax, ay, az, r1), second, third = curve.at(s)
            c, a = Array3f64(cx, cy, cz), Array3f64(ax, ay, az)
            t = _dot(c - o, a) / _dot(d, a)
            return t, c, a, r, r1, Array3f64(*second[:3]), Array3f64(*third[:3])

        t, c, a, r, _, _, _ = crossing(s)
        w = dr.fma(d, t, o) - c
        # dG/ds over a_z^2 at a root is the slope of the squared distance to the circle.
        slope = dr.detach(_slope(curve, s, dr.detach(o), dr.detach(d)))
        s = s - (_dot(w, w) - r * r) / slope
        t, c, a, r, r1, b, e = crossing(s)
        found = dr.isfinite(t_detached)
        t = dr.select(found, t, Float64(t_first))
        p = dr.fma(d, t, o)
        w = p - c
        n = dr.fma(_dot(a, a) - _dot(w, b), w, -r * r1 * a)
        width = span.y - span.x
        segments = dr.gather(Float64, self.segment_count, position)
        uv_out, dpdu, dpdv = Array2f64(0.0), Array3f64(0.0), Array3f64(0.0)
        tangent = dr.normalize(a)
        radial = dr.normalize(w)
        if uv or tangents:
            rot, rad = local_frame(tangent)
            u = dr.atan2(_dot(rot, radial), _dot(rad, radial))
            u = dr.select(u < 0, u + 2.0 * dr.pi, u) / (2.0 * dr.pi)
            prim = Float64(dr.gather(UInt32, self.prim, position))
            uv_out = Array2f64(u, (dr.fma(s, width, span.x) + prim) / segments)
        if tangents:
            around = dr.cross(tangent, radial)
            dpdu = 2.0 * dr.pi * r * around
            # Mitsuba's partials: the radial direction carried along v by the Frenet frame,
            # in the segment's parameter v (the piece's s over its width).
            cv, cvv, cvvv = a / width, b / (width * width), e / (width * width * width)
            speed = dr.norm(cv)
            binormal = dr.cross(cv, cvv)
            bending = dr.norm(binormal)
            torsion = _dot(cvvv, binormal) / (bending * bending)
            straight = (bending < speed * speed * speed * 2.0 ** -24)
            torsion = dr.select(straight | (bending < 1e-6) | (dr.norm(cvvv) < 1e-6), 0.0, torsion)
            turn = dr.select(straight, Array3f64(0.0), -(_dot(cvv, radial) / speed) * tangent
                             + speed * torsion * around)
            dpdv = segments * (cv + (r1 / width) * radial + r * turn)
        # The float32 search runs from the ray's point nearest the piece: its rounding
        # scales with |p| and the tube's radius there.
        error = gamma(64) * (dr.abs(p) + dr.norm(w))
        return dr.select(found, t, dr.inf), p, n, error, uv_out, dpdu, dpdv

    def prim_index(self, position: UInt32) -> UInt32:
        """The piece's segment's index among its model's segments, in file order."""
        return dr.gather(UInt32, self.prim, position)


def _slope(curve: _Polynomial, s, o, d):
    """d/ds of the squared distance from the ray's crossing of the circle's plane to the
    circle's centre, minus r^2, at a root: G'(s) / a_z^2 in the ray's frame."""
    poly, _, length = _in_ray_frame(o, d, curve.k)
    az = _dot(d, Array3f64(*curve.at(s)[1][:3])) / length
    return _g(poly, s)[1] / (az * az)
