"""Floating-point error bounds of hit points and sampled points (after pbrt-v4, section 6.8).

A point on a surface is computed in object space by its model (re-projected
onto the surface where the model allows it) and mapped to world space by the
instance's forward affine map, the translation added last. Its error bound is
componentwise and conservative, built from three parts:

1. the model's object-space bound (``AnalyticModel.point_error``,
   ``MeshLibrary.point_error``);
2. the *remap* bound of the instance: a ray that starts at the world point is
   taken back to object space by the stored float32 inverse, which is not the
   exact inverse of the stored float32 forward matrix, and that map rounds
   too. Both move the point, seen from object space, by at most
   ``remap * max|p_obj|`` per coordinate (see :func:`remap_error`);
3. the rounding of the forward map itself, ``gamma(4) (|A| |p_obj| + |b|)``
   (three fused multiply-adds, then the translation).

Higham's ``gamma(n) = n u / (1 - n u)`` bounds the relative error of n
roundings (u = 2^-24 in float32).
"""

from __future__ import annotations

import numpy as np

from .backend import Array3f, Array4f, Float, dr

#: Unit roundoff of float32.
UNIT_ROUNDOFF = 2.0 ** -24


def gamma(n: int) -> float:
    """Bound on the relative error of n float32 roundings (Higham; pbrt-v4's ``gamma``)."""
    return n * UNIT_ROUNDOFF / (1.0 - n * UNIT_ROUNDOFF)


def remap_error(forward: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """Per-instance bound of the object-space displacement of a point taken world -> object.

    Args:
        forward, inverse: (N, 3, 3) float64 holding the *stored* float32 linear
            parts A and A^-1 of each instance.

    Returns:
        (N,) float32 ``rho`` (rounded up) such that mapping a point ``A p + b``
        back with the stored inverse lands within ``rho * max|p|`` of ``p`` in
        every coordinate: ``|A^-1 A - I|_inf`` (the two stored matrices are not
        exact inverses) plus ``gamma(4) | |A^-1| |A| |_inf`` (the subtraction of
        b and the three fused multiply-adds of the inverse map).
    """
    mismatch = np.abs(inverse @ forward - np.eye(3)).sum(axis=2).max(axis=1)
    rounding = (np.abs(inverse) @ np.abs(forward)).sum(axis=2).max(axis=1)
    rho = (mismatch + gamma(4) * rounding).astype(np.float32)
    return np.nextafter(rho, np.float32(np.inf))


def transformed_point_error(rows: tuple[Array4f, Array4f, Array4f], p_obj: Array3f,
                            p_error: Array3f, remap: Float) -> Array3f:
    """World error bound of the point ``A p_obj + b`` (see the module docstring).

    Args:
        rows: the forward rows (A row i, b_i) per lane, as ``InstanceTable.forward``.
        p_obj: object-space point (Array3f).
        p_error: its object-space componentwise error bound (Array3f).
        remap: the instance's remap bound (Float, :func:`remap_error`).
    """
    # Step 2: the remap bound widens the object-space bound in every coordinate.
    p_abs = dr.abs(p_obj)
    e_obj = p_error + remap * dr.maximum(dr.maximum(p_abs.x, p_abs.y), p_abs.z)
    out = []
    for r in rows:
        a = Array3f(dr.abs(r.x), dr.abs(r.y), dr.abs(r.z))
        # Step 1 carried through the linear part, step 3 the rounding of the map itself.
        carried = dr.dot(a, e_obj) * (1.0 + gamma(4))
        out.append(dr.fma(gamma(4), dr.dot(a, p_abs) + dr.abs(r.w), carried))
    # The bound's own arithmetic rounds down at most a few ulp: widen it by gamma(4).
    return Array3f(*out) * (1.0 + gamma(4))
