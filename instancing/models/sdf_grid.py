"""Signed distance grids (Mitsuba's ``sdfgrid``): a surface given by values on a grid.

A grid of nx x ny x nz values spans the unit cube [0, 1]^3 of object space, value (i, j, k)
at the corner (i / (nx - 1), j / (ny - 1), k / (nz - 1)); the surface is the zero set of the
values' trilinear interpolant (Hansson-Soederlund, Evans and Akenine-Moeller, "Ray Tracing of
Signed Distance Function Grids", JCGT 11(3), 2022). Only voxels whose corners do not all
share one sign can hold it; each is a BVH leaf, bounded by the box of its edges' crossings
(tight: on a face the interpolant is bilinear, and along x over a y-z cell its zero moves
monotonically in y and z, so its extremes lie on the voxel's edges). As for the other
models, instances place a grid with their affine ``to_world``.

A ray through a voxel sees the interpolant as a cubic in t. Its first root is bracketed
between the roots of its derivative and refined by Newton steps that fall back to
bisection (phase 1 in float32; phase 2 in float64, with a last Newton step that carries
derivatives by the implicit function theorem). Normals are Mitsuba's: the geometric one is
the gradient of the interpolant in the voxel holding the point, the shading one either that
(``analytic``) or its smooth blend over the eight voxels around the nearest grid corner
(``smooth``, Mitsuba's default, after the paper above). A grid has no surface
coordinates and cannot emit light (as in Mitsuba).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..accel.bvh import BVHKernel, build_forest
from ..core.backend import (Array3f, Array3f64, Array4f, Bool, Float, Float64, Int32, UInt32, device_array,
                            dr)
from ..core.box import slab_span
from ..core.error_bounds import gamma
from ..core.errors import SceneError
from ..core.memory import require_memory

#: Voxels per BVH leaf at most (a voxel's test costs several triangle tests).
GRID_LEAF_SIZE = 2
#: Newton-or-bisection steps of the root's refinement: phase 1 (float32), phase 2 (float64).
STEPS_32, STEPS_64 = 10, 30
#: Bound on the distance between a phase-2 hit point and the surface a float32 test sees
#: there, relative to (|p| + 1) componentwise in object space: the offset of spawned rays.
POINT_ERROR = gamma(32)
#: The tight boxes are widened by this fraction of a voxel, so that a flat one (a surface
#: in a grid plane) is not lost to the slab test's rounding.
BOX_PAD = 1e-4
#: How shading normals are made, by Mitsuba's ``normals`` name.
NORMAL_MODES = ("smooth", "analytic")


@dataclass(frozen=True, eq=False)
class SDFGridData:
    """One grid: ``values`` (nz, ny, nx) float32 (x fastest, as Mitsuba's volume files),
    and whether its shading normals are ``smooth`` (else ``analytic``)."""

    values: np.ndarray
    smooth: bool = True

    @staticmethod
    def checked(values: np.ndarray, smooth: bool, where: str) -> "SDFGridData":
        """The grid of ``values``, or a SceneError naming ``where``: at least 2 values per
        axis, all finite, and some voxel holding a surface."""
        values = np.asarray(values)
        # The values and, per voxel holding surface, its corners, box and leaf entries.
        require_memory(20.0 * values.size, f"{where}: an SDF grid of {values.size} values")
        values = values.astype(np.float32)
        if values.ndim != 3 or min(values.shape) < 2:
            raise SceneError(f"{where}: an SDF grid needs at least 2 x 2 x 2 values, got shape "
                             f"{values.shape[::-1]} (x, y, z)")
        if not np.isfinite(values).all():
            raise SceneError(f"{where}: {int((~np.isfinite(values)).sum())} of the grid's values "
                             "are not finite")
        grid = SDFGridData(np.ascontiguousarray(values), smooth)
        if not grid.occupied().any():
            raise SceneError(f"{where}: no voxel of the grid holds a surface (none has corner "
                             "values of both signs, or a zero among nonzero ones)")
        return grid

    @property
    def resolution(self) -> np.ndarray:
        """Voxels per axis (x, y, z): the values per axis less one."""
        return np.array(self.values.shape[::-1]) - 1

    def _corner_views(self):
        """Per voxel corner c (offset (c & 1, c >> 1 & 1, c >> 2 & 1)), the values at that
        corner of every voxel, (vz, vy, vx) views."""
        v = self.values
        return [v[(c >> 2) & 1:v.shape[0] - 1 + ((c >> 2) & 1), (c >> 1) & 1:v.shape[1] - 1 + ((c >> 1) & 1),
                  c & 1:v.shape[2] - 1 + (c & 1)] for c in range(8)]

    def occupied(self) -> np.ndarray:
        """(vz, vy, vx) whether each voxel can hold the surface: Mitsuba's test (not all
        eight corners positive, nor all negative), and not all eight zero (the interpolant
        then vanishes in the whole voxel, which has no surface nor normal)."""
        views = self._corner_views()
        low, high = np.minimum.reduce(views), np.maximum.reduce(views)
        return ~((low > 0) | (high < 0) | ((low == 0) & (high == 0)))

    def corners(self, voxel: np.ndarray) -> np.ndarray:
        """The eight corner values (K, 8) of the voxels at integer positions ``voxel`` (K, 3)
        (x, y, z), corner c at offset (c & 1, c >> 1 & 1, c >> 2 & 1)."""
        x, y, z = voxel.T
        return np.stack([self.values[z + ((c >> 2) & 1), y + ((c >> 1) & 1), x + (c & 1)]
                         for c in range(8)], axis=1)


def tight_boxes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) voxel-local boxes (in [0, 1]^3) of the zero set in K voxels of corner values
    (K, 8): the box of the zero corners and of the edges' crossings."""
    offset = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.float64)
    lo = np.full((len(corners), 3), np.inf)
    hi = np.full((len(corners), 3), -np.inf)
    s = corners.astype(np.float64)
    for a in range(8):
        zero = s[:, a] == 0
        lo = np.where(zero[:, None], np.minimum(lo, offset[a]), lo)
        hi = np.where(zero[:, None], np.maximum(hi, offset[a]), hi)
        for axis in range(3):
            if a & (1 << axis):
                continue
            b = a | (1 << axis)
            crossing = (s[:, a] * s[:, b] <= 0) & (s[:, a] != s[:, b])
            w = np.where(crossing, s[:, a] / np.where(crossing, s[:, a] - s[:, b], 1.0), 0.0)
            point = offset[a] + w[:, None] * (offset[b] - offset[a])
            lo = np.where(crossing[:, None], np.minimum(lo, point), lo)
            hi = np.where(crossing[:, None], np.maximum(hi, point), hi)
    return lo, hi


