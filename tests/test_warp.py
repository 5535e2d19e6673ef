"""Sample warps (instancing/core/warp.py) against float64 NumPy closed forms.

Directions come back as float32 Dr.Jit arrays and are checked in float64. Distribution
tests use a fixed seed and a tolerance of 5 Monte Carlo standard errors (binomial per
histogram bin, or the sample standard deviation of a mean): a correct warp passes them
deterministically, a wrong density (e.g. uniform instead of cosine-weighted) misses them
by tens of standard errors.
"""

import math

import numpy as np
import pytest

import instancing  # noqa: F401  (selects the backend)
from instancing.core import warp
from instancing.core.backend import Array3f, Float

#: float32 unit roundoff; bounds below are a few of these (a sqrt, a sincos, a product).
EPS32 = 2.0 ** -24


def _floats(x: np.ndarray) -> Float:
    return Float(np.ascontiguousarray(x, np.float32))


def _vectors(x: np.ndarray) -> Array3f:
    return Array3f(*[_floats(x[:, k]) for k in range(3)])


def _zeros(n: int) -> Float:
    return _floats(np.zeros(n))


def _rows(v: Array3f) -> np.ndarray:
    return np.asarray(v, np.float64).T


def _uniform_squares(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # float32 draws in [0, 1): the warps' domain, never 1.0 after rounding.
    return rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32)


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v.astype(np.float32).astype(np.float64)


def _assert_uniform_histogram(a: np.ndarray, b: np.ndarray, a_range, b_range, bins: int = 8):
    """(a, b) samples fill a bins x bins grid over a_range x b_range evenly, every bin
    within 5 binomial standard errors of its expected count."""
    counts, _, _ = np.histogram2d(a, b, bins=bins, range=[a_range, b_range])
    n, p = len(a), 1.0 / bins ** 2
    sigma = math.sqrt(n * p * (1 - p))
    assert counts.sum() == n
    assert np.abs(counts - n * p).max() < 5 * sigma, counts


def _assert_mean(samples: np.ndarray, expected: float):
    """Sample mean within 5 standard errors of the closed form."""
    se = samples.std() / math.sqrt(len(samples))
    assert abs(samples.mean() - expected) < 5 * se, (samples.mean(), expected, se)


N_SAMPLES = 1 << 17


def test_cosine_hemisphere_directions_are_unit_and_in_the_upper_hemisphere():
    u1, u2 = _uniform_squares(1, N_SAMPLES)
    w = _rows(warp.square_to_cosine_hemisphere(_floats(u1), _floats(u2)))
    # |w| = 1 up to a few float32 roundings (sqrt, sincos, products).
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=8 * EPS32)
    assert (w[:, 2] >= 0).all()


def test_cosine_hemisphere_density_is_cos_over_pi():
    """pdf cos/pi per solid angle: (cos^2 theta, phi) is uniform on [0, 1] x [-pi, pi]
    (dw = d(cos) dphi and d(cos^2) = 2 cos d(cos)), E[cos] = 2/3, and the estimator
    f / pdf of int_H cos^2 dw = 2 pi / 3 is unbiased with pdf = cos * INV_PI."""
    u1, u2 = _uniform_squares(2, N_SAMPLES)
    w = _rows(warp.square_to_cosine_hemisphere(_floats(u1), _floats(u2)))
    cos = w[:, 2]
    _assert_uniform_histogram(cos ** 2, np.arctan2(w[:, 1], w[:, 0]), [0, 1], [-np.pi, np.pi])
    _assert_mean(cos, 2.0 / 3.0)
    _assert_mean(cos ** 2 / (cos * warp.INV_PI), 2.0 * np.pi / 3.0)


def test_uniform_sphere_directions_are_unit():
    u1, u2 = _uniform_squares(3, N_SAMPLES)
    w = _rows(warp.square_to_uniform_sphere(_floats(u1), _floats(u2)))
    # As above: a few float32 roundings.
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=8 * EPS32)


