"""Linear curves (Mitsuba's ``linearcurve``): tubes along polylines, of varying radius.

A curve is a polyline of control points, each with a radius; each segment is the convex hull
of its two end spheres (a cone tangent to both, and the spheres' outer caps), so that
consecutive segments join smoothly at the spheres they share and a curve ends in a round cap.
This is the geometry of Embree's round linear curves, which Mitsuba's plugin traces; as
there, a curve is only seen from outside: a ray from inside a segment does not hit it, nor a
neighbouring segment of the same curve where that segment holds both the ray's origin and
the hit (Embree cuts its neighbours' cones out of each segment).

Mitsuba's ``to_world`` of a plain curve moves its control points but not its radii, so a
curve model holds its control points already moved (radii as given); instances then place
the model by their affine maps, as for any model (Mitsuba's instances do the same).

A segment's test: the ray's entry into its end sphere (and its first sphere where a curve
starts: elsewhere that is the previous segment's, as Embree attributes it) or into the
frustum of the tangent cone between its tangency circles, whichever comes first, from the ray's point nearest the
segment (so that the quadratics see offsets of the segment's size, not the ray's length).
Surface coordinates and tangents are Mitsuba's: u around the tube from its frame about the
axis (+z its guide), v along all of the model's segments; the normal points from the centre
of the sphere that touches the tube at the hit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from ..accel.bvh import BVHKernel, build_forest
from ..core.backend import (Array2f64, Array3f, Array3f64, Array4f, Bool, Float, Float64, UInt32,
                            device_array, dr)
from ..core.box import outward32
from ..core.error_bounds import gamma
from ..core.errors import SceneError

#: Segments per BVH leaf at most.
CURVE_LEAF_SIZE = 2
#: Leaf entry of a segment without a neighbour on that side.
NO_NEIGHBOUR = 0xFFFFFFFF
#: The largest control point coordinate or radius: the curves' float32 tests square
#: differences of them, which must stay below float32's largest number (3.4e38).
COORDINATE_LIMIT = 1e18


@dataclass(frozen=True, eq=False)
class ControlPointCurves:
    """What the curve types share: ``points`` (K, 3) float64 control points (moved by the
    shape's ``to_world``), ``radii`` (K,), and ``first`` (S,) the first control point of each
    segment, in file order; curves are given as rows of control points (x, y, z, radius),
    each curve's rows consecutive, and a plain shape's ``to_world`` moves the points and
    keeps the radii (Mitsuba's curve plugins). Subclasses make them with a
    ``from_rows(rows, curve, where)`` constructor."""

    points: np.ndarray
    radii: np.ndarray
    first: np.ndarray

    @classmethod
    def from_curves(cls, curves: list[np.ndarray], where: str):
        """The curves of (n_i, 4) arrays of rows (x, y, z, radius); a SceneError naming
        ``where`` for malformed ones."""
        for c, curve in enumerate(curves):
            if np.ndim(curve) != 2 or np.shape(curve)[1] != 4:
                raise SceneError(f"{where}: curve {c}: control points must be rows of x, y, z and "
                                 f"radius, got shape {np.shape(curve)}")
        rows = np.concatenate([np.asarray(c, np.float64) for c in curves]) if curves else np.zeros((0, 4))
        return cls.from_rows(rows, np.repeat(np.arange(len(curves)), [len(c) for c in curves]), where)

    def curve_starts(self) -> np.ndarray:
        """The first control point of each curve."""
        raise NotImplementedError

    def moved(self, to_world: np.ndarray, where: str):
        """The curves with their control points moved by the affine ``to_world`` (4, 4), radii
        kept (Mitsuba's plain curve's ``to_world``); a SceneError naming ``where`` where a
        moved point lies beyond :data:`COORDINATE_LIMIT`."""
        points = self.points @ to_world[:3, :3].T + to_world[:3, 3]
        if not (np.abs(points) <= COORDINATE_LIMIT).all():
            raise SceneError(f"{where}: points_to_world moves a control point beyond {COORDINATE_LIMIT:.0e} "
                             "(the float32 tests square differences of coordinates)")
        return replace(self, points=points)


def checked_rows(rows: np.ndarray, curve: np.ndarray, where: str, least: int, what: str) -> np.ndarray:
    """The segments' first control points of the curves of control points ``rows`` (K, 4), point
    k in curve ``curve[k]`` (non-decreasing from 0, each curve's points consecutive), a
    segment of ``least`` consecutive points starting at every point of a curve but its last
    ``least - 1``; a SceneError naming ``where`` for a curve of fewer points, a point that is
    not finite or beyond :data:`COORDINATE_LIMIT`, or a negative radius (``what`` names the
    curve type in messages)."""
    if not len(rows):
        raise SceneError(f"{where}: no control points (a {what} file needs at least one "
                         f"curve of {least} points)")
    counts = np.bincount(curve)
    if (counts < least).any():
        c = int(np.argmax(counts < least))
        raise SceneError(f"{where}: curve {c} has {counts[c]} control point{'s' if counts[c] > 1 else ''}; "
                         f"a {what} needs at least {least}")
    bad = ~np.isfinite(rows).all(axis=1)
    if bad.any():
        raise SceneError(f"{where}: curve {curve[np.argmax(bad)]} holds a control point that is "
                         "not finite")
    large = (np.abs(rows) > COORDINATE_LIMIT).any(axis=1)
    if large.any():
        k = int(np.argmax(large))
        raise SceneError(f"{where}: curve {curve[k]} holds a control point beyond {COORDINATE_LIMIT:.0e} "
                         f"({rows[k].tolist()}; the float32 tests square differences of coordinates)")
    if (rows[:, 3] < 0).any():
        k = int(np.argmax(rows[:, 3] < 0))
        raise SceneError(f"{where}: curve {curve[k]} has a negative radius ({rows[k, 3]})")
    return np.flatnonzero(curve[:len(curve) - least + 1] == curve[least - 1:])


@dataclass(frozen=True, eq=False)
class LinearCurveData(ControlPointCurves):
    """Linear curves (see :class:`ControlPointCurves`): segment s joins points first[s] and
    first[s] + 1; ``left`` and ``right`` (S,) whether the segment before or after it belongs
    to the same curve."""

    left: np.ndarray
    right: np.ndarray

    @staticmethod
    def from_rows(rows: np.ndarray, curve: np.ndarray, where: str) -> "LinearCurveData":
        """The curves of control points ``rows`` (K, 4), point k in curve ``curve[k]``."""
        starts = checked_rows(rows, curve, where, 2, "linear curve")
        left = np.zeros(len(starts), bool)
        right = np.zeros(len(starts), bool)
        left[1:] = curve[starts[1:]] == curve[starts[:-1]]
        right[:-1] = left[1:]
        return LinearCurveData(rows[:, :3].copy(), rows[:, 3].copy(), starts, left, right)

    def curve_starts(self) -> np.ndarray:
        """The first control point of each curve."""
        return self.first[~self.left]

    @property
    def segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per segment its (p0, r0, p1, r1)."""
        return (self.points[self.first], self.radii[self.first], self.points[self.first + 1],
                self.radii[self.first + 1])


def read_curve_file(path: str | os.PathLike[str], where: str, data: type = LinearCurveData):
    """Mitsuba's curve file: a control point per line (x, y, z, radius), curves separated by
    empty lines, as ``data`` (a :class:`ControlPointCurves` type); a SceneError naming
    ``where`` and the line for a missing or malformed file."""
    name = f"curve file '{os.fspath(path)}'"
    try:
        with open(path, encoding="utf-8") as stream:
            lines = stream.read().splitlines()
    except FileNotFoundError:
        raise SceneError(f"{where}: {name} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{where}: {name} cannot be read ({exc})") from None
    # All numbers at once; a line per point; an empty line ends a curve.
    blank = np.array([not line.strip() for line in lines], bool)
    filled = [line for line, empty in zip(lines, blank) if not empty]
    try:
        values = np.loadtxt(filled, np.float64, ndmin=2) if filled else np.zeros((0, 4))
    except ValueError:
        values = np.zeros((0, 0))
    if values.shape != (len(filled), 4):
        for number, line in enumerate(lines, 1):
            fields = line.split()
            try:
                ok = not fields or len([float(f) for f in fields]) == 4
            except ValueError:
                ok = False
            if not ok:
                raise SceneError(f"{where}: {name} line {number}: expected x, y, z and radius, got "
                                 f"{line.strip()!r}")
    curve = np.cumsum(blank)[~blank]
    return data.from_rows(values, np.unique(curve, return_inverse=True)[1], f"{where} ({name})")


# -- a segment's geometry, in the precision of its arguments ----------------------------------

def _dot(a, b):
    return dr.fma(a.x, b.x, dr.fma(a.y, b.y, a.z * b.z))


def _sphere_entry(q, d, dd, r, t_from):
    """Entry distance (inf if none after ``t_from``) of the ray ``q + t d`` (q relative to
    the centre, ``dd = d . d``) into the sphere of radius r."""
    b = _dot(q, d)
    # The discriminant from the point of closest approach (no cancellation of |q|^2 - r^2).
    closest = q - (b / dd) * d
    disc = dr.fma(-dd, _dot(closest, closest), dd * r * r)
    t = (-b - dr.sqrt(dr.maximum(disc, 0.0))) / dd
    return dr.select((disc >= 0) & (t > t_from), t, dr.inf)


def _cone(p0, r0, p1, r1):
    """Unit axis (+z where the segment has no length), length, slope k = (r1 - r0) / L and
    whether the tangent cone exists (else the hull is the larger sphere)."""
    axis = p1 - p0
    length = dr.norm(axis)
    exists = length > dr.abs(r1 - r0)
    axis = dr.select(length > 0, axis / length, type(axis)(0.0, 0.0, 1.0))
    return axis, length, dr.select(exists, (r1 - r0) / length, 0.0), exists


def _cone_quadratic(q, d, r0, k, axis):
    """``a t^2 + 2 half_b t + c`` whose zeros are where ``q + t d`` (q relative to p0) meets
    the tangent cone (the points at distance (r0 + k z) / sqrt(1 - k^2) from the axis, z
    along it), with z at q and the cone's radius term there."""
    s2 = 1.0 - k * k
    qa, da = _dot(q, axis), _dot(d, axis)
    w0 = dr.fma(k, qa, r0)
    a = dr.fma(_dot(d, d) - da * da, s2, -(k * da) ** 2)
    half_b = dr.fma(_dot(q, d) - qa * da, s2, -w0 * k * da)
    c = dr.fma(_dot(q, q) - qa * qa, s2, -w0 * w0)
    return a, half_b, c, qa, w0


def _inside_frustum(q, r0, r1, axis, length, k, exists):
    """Whether points q (relative to p0) lie inside the tangent cone between its tangency
    circles (axial coordinates -r0 k and L - r1 k)."""
    _, _, c, qa, w0 = _cone_quadratic(q, q, r0, k, axis)
    return exists & (qa >= -r0 * k) & (qa <= dr.fma(-r1, k, length)) & (w0 > 0) & (c < 0)


def _frustum_entry(q, d, r0, r1, axis, length, k, exists, t_from):
    """Entry distance (inf if none after ``t_from``) of ``q + t d`` (q relative to p0)
    through the lateral surface of the tangent cone between its tangency circles, and which
    root it is (0 / 1)."""
    a, half_b, c, _, _ = _cone_quadratic(q, d, r0, k, axis)
    disc = dr.fma(half_b, half_b, -a * c)
    root = dr.sqrt(dr.maximum(disc, 0.0))
    s2, da = 1.0 - k * k, _dot(d, axis)
    z_lo, z_hi = -r0 * k, dr.fma(-r1, k, length)
    best, which = type(q.x)(dr.inf), UInt32(0)
    for index, sign in enumerate((-1.0, 1.0)):
        t = (-half_b + sign * root) / a
        x = dr.fma(d, t, q)
        z = _dot(x, axis)
        w = dr.fma(k, z, r0)
        # Entering: the gradient of the cone's implicit function points against d.
        grad_d = (_dot(x, d) - z * da) * s2 - w * k * da
        ok = (exists & (disc >= 0) & (w >= 0) & (z >= z_lo) & (z <= z_hi) & (grad_d < 0)
              & (t > t_from) & (t < best))
        best, which = dr.select(ok, t, best), dr.select(ok, UInt32(index), which)
    return best, which


def _inside_hull(x, p0, r0, p1, r1):
    """Whether points ``x`` lie inside the segment's hull (its spheres and the frustum)."""
    axis, length, k, exists = _cone(p0, r0, p1, r1)
    return ((_dot(x - p0, x - p0) < r0 * r0) | (_dot(x - p1, x - p1) < r1 * r1)
            | _inside_frustum(x - p0, r0, r1, axis, length, k, exists))


def segment_entry(o, d, p0, r0, p1, r1, first_sphere):
    """The ray's entry distance into the segment's hull (inf where it misses; see
    :meth:`LinearCurveLibrary._entry` for rays that start inside) and which part it enters by (0: the sphere at p0, 1: at p1, 2 / 3: the cone by
    its first / second root). The sphere at p0 counts where ``first_sphere`` (a curve's
    start): elsewhere it is the previous segment's (Embree's segments end in their sphere)."""
    axis, length, k, exists = _cone(p0, r0, p1, r1)
    dd = _dot(d, d)
    # From the ray's point nearest p0: offsets of the segment's size in the quadratics.
    t_c = _dot(p0 - o, d) / dd
    near = dr.fma(d, t_c, o)
    t0 = dr.select(first_sphere, _sphere_entry(near - p0, d, dd, r0, -t_c), dr.inf)
    t1 = _sphere_entry(near - p1, d, dd, r1, -t_c)
    tf, root = _frustum_entry(near - p0, d, r0, r1, axis, length, k, exists, -t_c)
    part = dr.select(t1 < t0, UInt32(1), UInt32(0))
    t = dr.minimum(t0, t1)
    part = dr.select(tf < t, 2 + root, part)
    t = dr.minimum(t, tf) + t_c
    return t, part


class LinearCurveLibrary:
    """The scene's linear curve models, their segments in one BVH forest.

    Per leaf (a segment, in leaf order): (p0, r0) and (p1, r1) as two float4 packets, its
    index among its model's segments (Mitsuba's primitive index) and its model's segment
    count (for v), the leaf entries of its neighbours in the same curve, and the box of it
    and its neighbours (where a ray must start for the tests of rays from inside a tube).
    """

    def __init__(self, curves: list[LinearCurveData]):
        lo_parts, hi_parts, sizes, packets, index, count, left, right, reach = [], [], [], [], [], [], [], [], []
        #: Per model, the object-space box of its segments.
        self.object_bounds: list[tuple[np.ndarray, np.ndarray]] = []
        offset = 0
        for curve in curves:
            p0, r0, p1, r1 = curve.segments
            lo = np.minimum(p0 - r0[:, None], p1 - r1[:, None])
            hi = np.maximum(p0 + r0[:, None], p1 + r1[:, None])
            lo_parts.append(lo)
            hi_parts.append(hi)
            # The box of the segment and its neighbours in the same curve: where a ray must
            # start for the tests of rays from inside a tube to matter.
            reach_lo, reach_hi = lo.copy(), hi.copy()
            for shift, same in ((1, curve.left), (-1, curve.right)):
                reach_lo[same] = np.minimum(reach_lo[same], np.roll(lo, shift, axis=0)[same])
                reach_hi[same] = np.maximum(reach_hi[same], np.roll(hi, shift, axis=0)[same])
            reach.append(np.stack([reach_lo, reach_hi], axis=1))
            self.object_bounds.append((lo.min(axis=0), hi.max(axis=0)))
            n = len(p0)
            sizes.append(n)
            packets.append(np.concatenate([p0, r0[:, None], p1, r1[:, None]], axis=1))
            index.append(np.arange(n))
            count.append(np.full(n, n))
            # Neighbours as positions in the concatenated file order, mapped to leaves below.
            left.append(np.where(curve.left, offset + np.arange(n) - 1, -1))
            right.append(np.where(curve.right, offset + np.arange(n) + 1, -1))
            offset += n
        trees, self.root_refs = build_forest(np.concatenate(lo_parts), np.concatenate(hi_parts), sizes,
                                             CURVE_LEAF_SIZE)
        order = trees.order
        leaf_of = np.empty(len(order), np.int64)
        leaf_of[order] = np.arange(len(order))
        self.kernel = BVHKernel(trees, frontier=0, nested=True)
        self.packets = device_array(Float, np.concatenate(packets)[order].astype(np.float32).ravel())
        self.prim = device_array(UInt32, np.concatenate(index)[order].astype(np.uint32))
        reach = np.concatenate(reach)[order]
        self.reach = device_array(Float, np.stack(outward32(reach[:, 0], reach[:, 1]), axis=1).ravel())
        self.segment_count = device_array(Float64, np.concatenate(count)[order].astype(np.float64))
        neighbours = [np.concatenate(side)[order] for side in (left, right)]
        self.neighbours = [device_array(UInt32, np.where(side >= 0, leaf_of[np.maximum(side, 0)],
                                                         NO_NEIGHBOUR).astype(np.uint32))
                           for side in neighbours]
        #: Curves shade by their geometric normal.
        self.smooth = [False] * len(curves)

    def _segment(self, position: UInt32, vector=Array3f):
        """(p0, r0, p1, r1) of the segment at leaf ``position``, as ``vector`` and its scalar."""
        a = dr.gather(Array4f, self.packets, 2 * position)
        b = dr.gather(Array4f, self.packets, 2 * position + 1)
        scalar = type(vector().x)
        return (vector(a.x, a.y, a.z), scalar(a.w), vector(b.x, b.y, b.z), scalar(b.w))

    def _entry(self, o, d, position: UInt32):
        """:func:`segment_entry` against the segment at ``position``: no hit where the origin
        lies inside the segment's hull, nor where a neighbour of the same curve holds both
        the origin and the hit (Embree's cut). Those tests run in a branch that a SIMD
        packet takes only where one of its rays starts within the box of the segment and
        its neighbours."""
        vector = type(o)
        segment = self._segment(position, vector)
        starts = dr.gather(UInt32, self.neighbours[0], position) == NO_NEIGHBOUR
        t, part = segment_entry(o, d, *segment, starts)
        lo = vector(dr.gather(Array3f, self.reach, 2 * position))
        hi = vector(dr.gather(Array3f, self.reach, 2 * position + 1))
        near = dr.isfinite(t) & dr.all((o >= lo) & (o <= hi))

        def seen_from_inside(t, o, d, position):
            inside = _inside_hull(o, *self._segment(position, vector))
            hit = dr.fma(d, dr.select(dr.isfinite(t), t, 0.0), o)
            for side in self.neighbours:
                other = dr.gather(UInt32, side, position)
                exists = other != NO_NEIGHBOUR
                neighbour = self._segment(dr.select(exists, other, position), vector)
                inside |= exists & _inside_hull(o, *neighbour) & _inside_hull(hit, *neighbour)
            return dr.select(inside, dr.inf, t)

        t = dr.if_stmt((t, o, d, position), near, seen_from_inside, lambda t, o, d, position: t)
        return t, part

    def intersect(self, o: Array3f, d: Array3f, t_max: Float, active: Bool,
                  root_ref: UInt32, any_hit: bool = False) -> tuple[Float, UInt32]:
        """Nearest segment hit of object-space rays through the model whose root is
        ``root_ref``: ``(t, position)`` with t = inf where nothing is hit in (0, t_max);
        ``position`` is the leaf-order segment. With ``any_hit``, the walk stops at the
        first segment hit."""
        def distance(position, t_best):
            t = self._entry(o, d, position)[0]
            return dr.select((t > 0) & (t < t_best), t, dr.inf)

        return self.kernel.nearest(o, d, t_max, active, root_ref, any_hit, distance)

    def surface_point(self, o, d, position: UInt32, t_first, uv: bool, tangents: bool):
        """Differentiable float64 (t, object-space point, normal (not normalized), the point's
        error bound, uv, dp/du, dp/dv) of the rays' hits on the segment at ``position`` (uv
        and the tangents 0 unless asked for); where the second test misses (a grazing ray),
        t is inf and the point lies at ``t_first``."""
        p0, r0, p1, r1 = self._segment(position, Array3f64)
        with dr.suspend_grad():
            t_detached, part = self._entry(dr.detach(o), dr.detach(d), position)
        # The part's entry again with derivatives (the same formulas, on the attached ray).
        axis, length, k, _ = _cone(p0, r0, p1, r1)
        dd = _dot(d, d)
        t_c = _dot(p0 - o, d) / dd
        near = dr.fma(d, t_c, o)
        t_att = dr.select(part == 1, _sphere_entry(near - p1, d, dd, r1, -dr.inf),
                          _sphere_entry(near - p0, d, dd, r0, -dr.inf))
        a, half_b, c, _, _ = _cone_quadratic(near - p0, d, r0, k, axis)
        root = dr.sqrt(dr.maximum(dr.fma(half_b, half_b, -a * c), 0.0))
        t_att = dr.select(part >= 2, (-half_b + dr.select(part == 3, root, -root)) / a, t_att) + t_c
        found = dr.isfinite(t_detached)
        t = dr.select(found, t_att, Float64(t_first))
        p = dr.fma(d, t, o)
        # The centre of the sphere touching the tube at p: an end's, or on the cone the one
        # whose tangency circle holds p.
        s = (_dot(p - p0, axis) + r0 * k) / (1.0 - k * k)
        v_local = dr.select(part == 0, 0.0, dr.select(part == 1, 1.0, dr.clip(s / length, 0.0, 1.0)))
        centre = dr.fma(p1 - p0, v_local, p0)
        n = p - centre
        unit = dr.normalize(n)
        uv_out, dpdu, dpdv = Array2f64(0.0), Array3f64(0.0), Array3f64(0.0)
        segments = dr.gather(Float64, self.segment_count, position)
        if uv or tangents:
            rot, rad = local_frame(axis)
            u = dr.atan2(_dot(rot, unit), _dot(rad, unit))
            u = dr.select(u < 0, u + 2.0 * dr.pi, u) / (2.0 * dr.pi)
            prim = Float64(dr.gather(UInt32, self.prim, position))
            uv_out = Array2f64(u, (v_local + prim) / segments)
        if tangents:
            dpdu = 2.0 * dr.pi * dr.cross(axis, n)
            dpdv = segments * dr.fma(unit, r1 - r0, p1 - p0)
        # The float32 tests run from the ray's point nearest the segment: their rounding
        # scales with |p| and the tube's radius there.
        error = gamma(32) * (dr.abs(p) + dr.norm(n))
        return dr.select(found, t, dr.inf), p, n, error, uv_out, dpdu, dpdv

    def prim_index(self, position: UInt32) -> UInt32:
        """The segment's index among its model's segments, in file order."""
        return dr.gather(UInt32, self.prim, position)


def local_frame(axis):
    """Mitsuba's frame about a segment's axis: ``rot`` the +z guide made orthogonal to the
    axis (+y where the axis is along z), ``rad = rot x axis``."""
    guide = type(axis)(0.0, 0.0, 1.0)
    rot = dr.normalize(guide - axis * _dot(axis, guide))
    rot = dr.select(dr.abs(_dot(guide, axis)) == 1.0, type(axis)(0.0, 1.0, 0.0), rot)
    return rot, dr.cross(rot, axis)