def _cubic(corners: tuple, q, e):
    """Coefficients (c0, c1, c2, c3) of the trilinear interpolant of the eight ``corners``
    along ``q + s e`` (voxel-local coordinates), in the precision of ``q``."""
    s000, s100, s010, s110, s001, s101, s011, s111 = corners
    a1, a2, a3 = s100 - s000, s010 - s000, s001 - s000
    a4 = s110 - s100 - s010 + s000
    a5 = s011 - s010 - s001 + s000
    a6 = s101 - s100 - s001 + s000
    a7 = s111 - s110 - s101 - s011 + s100 + s010 + s001 - s000
    qx, qy, qz = q
    ex, ey, ez = e
    c0 = s000 + a1 * qx + a2 * qy + a3 * qz + a4 * qx * qy + a5 * qy * qz + a6 * qx * qz \
        + a7 * qx * qy * qz
    c1 = (a1 * ex + a2 * ey + a3 * ez + a4 * (qx * ey + qy * ex) + a5 * (qy * ez + qz * ey)
          + a6 * (qx * ez + qz * ex) + a7 * (qx * qy * ez + qx * qz * ey + qy * qz * ex))
    c2 = a4 * ex * ey + a5 * ey * ez + a6 * ex * ez + a7 * (qx * ey * ez + qy * ex * ez + qz * ex * ey)
    c3 = a7 * ex * ey * ez
    return c0, c1, c2, c3