def test_uniform_sphere_density_is_one_over_four_pi():
    """Uniform on the sphere: (z, phi) uniform on [-1, 1] x [-pi, pi] (Archimedes),
    E[z] = 0, E[z^2] = 1/3, and f / pdf with pdf = INV_FOUR_PI estimates
    int_S2 x^2 dw = 4 pi / 3."""
    u1, u2 = _uniform_squares(4, N_SAMPLES)
    w = _rows(warp.square_to_uniform_sphere(_floats(u1), _floats(u2)))
    _assert_uniform_histogram(w[:, 2], np.arctan2(w[:, 1], w[:, 0]), [-1, 1], [-np.pi, np.pi])
    _assert_mean(w[:, 2], 0.0)
    _assert_mean(w[:, 2] ** 2, 1.0 / 3.0)
    _assert_mean(w[:, 0] ** 2 / warp.INV_FOUR_PI, 4.0 * np.pi / 3.0)


def _frame_normals() -> np.ndarray:
    """Random unit normals plus the special cases of the branch-free frame: the poles,
    normals near the south pole (where 1 / (sign + z) is largest), and the equator."""
    rng = np.random.default_rng(5)
    special = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0],
                        [1e-4, 0, -1.0], [0, -3e-4, -1.0], [0.6, 0.8, 0.0], [-0.6, 0.0, -0.8]])
    special /= np.linalg.norm(special, axis=1, keepdims=True)
    return np.concatenate([_unit_vectors(rng, 2000), special.astype(np.float32).astype(np.float64)])


def test_to_frame_maps_plus_z_to_the_normal():
    n = _frame_normals()
    zero = _zeros(len(n))
    mapped = _rows(warp.to_frame(_vectors(n), Array3f(zero, zero, zero + 1.0)))
    # n * 1 + s * 0 + t * 0: exact up to one rounding per term.
    np.testing.assert_allclose(mapped, n, atol=4 * EPS32)


def test_to_frame_is_a_rotation():
    """The images of the local axes are orthonormal and right-handed (det +1), so dot
    products and lengths of any local vectors are kept."""
    n = _frame_normals()
    nv = _vectors(n)
    zero = _zeros(len(n))
    axes = [_rows(warp.to_frame(nv, Array3f(*[zero + float(c) for c in e]))) for e in np.eye(3)]
    frame = np.stack(axes, axis=2)  # columns: images of x, y, z
    gram = np.einsum("nki,nkj->nij", frame, frame)
    # Orthonormal up to a few float32 roundings of the frame's entries (measured < 4e-7).
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=16 * EPS32)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0, atol=16 * EPS32)
    rng = np.random.default_rng(6)
    a = rng.normal(size=(len(n), 3)).astype(np.float32).astype(np.float64)
    b = rng.normal(size=(len(n), 3)).astype(np.float32).astype(np.float64)
    fa, fb = _rows(warp.to_frame(nv, _vectors(a))), _rows(warp.to_frame(nv, _vectors(b)))
    # Same bound, scaled by the vectors' lengths (|a|, |b| < ~5).
    np.testing.assert_allclose(np.sum(fa * fb, axis=1), np.sum(a * b, axis=1), atol=2e-5)


def test_power_heuristic_and_its_mirror_sum_to_one():
    rng = np.random.default_rng(7)
    a = rng.exponential(size=5000).astype(np.float32)
    b = rng.exponential(size=5000).astype(np.float32)
    b[:500] = 0.0  # one strategy cannot produce the sample: the other gets weight 1
    w_ab = np.asarray(warp.power_heuristic(_floats(a), _floats(b)), np.float64)
    w_ba = np.asarray(warp.power_heuristic(_floats(b), _floats(a)), np.float64)
    # a^2 / (a^2 + b^2) rounds three times in float32.
    np.testing.assert_allclose(w_ab + w_ba, 1.0, atol=4 * EPS32)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    np.testing.assert_allclose(w_ab, a64 ** 2 / (a64 ** 2 + b64 ** 2), rtol=4 * EPS32)
    assert (w_ab[:500] == 1.0).all() and (w_ba[:500] == 0.0).all()


