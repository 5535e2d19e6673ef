"""The ray/box slab test and the pairing of overlapping boxes (instancing.core.box)."""

from __future__ import annotations

import numpy as np
import pytest

from instancing.core import box
from instancing.core.backend import Array3f, Float, dr
from instancing.core.box import outward32, overlapping_pairs, ray_box


def test_a_box_is_not_culled_by_a_hit_on_its_own_surface():
    """A traversal culls a box whose entry lies beyond the nearest hit so far; a hit on the
    box's own surface (a coincident face, a flat instance's plane) must not cull it, although
    the float32 entry distance can round above that hit's t. Rays from random origins to
    random points on random float32 boxes' faces, t_max the float32-rounded exact distance
    of the crossing (float64 from the float32 ray)."""
    rng = np.random.default_rng(5)
    n = 100_000
    lo = rng.uniform(-10, 10, (n, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0, 5, (n, 3))).astype(np.float32)
    rows, axis = np.arange(n), rng.integers(0, 3, n)
    face = np.where(rng.integers(0, 2, n) == 1, hi[rows, axis], lo[rows, axis]).astype(np.float64)
    p = rng.uniform(lo, hi)
    p[rows, axis] = face
    o = rng.uniform(-30, 30, (n, 3)).astype(np.float32)
    d = p - o
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    t = ((face - o[rows, axis]) / d[rows, axis]).astype(np.float32)
    ahead = t > 0
    t_near, hit = ray_box(Array3f(*lo.T), Array3f(*hi.T), Array3f(*o.T), dr.rcp(Array3f(*d.T)), Float(t))
    t_near, hit = np.array(t_near), np.array(hit)
    # The sample does reach the rounding: many entries come out above the crossing's t.
    assert (t_near[ahead] > t[ahead]).sum() > 1000
    assert hit[ahead].all()


def test_outward32_contains_the_float64_box():
    rng = np.random.default_rng(6)
    lo = rng.normal(0, 1e3, (10_000, 3))
    hi = lo + rng.uniform(0, 1, (10_000, 3))
    lo32, hi32 = outward32(lo, hi)
    assert lo32.dtype == hi32.dtype == np.float32
    assert (lo32 <= lo).all() and (hi32 >= hi).all()
    # Each bound is the nearest float32 or, where that lies inside the box, the next one out.
    near_lo, near_hi = lo.astype(np.float32), hi.astype(np.float32)
    assert ((lo32 == near_lo) | (lo32 == np.nextafter(near_lo, np.float32(-np.inf)))).all()
    assert ((hi32 == near_hi) | (hi32 == np.nextafter(near_hi, np.float32(np.inf)))).all()
    assert (lo32 < near_lo).any() and (hi32 > near_hi).any()


@pytest.mark.parametrize("path", ["grid", "direct"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overlapping_pairs_are_the_brute_force_pairs(seed, path, monkeypatch):
    """Boxes of mixed sizes (many small, a few spanning most of the field, some touching
    exactly, some degenerate) paired by the grid, or by the direct tests in blocks of a few
    rows, against all N M tests in float64, across two sets and within one."""
    if path == "grid":
        monkeypatch.setattr(box, "PAIRING_DIRECT_TESTS", 0)
    else:
        monkeypatch.setattr(box, "PAIRING_BLOCK_TESTS", 1500)
    rng = np.random.default_rng(seed)

    def boxes(n):
        lo = rng.uniform(-10, 10, (n, 3))
        size = rng.exponential(0.4, (n, 3))
        size[rng.random(n) < 0.02] *= 60.0  # outsized boxes
        size[rng.random(n) < 0.05, 0] = 0.0  # flat boxes
        return lo, lo + size

    lo_a, hi_a = boxes(700)
    lo_b, hi_b = boxes(500)
    hi_b[:20] += hi_a[:20] - lo_b[:20]  # boxes that only touch a corner of an a box
    lo_b[:20] = hi_a[:20]
    i, j = overlapping_pairs(lo_a, hi_a, lo_b, hi_b)
    brute = np.all((lo_a[:, None] <= hi_b[None]) & (lo_b[None] <= hi_a[:, None]), axis=2)
    expected_i, expected_j = np.nonzero(brute)
    assert len(expected_i) > 300
    np.testing.assert_array_equal(i, expected_i)
    np.testing.assert_array_equal(j, expected_j)
    assert overlapping_pairs(lo_a[:0], hi_a[:0], lo_b, hi_b)[0].size == 0
    # One set: the pairs i < j among it.
    i, j = overlapping_pairs(lo_a, hi_a)
    expected_i, expected_j = np.nonzero(np.triu(np.all((lo_a[:, None] <= hi_a[None])
                                                       & (lo_a[None] <= hi_a[:, None]), axis=2), 1))
    np.testing.assert_array_equal(i, expected_i)
    np.testing.assert_array_equal(j, expected_j)


@pytest.mark.parametrize("seed", [0, 1])
def test_swept_overlap_is_overlap_somewhere_along_the_sweep(seed):
    """Boxes b moved along their sweeps (some with an axis held still, some starting or
    ending just touching) meet a exactly when the static overlap test holds at some t of a
    fine grid over [0, 1], up to the grid's step."""
    rng = np.random.default_rng(seed)
    n = 1500
    lo_a = rng.uniform(-5, 5, (n, 3))
    hi_a = lo_a + rng.exponential(0.5, (n, 3))
    lo_b = lo_a + rng.normal(0.0, 1.5, (n, 3))
    hi_b = lo_b + rng.exponential(0.5, (n, 3))
    # Mostly towards a, by more or less than the way there.
    sweep = (lo_a - lo_b) * rng.uniform(0.0, 2.0, (n, 1)) + rng.normal(0.0, 0.7, (n, 3))
    sweep[rng.random((n, 3)) < 0.15] = 0.0
    # Boxes that touch a exactly (dyadic bounds: no rounding) at the sweep's start, moving
    # away along x, or at its end, coming towards it, level with it in y and z.
    hi_a[:100, 0] = np.round(hi_a[:100, 0] * 1024.0) / 1024.0
    lo_b[:100, 1:], hi_b[:100, 1:], sweep[:100, 1:] = lo_a[:100, 1:], hi_a[:100, 1:], 0.0
    sweep[:100, 0] = np.repeat([2.0, -2.0], 50)
    lo_b[:100, 0] = hi_a[:100, 0] - np.repeat([0.0, -2.0], 50)
    hi_b[:100, 0] = lo_b[:100, 0] + 0.25
    got = box.swept_overlap(lo_a, hi_a, lo_b, hi_b, sweep)
    t = np.linspace(0.0, 1.0, 2001)
    shifted = sweep[:, None] * t[None, :, None]
    met = np.all((lo_a[:, None] <= hi_b[:, None] + shifted)
                 & (lo_b[:, None] + shifted <= hi_a[:, None]), axis=-1)
    assert (got >= met.any(axis=1)).all()  # conservative
    # Found but missed by the grid: the boxes come within one grid step of the sweep.
    step = np.abs(sweep).max(axis=1, keepdims=True) / (len(t) - 1)
    gap = np.maximum(np.maximum(lo_a[:, None] - hi_b[:, None] - shifted,
                                lo_b[:, None] + shifted - hi_a[:, None]), 0.0).max(axis=-1)
    only_got = got & ~met.any(axis=1)
    assert (gap.min(axis=1)[only_got] <= step[only_got, 0] + 1e-9).all()
    assert 0.2 < got.mean() < 0.8
    assert met[:100].any(axis=1).all()