def _poly(c, s):
    """The cubic ``c`` and its derivative at ``s``."""
    c0, c1, c2, c3 = c
    return dr.fma(dr.fma(dr.fma(c3, s, c2), s, c1), s, c0), dr.fma(dr.fma(3.0 * c3, s, 2.0 * c2), s, c1)


def first_root(c, s_max, steps: int):
    """The first root of the cubic ``c`` in [0, s_max] and whether there is one (else the
    root is inf). The cubic is monotone between its derivative's roots: the first of those
    pieces whose ends differ in sign (or hold a zero) brackets the root, which Newton
    steps refine, each replaced by the bracket's midpoint where it leaves the bracket."""
    scalar = type(s_max)
    c0, c1, c2, c3 = c
    # The derivative's roots, by the cancellation-free quadratic formula; a root that is
    # not finite (a quadratic or linear derivative) falls outside [0, s_max] below.
    qa, qb, qc = 3.0 * c3, 2.0 * c2, c1
    disc = dr.fma(qb, qb, -4.0 * qa * qc)
    real = disc > 0
    q = -0.5 * (qb + dr.copysign(dr.sqrt(dr.maximum(disc, 0.0)), qb))
    r1, r2 = q / qa, qc / q
    r1 = dr.select(real & dr.isfinite(r1), r1, -1.0)
    r2 = dr.select(real & dr.isfinite(r2), r2, -1.0)
    m1 = dr.clip(dr.minimum(r1, r2), 0.0, s_max)
    m2 = dr.clip(dr.maximum(r1, r2), 0.0, s_max)
    points = (scalar(0.0), m1, m2, s_max)
    values = [_poly(c, p)[0] for p in points]
    found = Bool(False)
    a, b = scalar(0.0), scalar(0.0)
    fa, fb = scalar(0.0), scalar(0.0)
    for k in range(3):
        here = ~found & (values[k] * values[k + 1] <= 0)
        a, b = dr.select(here, points[k], a), dr.select(here, points[k + 1], b)
        fa, fb = dr.select(here, values[k], fa), dr.select(here, values[k + 1], fb)
        found |= here
    # The regula falsi point to start from (an end that is a root stays put).
    x = dr.select(fa == fb, a, a - fa * (b - a) / (fb - fa))
    x = dr.select(fa == 0, a, x)
    for _ in range(steps):
        f, df = _poly(c, x)
        below = (f * fa) > 0
        a, fa = dr.select(below, x, a), dr.select(below, f, fa)
        b = dr.select(below, b, x)
        newton = x - f / df
        x = dr.select((newton > a) & (newton < b), newton, 0.5 * (a + b))
        x = dr.select(f == 0, dr.select(below, a, b), x)
    return dr.select(found, x, scalar(dr.inf)), found


