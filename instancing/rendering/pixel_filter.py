"""Reconstruction filters: Mitsuba's ``box``, ``gaussian`` and ``tent``, separable in x and y.

Film samples are drawn from the filter's distribution (filter importance sampling:
:meth:`PixelFilter.offset`), so every camera sample has weight 1; boundary samples, which
land at given film points, are splatted into the pixels whose filter covers them with the
filter's density (:meth:`PixelFilter.weight`). Both estimate Mitsuba's filtered image,
which splats each sample with the filter's weights and divides by their sum. Mitsuba
draws its samples on the film only, so a pixel near the film's edge averages the part of
its filter that lies on the film: ours are drawn from the filter restricted to the film,
and splatted with its density divided by that part's share
(:meth:`PixelFilter.film_share`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..core.backend import Float, dr

#: Mitsuba's ``gaussian`` filter: standard deviation 0.5 px, truncated at 4 sigma.
GAUSSIAN_STDDEV = 0.5
GAUSSIAN_RADIUS = 4 * GAUSSIAN_STDDEV
#: The Gaussian's erf argument scale (sigma sqrt 2) and its mass within the radius.
_GAUSSIAN_SCALE = GAUSSIAN_STDDEV * math.sqrt(2.0)
_GAUSSIAN_EDGE = math.erf(GAUSSIAN_RADIUS / _GAUSSIAN_SCALE)
#: Mitsuba's ``tent`` filter radius (px).
TENT_RADIUS = 1.0


@dataclass(frozen=True)
class PixelFilter:
    """One of :data:`PIXEL_FILTERS`: ``radius`` is its reach in pixels (None for the box,
    which covers its own pixel only)."""

    name: str
    radius: float | None

    def offset(self, u: Float, low: Float | None = None, high: Float | None = None) -> Float:
        """An offset from the pixel centre (pixels) distributed as the filter, from u in
        [0, 1); with ``low`` and ``high``, as the filter restricted to [low, high] (the part
        of its reach that lies on the film: Mitsuba draws film samples on the film only)."""
        if self.name == "box":
            return u - 0.5
        if low is not None:
            below = self.cdf(low)
            u = dr.fma(u, self.cdf(high) - below, below)
        if self.name == "tent":
            # Inverse CDF of the density 1 - |x| on [-1, 1], scaled to the radius.
            lower = dr.sqrt(2.0 * u) - 1.0
            upper = 1.0 - dr.sqrt(2.0 - 2.0 * u)
            return TENT_RADIUS * dr.select(u < 0.5, lower, upper)
        # Inverse CDF of the Gaussian truncated to [-R, R].
        return _GAUSSIAN_SCALE * dr.erfinv((2.0 * u - 1.0) * _GAUSSIAN_EDGE)

    def cdf(self, offset: Float) -> Float:
        """The filter's mass below an offset from the pixel centre (0 to 1 across its reach)."""
        if self.name == "box":
            return dr.clip(offset + 0.5, 0.0, 1.0)
        if self.name == "tent":
            x = dr.clip(offset / TENT_RADIUS, -1.0, 1.0)
            return dr.select(x < 0.0, 0.5 * dr.square(1.0 + x), 1.0 - 0.5 * dr.square(1.0 - x))
        x = dr.clip(offset, -GAUSSIAN_RADIUS, GAUSSIAN_RADIUS)
        return 0.5 + 0.5 * dr.erf(x / _GAUSSIAN_SCALE) / _GAUSSIAN_EDGE

    def film_share(self, centre: Float, size) -> Float:
        """The share of the filter around a pixel centre that lies on a film side of
        ``size`` pixels (1 away from the film's edges)."""
        return self.cdf(size - centre) - self.cdf(-centre)

    def weight(self, offset: Float) -> Float:
        """The filter's density (per pixel) at a film offset; 0 beyond its radius (the box:
        1 within half a pixel)."""
        if self.name == "box":
            return dr.select(dr.abs(offset) <= 0.5, 1.0, 0.0)
        if self.name == "tent":
            return dr.maximum(1.0 - dr.abs(offset) / TENT_RADIUS, 0.0) / TENT_RADIUS
        norm = GAUSSIAN_STDDEV * math.sqrt(2 * math.pi) * _GAUSSIAN_EDGE
        return dr.select(dr.abs(offset) <= GAUSSIAN_RADIUS,
                         dr.exp(-0.5 * dr.square(offset / GAUSSIAN_STDDEV)) / norm, 0.0)


PIXEL_FILTERS = {"box": PixelFilter("box", None), "gaussian": PixelFilter("gaussian", GAUSSIAN_RADIUS),
                 "tent": PixelFilter("tent", TENT_RADIUS)}
