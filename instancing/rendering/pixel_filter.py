"""Reconstruction filters: Mitsuba's ``box``, ``gaussian`` and ``tent``, separable in x and y,
of any size (the Gaussian's standard deviation, the tent's radius), and its cubic filters of
radius 2, ``mitchell`` (any B and C) and ``catmullrom`` (Mitchell and Netravali's family,
whose negative lobes sharpen), and the windowed sinc ``lanczos`` of any whole number of lobes.

Film samples are drawn uniformly in their pixel. With a box each pixel averages its own;
with a wide filter they are splatted as Mitsuba's film does (:attr:`PixelFilter.splats`:
weighted into every pixel the filter reaches, each pixel divided by its weights' sum).
Mitsuba draws its samples on the film only, so a pixel near the film's edge averages the
part of its filter that lies on the film; with the film's ``sample_border`` it also samples
a border around the film (:attr:`PixelFilter.border`), and every pixel averages its whole
filter. Boundary samples, which land at given film points, are splatted into the pixels
whose filter covers them with the filter's density (:meth:`PixelFilter.weight`), divided by
the share of the filter that the film samples (:meth:`PixelFilter.film_share`). All
estimate Mitsuba's filtered image.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..core.backend import Float, dr
from ..scene.camera import CUBIC_FILTERS, GAUSSIAN_REACH, RFILTER_SIZES, Camera

#: The Gaussian's mass within its reach (the same for every standard deviation).
_GAUSSIAN_EDGE = math.erf(GAUSSIAN_REACH / math.sqrt(2.0))
#: Chebyshev terms per lobe of a Lanczos filter's integral (error below 1e-7 for 1 - 32 lobes).
_LANCZOS_TERMS_PER_LOBE = 8
#: Mitsuba's ray epsilon for float32 (1500 ulp of 1), by which its film border falls short
#: of the filter's radius.
_RAY_EPSILON = 1500.0 * 2.0 ** -24


@dataclass(frozen=True)
class PixelFilter:
    """A reconstruction filter: ``name`` one of :data:`~instancing.scene.camera.RFILTERS`,
    ``size`` the Gaussian's standard deviation or the tent's radius in pixels (None:
    Mitsuba's default; the box has no size)."""

    name: str
    size: float | None = None
    #: Whether samples are restricted to the film (False: the film's ``sample_border``).
    film_only: bool = True
    #: A cubic filter's (B, C) (None: its own, :data:`~instancing.scene.camera.CUBIC_FILTERS`).
    bc: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        default = RFILTER_SIZES[self.name]
        if default is not None and self.size is None:
            object.__setattr__(self, "size", default[1])
        if self.name in CUBIC_FILTERS and self.bc is None:
            object.__setattr__(self, "bc", CUBIC_FILTERS[self.name])

    @classmethod
    def of(cls, camera: Camera) -> "PixelFilter":
        """The filter of a camera's film."""
        return cls(camera.rfilter, camera.rfilter_size, not camera.sample_border, camera.rfilter_bc)

    @property
    def splats(self) -> bool:
        """Whether film samples are splatted (Mitsuba's film: added into every pixel the
        filter reaches with its weight there, each pixel divided by its weights' sum): the
        wide filters. With the box each pixel averages its own samples."""
        return self.name != "box"

    @property
    def border(self) -> int:
        """Pixels sampled beyond each side of the film: Mitsuba's border, the filter's
        radius less half a pixel rounded up, where the film samples its border; else 0."""
        if self.film_only or self.radius is None:
            return 0
        return int(math.ceil(self.radius - 0.5 - 2.0 * _RAY_EPSILON))

    @property
    def reach(self) -> int:
        """The pixels a sample reaches on either side of its own, by the filter's radius."""
        return 0 if self.radius is None else int(math.floor(self.radius + 0.5))

    @property
    def radius(self) -> float | None:
        """Its reach in pixels (None for the box, which covers its own pixel only)."""
        if self.name == "box":
            return None
        if self.name in CUBIC_FILTERS:
            return 2.0
        return GAUSSIAN_REACH * self.size if self.name == "gaussian" else self.size


    def cdf(self, offset: Float) -> Float:
        """The filter's mass below an offset from the pixel centre (0 to 1 across its reach)."""
        if self.name == "box":
            return dr.clip(offset + 0.5, 0.0, 1.0)
        if self.name == "tent":
            x = dr.clip(offset / self.size, -1.0, 1.0)
            return dr.select(x < 0.0, 0.5 * dr.square(1.0 + x), 1.0 - 0.5 * dr.square(1.0 - x))
        if self.bc is not None:
            # The cubic's integral from 0 to |x| (its pieces' antiderivatives), odd about 0.
            x = dr.minimum(dr.abs(offset), 2.0)
            inner, outer = _cubic_pieces(*self.bc)
            near = dr.minimum(x, 1.0)
            far = dr.maximum(x, 1.0)
            half = _antiderivative(inner, near) + _antiderivative(outer, far) - _antiderivative(outer, 1.0)
            return 0.5 + dr.select(offset < 0.0, -half, half)
        if self.name == "lanczos":
            series = _lanczos(self.size)[1]
            half = _chebyshev(series, 2.0 * dr.minimum(dr.abs(offset), self.size) / self.size - 1.0)
            return 0.5 + dr.select(offset < 0.0, -half, half)
        x = dr.clip(offset, -self.radius, self.radius)
        return 0.5 + 0.5 * dr.erf(x / (self.size * math.sqrt(2.0))) / _GAUSSIAN_EDGE

    def film_share(self, centre: Float, size) -> Float:
        """The share of the filter around a pixel centre that lies on a film side of
        ``size`` pixels (1 away from the film's edges, and everywhere when samples are not
        restricted to the film)."""
        if not self.film_only:
            return 1.0
        return self.cdf(size - centre) - self.cdf(-centre)

    def weight(self, offset: Float) -> Float:
        """The filter's density (per pixel) at a film offset; 0 beyond its radius (the box:
        1 within half a pixel)."""
        if self.name == "box":
            return dr.select(dr.abs(offset) <= 0.5, 1.0, 0.0)
        if self.name == "tent":
            return dr.maximum(1.0 - dr.abs(offset) / self.size, 0.0) / self.size
        if self.bc is not None:
            # Mitchell and Netravali's piecewise cubic (its integral is 1 for every B and C).
            x = dr.abs(offset)
            inner, outer = _cubic_pieces(*self.bc)
            value = dr.select(x < 1.0, _polynomial(inner, x), _polynomial(outer, x))
            return dr.select(x < 2.0, value, 0.0)
        if self.name == "lanczos":
            # sinc(pi x) sinc(pi x / lobes) within its lobes, as Mitsuba's, normalised.
            x = dr.abs(offset)
            x1 = math.pi * x
            x2 = x1 / self.size
            value = dr.select(x < 1e-7, 1.0, dr.sin(x1) * dr.sin(x2) / (x1 * x2))
            return dr.select(x <= self.size, value, 0.0) / _lanczos(self.size)[0]
        norm = self.size * math.sqrt(2 * math.pi) * _GAUSSIAN_EDGE
        return dr.select(dr.abs(offset) <= self.radius,
                         dr.exp(-0.5 * dr.square(offset / self.size)) / norm, 0.0)


def _cubic_pieces(b: float, c: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The coefficients (constant first) of Mitchell and Netravali's cubic on |x| < 1 and on
    1 <= |x| < 2, for its B and C (as Mitsuba's ``mitchell`` evaluates it)."""
    inner = ((6.0 - 2.0 * b) / 6.0, 0.0, (-18.0 + 12.0 * b + 6.0 * c) / 6.0, (12.0 - 9.0 * b - 6.0 * c) / 6.0)
    outer = ((8.0 * b + 24.0 * c) / 6.0, (-12.0 * b - 48.0 * c) / 6.0, (6.0 * b + 30.0 * c) / 6.0,
             (-b - 6.0 * c) / 6.0)
    return inner, outer


def _polynomial(coefficients: tuple[float, ...], x: Float) -> Float:
    """sum_k a_k x^k (Horner)."""
    value = Float(coefficients[-1])
    for a in coefficients[-2::-1]:
        value = dr.fma(value, x, a)
    return value


def _antiderivative(coefficients: tuple[float, ...], x: Float) -> Float:
    """The polynomial's integral from 0 to x."""
    return x * _polynomial(tuple(a / (k + 1) for k, a in enumerate(coefficients)), x)


def _chebyshev(series: np.ndarray, u: Float) -> Float:
    """The Chebyshev series sum_k c_k T_k(u) at u in [-1, 1] (Clenshaw's recurrence)."""
    b1, b2 = Float(0.0), Float(0.0)
    for c in series[:0:-1]:
        b1, b2 = dr.fma(2.0 * u, b1, float(c) - b2), b1
    return dr.fma(u, b1, float(series[0]) - b2)


@functools.cache
def _lanczos(lobes: float) -> tuple[float, np.ndarray]:
    """A Lanczos filter's integral over its reach and the Chebyshev series (on [0, lobes],
    mapped to [-1, 1]) of its normalised integral from 0: the windowed sinc's integral has
    no closed form, so it is summed once in float64 (trapezoids on 2^12 steps per lobe) and
    fitted at Chebyshev points, LANCZOS_TERMS_PER_LOBE terms per lobe."""
    x = np.linspace(0.0, lobes, int(lobes) * (1 << 12) + 1)
    w = np.sinc(x) * np.sinc(x / lobes)
    half = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(x))])
    norm = 2.0 * half[-1]
    degree = _LANCZOS_TERMS_PER_LOBE * int(lobes) + 8
    nodes = np.cos(np.pi * (np.arange(2 * degree) + 0.5) / (2 * degree))
    values = np.interp(0.5 * lobes * (nodes + 1.0), x, half) / norm
    return norm, np.polynomial.chebyshev.chebfit(nodes, values, degree)