class SDFGridLibrary:
    """The scene's SDF grid models, their voxels in one BVH forest for a shared kernel.

    Args:
        grids: the grids, in the order the scene numbers them.

    Per leaf (a voxel holding surface, in leaf order): its eight corner values (two float4
    packets), its integer position (x, y, z) as floats, its grid, and its rank among its
    grid's such voxels in scan order (x fastest: Mitsuba's primitive index). Per grid: its
    resolution (voxels per axis), the offset of its values in the flat value array, and its
    value counts per axis.
    """

    def __init__(self, grids: list[SDFGridData]):
        lo_parts, hi_parts, sizes, leaves = [], [], [], []
        #: Per grid, the object-space box of its voxels' tight boxes.
        self.object_bounds: list[tuple[np.ndarray, np.ndarray]] = []
        for g, grid in enumerate(grids):
            filled = np.flatnonzero(grid.occupied().ravel())
            rx, ry, _ = grid.resolution
            voxel = np.stack([filled % rx, (filled // rx) % ry, filled // (rx * ry)], axis=1)
            corners = grid.corners(voxel)
            local_lo, local_hi = tight_boxes(corners)
            h = 1.0 / grid.resolution
            lo = (voxel + np.maximum(local_lo - BOX_PAD, 0.0)) * h
            hi = (voxel + np.minimum(local_hi + BOX_PAD, 1.0)) * h
            lo_parts.append(lo)
            hi_parts.append(hi)
            sizes.append(len(filled))
            leaves.append((corners, voxel, np.full(len(filled), g), np.arange(len(filled))))
            self.object_bounds.append((lo.min(axis=0), hi.max(axis=0)))
        trees, self.root_refs = build_forest(np.concatenate(lo_parts), np.concatenate(hi_parts), sizes,
                                             GRID_LEAF_SIZE)
        corners, voxel, grid_of, rank = (np.concatenate(part)[trees.order] for part in zip(*leaves))
        self.kernel = BVHKernel(trees, frontier=0, nested=True)
        self.corner_values = device_array(Float, corners.astype(np.float32).ravel())
        self.voxel = device_array(Float, voxel.astype(np.float32).ravel())
        self.grid_of = device_array(UInt32, grid_of.astype(np.uint32))
        self.rank = device_array(UInt32, rank.astype(np.uint32))
        resolution = np.array([g.resolution for g in grids], np.float64)
        self.resolution = device_array(Float, resolution.astype(np.float32).ravel())
        counts = np.array([g.values.shape[::-1] for g in grids], np.int64)
        offsets = np.cumsum([0] + [g.values.size for g in grids])[:-1]
        self.value_offset = device_array(UInt32, offsets.astype(np.uint32))
        self.value_count = device_array(Int32, counts.astype(np.int32).ravel())
        self.values = device_array(Float, np.concatenate([g.values.ravel() for g in grids]))
        #: Per grid, whether its shading normals are smooth.
        self.smooth = [g.smooth for g in grids]
        self.smooth_grids = device_array(UInt32, np.array(self.smooth, np.uint32))

    # -- phase 1 ----------------------------------------------------------------------------

    def intersect(self, o: Array3f, d: Array3f, t_max: Float, active: Bool,
                  root_ref: UInt32, any_hit: bool = False) -> tuple[Float, UInt32]:
        """Nearest surface hit of object-space rays through the grid whose root is
        ``root_ref``: ``(t, position)`` with t = inf where nothing is hit in (0, t_max);
        ``position`` is the leaf-order voxel. With ``any_hit``, the walk stops at the
        first voxel hit."""
        return self.kernel.nearest(
            o, d, t_max, active, root_ref, any_hit,
            lambda position, t_best: self._voxel_hit(o, d, position, t_best, Float, STEPS_32)[0])

    def _voxel_hit(self, o, d, position: UInt32, t_max, scalar, steps: int):
        """(t, t at the voxel's entry) of the rays against the voxel at ``position``, in
        the precision ``scalar`` of ``o``."""
        vector = type(o)
        grid = dr.gather(UInt32, self.grid_of, position)
        resolution = vector(dr.gather(Array3f, self.resolution, grid))
        voxel = vector(dr.gather(Array3f, self.voxel, position))
        low = dr.gather(Array4f, self.corner_values, 2 * position)
        high = dr.gather(Array4f, self.corner_values, 2 * position + 1)
        corners = tuple(scalar(v) for v in (*low, *high))
        # The ray in voxel-local coordinates, from where it enters the voxel.
        u = dr.fma(o, resolution, -voxel)
        e = d * resolution
        t_in, t_out = slab_span(vector(0.0), vector(1.0), u, dr.rcp(e))
        t_out = dr.minimum(t_out, t_max)
        q = dr.clip(dr.fma(e, t_in, u), 0.0, 1.0)
        cubic = _cubic(corners, q, e)
        s, found = first_root(cubic, dr.maximum(t_out - t_in, 0.0), steps)
        t = t_in + s
        hit = found & (t_in <= t_out) & (t > 0) & (t < t_max)
        return dr.select(hit, t, scalar(dr.inf)), t_in

    # -- phase 2 ----------------------------------------------------------------------------

    def surface_point(self, o, d, position: UInt32, t_first):
        """Differentiable float64 (t, object-space point, geometric normal, shading normal)
        of the rays' hits in the voxel at ``position`` (normals not normalized); where the
        second test misses (a grazing ray), t is inf and the point lies at ``t_first``."""
        with dr.suspend_grad():
            t, t_in = self._voxel_hit(dr.detach(o), dr.detach(d), position, Float64(dr.inf),
                                            Float64, STEPS_64)
        # One Newton step on the attached cubic: its derivatives are the implicit root's.
        resolution = Array3f64(dr.gather(Array3f, self.resolution, dr.gather(UInt32, self.grid_of, position)))
        voxel = Array3f64(dr.gather(Array3f, self.voxel, position))
        u = dr.fma(o, resolution, -voxel)
        e = d * resolution
        low = dr.gather(Array4f, self.corner_values, 2 * position)
        high = dr.gather(Array4f, self.corner_values, 2 * position + 1)
        corners = tuple(Float64(v) for v in (*low, *high))
        t_at = dr.select(dr.isfinite(t), t, Float64(t_first))
        s = dr.detach(t_at - t_in)
        cubic = _cubic(corners, dr.fma(e, Float64(dr.detach(t_in)), u), e)
        f, df = _poly(cubic, s)
        step = dr.select(dr.isfinite(t) & (df != 0), f / df, 0.0)
        t_hit = t_in + s - (step - dr.detach(step))
        p = dr.fma(d, t_hit, o)
        n = self.gradient(p, position)
        sn = self.smooth_normal(p, position) if any(self.smooth) else n
        if any(self.smooth) and not all(self.smooth):
            smooth = dr.gather(UInt32, self.smooth_grids, dr.gather(UInt32, self.grid_of, position)) != 0
            sn = dr.select(smooth, sn, n)
        return dr.select(dr.isfinite(t), t_hit, dr.inf), p, n, sn

    def point_error(self, p) -> Array3f:
        """Componentwise bound on a hit point's distance from the surface a float32 test
        sees (:data:`POINT_ERROR`)."""
        return Array3f(POINT_ERROR * (dr.abs(p) + 1.0))

    def prim_index(self, position: UInt32) -> UInt32:
        """The voxel's rank among its grid's voxels that hold surface, in scan order."""
        return dr.gather(UInt32, self.rank, position)

    # -- the interpolant and its normals ----------------------------------------------------

    def _grid_counts(self, grid: UInt32) -> tuple[Int32, Int32, Int32]:
        """The grid's value counts per axis (x, y, z)."""
        return tuple(dr.gather(Int32, self.value_count, 3 * grid + k) for k in range(3))

    def _value(self, grid: UInt32, counts: tuple, corner: tuple) -> Float64:
        """The grid's value at the integer corner (x, y, z), clamped into the grid."""
        nx, ny, nz = counts
        x, y, z = (dr.clip(c, 0, n - 1) for c, n in zip(corner, counts))
        offset = dr.gather(UInt32, self.value_offset, grid)
        return Float64(dr.gather(Float, self.values, offset + UInt32((z * ny + y) * nx + x)))

    def _cell(self, p, position: UInt32):
        """(grid, value counts, voxels per axis, the point in voxel units) of object-space
        points in the grid of the voxel at ``position``."""
        grid = dr.gather(UInt32, self.grid_of, position)
        resolution = Array3f64(dr.gather(Array3f, self.resolution, grid))
        return grid, self._grid_counts(grid), resolution, p * resolution

    def gradient(self, p, position: UInt32):
        """The interpolant's object-space gradient at ``p`` in the voxel holding it (clamped
        into the grid): Mitsuba's geometric normal, not normalized."""
        grid, counts, resolution, scaled = self._cell(p, position)
        voxel = [dr.clip(Int32(dr.floor(scaled[k])), 0, counts[k] - 2) for k in range(3)]
        w = [scaled[k] - Float64(voxel[k]) for k in range(3)]
        s = {(i, j, k): self._value(grid, counts, (voxel[0] + i, voxel[1] + j, voxel[2] + k))
             for i in (0, 1) for j in (0, 1) for k in (0, 1)}
        out = []
        for axis in range(3):
            a, b = [k for k in range(3) if k != axis]
            total = Float64(0.0)
            for ia in (0, 1):
                for ib in (0, 1):
                    weight = (w[a] if ia else 1.0 - w[a]) * (w[b] if ib else 1.0 - w[b])
                    lo, hi = [0, 0, 0], [0, 0, 0]
                    lo[a] = hi[a] = ia
                    lo[b] = hi[b] = ib
                    hi[axis] = 1
                    total += weight * (s[tuple(hi)] - s[tuple(lo)])
            out.append(total * resolution[axis])
        return Array3f64(*out)

    def smooth_normal(self, p, position: UInt32):
        """Mitsuba's smooth shading normal at ``p`` (object space, not normalized): the
        unit gradients of the eight voxels around the nearest grid corner, each the
        differences of the interpolant across its voxel's slabs at p, blended trilinearly
        (a voxel with a negative index left out, as its axis's weight)."""
        grid, counts, resolution, scaled = self._cell(p, position)
        nearest = [Int32(dr.round(scaled[k])) for k in range(3)]
        # The interpolant on grid plane i of each axis, at p's other two coordinates.
        cell = [dr.clip(Int32(dr.floor(scaled[k])), 0, counts[k] - 2) for k in range(3)]
        w = [scaled[k] - Float64(cell[k]) for k in range(3)]

        def on_plane(axis: int, plane: Int32) -> Float64:
            a, b = [k for k in range(3) if k != axis]
            total = Float64(0.0)
            for ia in (0, 1):
                for ib in (0, 1):
                    corner = [None, None, None]
                    corner[axis], corner[a], corner[b] = plane, cell[a] + ia, cell[b] + ib
                    weight = (w[a] if ia else 1.0 - w[a]) * (w[b] if ib else 1.0 - w[b])
                    total += weight * self._value(grid, counts, tuple(corner))
            return total

        # Per axis, the gradient component of the voxels at offsets 0 and 1 below the corner.
        planes = [[on_plane(k, nearest[k] + j) for j in (-1, 0, 1)] for k in range(3)]
        component = [[(planes[k][j + 1] - planes[k][j]) * resolution[k] for j in (0, 1)] for k in range(3)]
        valid = [[nearest[k] - 1 + j >= 0 for j in (0, 1)] for k in range(3)]
        weight = [scaled[k] - Float64(nearest[k]) + 0.5 for k in range(3)]
        # An axis whose voxels on one side are all left out weighs the other side alone.
        for k in range(3):
            weight[k] = dr.select(~valid[k][0], 1.0, weight[k])
            weight[k] = dr.select(~valid[k][1], 0.0, weight[k])
        n = Array3f64(0.0)
        for i in (0, 1):
            for j in (0, 1):
                for k in (0, 1):
                    g = Array3f64(component[0][i], component[1][j], component[2][k])
                    unit = dr.select(valid[0][i] & valid[1][j] & valid[2][k], dr.normalize(g), 0.0)
                    n += ((weight[0] if i else 1.0 - weight[0]) * (weight[1] if j else 1.0 - weight[1])
                          * (weight[2] if k else 1.0 - weight[2])) * unit
        return n