def test_power_heuristic_of_densities_whose_squares_overflow_is_finite():
    """Densities past float32's square root (a grazing emitter sample: 1e20) keep their
    ratio's weight (float64 closed form); an infinite one gives 0, as Mitsuba's."""
    a = np.array([1e20, 1e20, 3e25, 1.0, 1e-30, np.inf], np.float32)
    b = np.array([1.0, 2e20, 1e25, 1e22, 1e-31, 1.0], np.float32)
    w = np.asarray(warp.power_heuristic(_floats(a), _floats(b)), np.float64)
    a64, b64 = a[:5].astype(np.float64), b[:5].astype(np.float64)
    np.testing.assert_allclose(w[:5], a64 ** 2 / (a64 ** 2 + b64 ** 2), rtol=8 * EPS32, atol=1e-40)
    assert w[5] == 0.0


@pytest.mark.parametrize("pdf_b", [0.0, 0.5, 1e30])
def test_power_heuristic_is_zero_where_pdf_a_is_zero(pdf_b):
    w = np.asarray(warp.power_heuristic(_floats(np.zeros(4)), _floats(np.full(4, pdf_b))))
    assert np.array_equal(w, np.zeros(4, np.float32))
    assert np.isfinite(w).all()


@pytest.mark.parametrize("distance", [1.05, 3.0, 400.0])
def test_unit_sphere_cone_sample_is_uniform_over_the_cone_of_the_visible_sphere(distance):
    """From points at ``distance`` (in radii) from the centre, in random directions: every
    sample lies on the unit sphere's visible side; the directions to them are uniform over
    the cone the sphere subtends (cos theta uniform on [cos theta_max, 1], float64 closed
    form; azimuth uniform), and the density is 1 / the cone's solid angle."""
    rng = np.random.default_rng(7)
    n = 1 << 16
    axis = rng.normal(size=(n, 3))
    p = distance * axis / np.linalg.norm(axis, axis=1, keepdims=True)
    u1, u2 = _uniform_squares(3, n)
    q = _rows(warp.unit_sphere_cone_sample(_vectors(p), _floats(u1), _floats(u2))).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=2e-6)
    assert (np.sum(q * p, axis=1) >= 1.0 - 1e-4 * distance).all()  # on the side p sees
    to_q = (q - p) / np.linalg.norm(q - p, axis=1, keepdims=True)
    cos_theta = np.sum(to_q * -p, axis=1) / distance
    cos_max = math.sqrt(1.0 - 1.0 / distance ** 2)
    # cos theta is 1 - u1 (1 - cos_max) exactly in float64: the directions fill the cone
    # uniformly in solid angle (error: float32 rounding of the sphere point).
    np.testing.assert_allclose(1.0 - cos_theta, u1 * (1.0 - cos_max), rtol=2e-3,
                               atol=2e-6 * distance)
    pdf = np.asarray(warp.unit_sphere_cone_pdf(_vectors(p)), np.float64)
    np.testing.assert_allclose(pdf, 1.0 / (2 * math.pi * (1.0 - cos_max)), rtol=1e-5)
    # The azimuth around the axis: uniform (its histogram within 5 binomial sigmas).
    s = np.cross(-p / distance, np.array([0.3, 0.5, 0.81]))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    t = np.cross(-p / distance, s)
    phi = np.arctan2(np.sum(to_q * t, axis=1), np.sum(to_q * s, axis=1))
    counts = np.histogram(phi, bins=16, range=(-math.pi, math.pi))[0]
    assert np.abs(counts - n / 16).max() < 5 * math.sqrt(n / 16)
