"""The environment: light arriving from infinitely far away, Mitsuba's ``constant`` (the
same radiance from every direction) or ``envmap`` (a latitude-longitude image).

An environment map is looked up as Mitsuba's ``envmap`` plugin looks it up. A world
direction d is taken into the map's frame by the inverse of its ``to_world`` rotation, then
``u = atan2(d.x, -d.z) / 2 pi`` (wrapped into [0, 1)) and ``v = acos(d.y) / pi`` (+y is
up); the radiance is the image interpolated bilinearly with texel centres at
``(i + 1/2) / width`` across u (periodic) and rows at ``j / (height - 1)`` down v (the first
and last rows on the poles), times ``scale``.

Importance sampling (next-event estimation towards the environment), as Mitsuba's: between
the grid points of that interpolation the radiance is bilinear in four texels, so the
sphere is cut into width x (height - 1) cells in (u, v), and the density in (u, v) is the
bilinear interpolant of ``g = luminance * sin(theta)`` at the grid points (sin(theta) the
Jacobian of the sphere): a cell is picked with probability proportional to the mean of its
four corner values, a point in it by Mitsuba's ``square_to_bilinear``. The solid-angle
density is ``p_uv / (2 pi^2 sin(theta))``. Where all four corners are 0 (black texels, or
a cell at a pole whose other row is black) no sample lands: the BSDF's samples find that
light, weighted by MIS. A constant environment is not sampled: the BSDF's own samples find
it (:mod:`instancing.rendering.integrators.direct`), except where there are none (uniformly
over the sphere then).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.backend import (Array3f, Float, Int32, TensorXf, UInt32, device_array, device_vectors, dr,
                            mitsuba_module)
from ..core.warp import square_to_uniform_sphere
from ..materials.texture import LUMINANCE
from .description import ConstantLight, EnvironmentMap


class Environment:
    """The scene's environment as kernels read it (module docstring)."""

    def __init__(self, light: ConstantLight | EnvironmentMap):
        self.constant = None
        self.sampled = False
        if isinstance(light, ConstantLight):
            # Opaque: a recoloured environment reuses the compiled kernels.
            self.constant = dr.opaque(Array3f, light.radiance)
            return
        texels = np.asarray(light.texels, np.float64) * light.scale
        self.height, self.width = texels.shape[:2]
        self.texels = device_vectors(texels.reshape(-1, 3).astype(np.float32))
        rotation = np.asarray(light.to_world, np.float64)[:3, :3]
        self.to_world = [dr.opaque(Float, float(c)) for c in rotation.ravel()]
        self.from_world = [dr.opaque(Float, float(c)) for c in rotation.T.ravel()]
        # The density's values at the grid points, and each cell's mean of its four (the
        # next column wrapping around).
        theta = np.pi * np.arange(self.height) / (self.height - 1)
        corner = (texels @ np.array(LUMINANCE)) * np.sin(theta)[:, None]
        rows = corner[:-1] + corner[1:]
        weights = (0.25 * (rows + np.roll(rows, -1, axis=1))).ravel()
        total = weights.sum()
        if not total > 0:
            return  # black: nothing to sample
        self.sampled = True
        self.corner = device_array(Float, (corner / total).astype(np.float32).ravel())
        self.cell_mean = device_array(Float, (weights / total).astype(np.float32))
        cdf = np.cumsum(weights) / total
        self.cdf = device_array(Float, cdf.astype(np.float32))
        self.cell_count = len(weights)

    @property
    def values(self) -> Array3f:
        """What the lookups read: the constant radiance, or the map's texels times its scale."""
        return self.constant if self.constant is not None else self.texels

    @values.setter
    def values(self, values: Array3f) -> None:
        if self.constant is not None:
            self.constant = values
        else:
            self.texels = values

    def attach(self, radiance: Array3f | None = None, texels: TensorXf | None = None,
               scale: Float | None = None) -> None:
        """Give the lookups the derivatives of a constant environment's ``radiance``, or of a
        map's ``texels`` ((H, W, 3)) and ``scale`` (both given); the stored values stay, and
        so does the sampling density (a choice of samples, not part of what they estimate)."""
        if radiance is not None:
            self.constant = self.constant + (radiance - dr.detach(radiance))
            return
        index = dr.arange(UInt32, self.width * self.height) * 3
        product = Array3f(*[dr.gather(Float, texels.array, index + c) for c in range(3)]) * scale
        self.texels = self.texels + (product - dr.detach(product))

    # -- lookups --------------------------------------------------------------------------

    def radiance(self, d: Array3f) -> Array3f:
        """Radiance arriving along -d (d: world directions the rays travel, unit)."""
        if self.constant is not None:
            return self.constant
        x, y = self._grid_point(self._local(d))
        return self._bilinear(x, y)

    def pdf(self, d: Array3f) -> Float:
        """Solid-angle density with which :meth:`sample` picks the world direction d."""
        if self.constant is not None:
            return dr.full(Float, 0.25 / math.pi, dr.width(d))
        local = self._local(d)
        x, y = self._grid_point(local)
        column = Int32(dr.floor(x))
        fx = x - Float(column)
        column = dr.select(column < 0, column + self.width, column)
        row = dr.minimum(Int32(dr.floor(y)), self.height - 2)
        fy = y - Float(row)
        sin_theta = dr.safe_sqrt(dr.fma(local.x, local.x, local.z * local.z))
        density = self._bilinear_density(row, column, fx, fy)
        return dr.select(sin_theta > 0, density / (2.0 * math.pi ** 2 * sin_theta), 0.0)

    def sample(self, u1: Float, u2: Float, u3: Float) -> tuple[Array3f, Float, Array3f]:
        """(world direction, its solid-angle density, the radiance arriving along it); a
        constant environment uniformly over the sphere (drawn only where no BSDF samples
        find it, the direct integrator's ``bsdf_samples`` 0, and by ``volpath``)."""
        if self.constant is not None:
            return square_to_uniform_sphere(u1, u2), Float(0.25 / math.pi), self.constant
        cell = dr.binary_search(0, self.cell_count - 1,
                                lambda i: dr.gather(Float, self.cdf, i) <= u1)
        cell = dr.minimum(cell, self.cell_count - 1)
        row = cell // self.width
        column = cell - row * self.width
        corners = self._corners(Int32(row), Int32(column))
        point, _ = mitsuba_module().warp.square_to_bilinear(*corners, mitsuba_module().Point2f(u2, u3))
        x, y = Float(column) + point.x, Float(row) + point.y
        # Back from the grid point to (u, v) and the direction.
        phi = 2.0 * math.pi * ((x + 0.5) / self.width)
        theta = math.pi * (y / (self.height - 1))
        sin_theta, cos_theta = dr.sincos(theta)
        sin_phi, cos_phi = dr.sincos(phi)
        local = Array3f(sin_phi * sin_theta, cos_theta, -cos_phi * sin_theta)
        d = self._rotated(local, self.to_world)
        # The density as pdf() gives it (rounding can put a point on a cell's edge into
        # the next cell): MIS weighs both techniques by one function.
        return d, self.pdf(d), self._bilinear(x, y)

    def _corners(self, row: Int32, column: Int32) -> list[Float]:
        """The density's values at the cell's corners: (x, y) = (0, 0), (1, 0), (0, 1), (1, 1)."""
        right = dr.select(column + 1 >= self.width, 0, column + 1)
        return [dr.gather(Float, self.corner, UInt32(r * self.width + c))
                for r, c in ((row, column), (row, right), (row + 1, column), (row + 1, right))]

    def _bilinear_density(self, row: Int32, column: Int32, fx: Float, fy: Float) -> Float:
        """Density in (u, v) at (fx, fy) in the cell: the corner values interpolated, per
        unit of the grid's cells (width x (height - 1) of them over [0, 1]^2)."""
        v00, v10, v01, v11 = self._corners(row, column)
        value = dr.lerp(dr.lerp(v00, v10, fx), dr.lerp(v01, v11, fx), fy)
        return value * (self.width * (self.height - 1))

    # -- the map's frame and grid ------------------------------------------------------------

    def _local(self, d: Array3f) -> Array3f:
        return self._rotated(d, self.from_world)

    @staticmethod
    def _rotated(d: Array3f, m: list) -> Array3f:
        return Array3f(*[dr.fma(m[3 * r], d.x, dr.fma(m[3 * r + 1], d.y, m[3 * r + 2] * d.z))
                         for r in range(3)])

    def _grid_point(self, local: Array3f) -> tuple[Float, Float]:
        """The direction's place on the interpolation grid: x in [-1/2, width - 1/2) texel
        units across u (texel centres at integers), y in [0, height - 1] down v."""
        u = dr.atan2(local.x, -local.z) * (0.5 / math.pi)
        u = u - dr.floor(u)
        v = dr.safe_acos(local.y) * (1.0 / math.pi)
        return u * self.width - 0.5, dr.clip(v, 0.0, 1.0) * (self.height - 1)

    def _bilinear(self, x: Float, y: Float) -> Array3f:
        """The texels interpolated at grid point (x, y): columns wrap, rows clamp."""
        x0, y0 = dr.floor(x), dr.floor(y)
        fx, fy = x - x0, y - y0
        c0 = Int32(x0)
        c0 = dr.select(c0 < 0, c0 + self.width, c0)
        c1 = dr.select(c0 + 1 >= self.width, c0 + 1 - self.width, c0 + 1)
        r0 = dr.minimum(Int32(y0), self.height - 1)
        r1 = dr.minimum(r0 + 1, self.height - 1)

        def texel(r, c):
            return dr.gather(Array3f, self.texels, UInt32(r * self.width + c))

        top = dr.lerp(texel(r0, c0), texel(r0, c1), fx)
        bottom = dr.lerp(texel(r1, c0), texel(r1, c1), fx)
        return dr.lerp(top, bottom, fy)
