"""Axis-aligned boxes: the ray/box slab test and the outward float32 rounding that
keeps a box conservative."""

from __future__ import annotations

import numpy as np

from .backend import Array3f, Bool, Float, dr


#: t_far and t_max scaled up by 2 ulp-ish (Ize, "Robust BVH Ray Traversal") in the box test,
#: so that rounding in the slab test never culls a box the ray touches, nor one whose surface
#: ties the nearest hit so far (its entry distance can round above that hit's t).
SLAB_SLACK = 1.0 + 2.0 * 1.1920929e-07


def slab_span(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f) -> tuple[Float, Float]:
    """Slab test of the ray ``o + t d`` (``inv_d = 1 / d``) against a box: the part
    (t_near, t_far) of t >= 0 inside it (empty: t_near > t_far)."""
    return _slabs(lo, hi, o, inv_d, 0.0)


def slab_interval(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f) -> tuple[Float, Float]:
    """The interval (t_enter, t_exit) of the whole line ``o + t d`` inside the box, t of
    either sign (empty: t_enter > t_exit)."""
    return _slabs(lo, hi, o, inv_d, -float("inf"))


def _slabs(lo, hi, o, inv_d, t_from: float) -> tuple[Float, Float]:
    """The last slab entered after ``t_from`` and the first one left, in the precision of
    ``o``. An axis whose distances are NaN (0 * inf: an origin on a slab's plane, the
    direction parallel to it) is left out, so that the box is not culled there."""
    t_lo = (lo - o) * inv_d
    t_hi = (hi - o) * inv_d
    # Each axis's entry and exit by the direction's sign, then the running bounds by
    # compare and select: a NaN compares false and is skipped, and each select compiles to
    # one min or max instruction (dr.minimum's NaN-propagating form takes several).
    backwards = inv_d < 0
    near = dr.select(backwards, t_hi, t_lo)
    far = dr.select(backwards, t_lo, t_hi)
    scalar = type(near.x)
    t_enter, t_exit = scalar(t_from), scalar(float("inf"))
    for k in range(3):
        t_enter = dr.select(near[k] > t_enter, near[k], t_enter)
        t_exit = dr.select(far[k] < t_exit, far[k], t_exit)
    return t_enter, t_exit


def ray_box(lo: Array3f, hi: Array3f, o: Array3f, inv_d: Array3f, t_max: Float) -> tuple[Float, Bool]:
    """Ray/box slab test: (entry distance, hit) for the segment (0, t_max) of the ray
    ``o + t d`` (``inv_d = 1 / d``)."""
    t_near, t_far = slab_span(lo, hi, o, inv_d)
    return t_near, within(t_near, t_far) & within(t_near, t_max)


def within(t_near: Float, t_max: Float) -> Bool:
    """Whether a box entered at ``t_near`` lies within ``t_max`` up to the slab test's
    rounding (:data:`SLAB_SLACK`): the test that culls a box behind the nearest hit."""
    return t_near <= t_max * SLAB_SLACK


def outward32(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Round float64 boxes outward to float32 so that they stay conservative."""
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32
