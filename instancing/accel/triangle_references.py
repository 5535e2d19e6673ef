"""Triangle references: the items of the meshes' BVHs, slender or slanted triangles split
into several before the build (early split clipping: Ernst and Greiner, "Early Split Clipping
for Bounding Volume Hierarchies", 2007; the split budget as in Karras and Aila, "Fast Parallel
Construction of High-Quality Bounding Volume Hierarchies", 2013).

A triangle whose box is much larger than the triangle fills the tree with empty space: the
rays that pass beside a sliver or a long diagonal triangle enter its leaf and the nodes above
it. Such a triangle is given several references instead, each the box of the triangle's part
in one piece of its box, so that the builder sees tight boxes. A leaf holds references; a ray
that enters two leaves referencing one triangle tests it twice, with the same result.

Which triangles, and how many references: a triangle's box excess is its box's surface area
over twice its area (2 for a right triangle along two axes, growing with slant and
slenderness). Triangles of excess SPLIT_MIN_EXCESS or more may split, each into
``1 + floor(D w)`` pieces (at most MAX_PIECES), w the cube root of its box's area beyond its
own two faces (rays enter a box in proportion to its area, and each halving saves less) and D
the largest factor that keeps a mesh's references within MAX_REFERENCES per triangle. The
pieces come from halving: a piece's box is cut at the midpoint of its longest side (a
float32 value), each half taking the box of the triangle's part on its side (the side's
corners and the edges' crossings of the plane), clipped to the piece's box.

Whether a mesh's tree is built over its references or its triangles, the surface area
heuristic decides (:func:`mesh_forest`): splitting the large slanted triangles of a low-poly
tree makes its tree cost more (and walk slower) than it saves. The references are tried only
where the triangles that split hold a good share of the mesh's box area, and for a large mesh
the choice is made on a sample, so that a mesh they do not help loads about as fast as before.
"""

from __future__ import annotations

import numpy as np

from ..core.backend import Array3f64, Bool, Float, Float64, UInt32, dr, device_array
from .bvh import BVHArrays, build_forest, morton_codes, select_trees, tree_costs
from .sah import box_area

#: Box excess from which a triangle may split (module docstring): well-shaped meshes (the
#: bundled torus, Mitsuba's material-preview meshes: 2 - 5 for nearly all triangles) keep
#: their triangles, and Mitsuba's participating-media dome, a fan of slivers (excess 11 at the
#: median), splits (docs/performance.md, participating-media scenes; sweep in
#: docs/how-it-works.md).
SPLIT_MIN_EXCESS = 6.0
#: References of one triangle at most.
MAX_PIECES = 16
#: References per triangle of a mesh at most, on average.
MAX_REFERENCES = 3.0
#: Share of a mesh's triangle box area that its splitting triangles must hold for the
#: references' tree to be tried: Mitsuba's participating-media dome 0.98 (its references win);
#: the bundled low-poly tree 0.42 (they lose, 1.15x its triangles' surface cost); a teapot 0.14
#: (1.03x), Mitsuba's material-preview meshes 0.17 / 0.23 (trying them took the scene's load
#: from 0.20 s to about half a second).
MIN_SPLIT_SHARE = 0.3
#: Relative widening of a reference's box before the builder rounds it outward to float32:
#: covers the float64 rounding of the edges' crossing points.
_CROSSING_SLACK = 1e-13
#: Steps of the bisection for the budget's factor D.
_BISECTION_STEPS = 40


def triangle_boxes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The float64 boxes (lo, hi) (F, 3) of triangles (F, 3 corners, 3) of any float type: the
    corners' smallest and largest coordinates (three elementwise passes, which NumPy runs
    faster than a reduction over the corner axis)."""
    lo = np.minimum(np.minimum(corners[:, 0], corners[:, 1]), corners[:, 2])
    hi = np.maximum(np.maximum(corners[:, 0], corners[:, 1]), corners[:, 2])
    return lo.astype(np.float64, copy=False), hi.astype(np.float64, copy=False)


def piece_counts(corners: np.ndarray, boxes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The number of references of each triangle (F, 3 corners, 3) (module docstring); a
    degenerate triangle, which no ray hits, keeps one. ``boxes``: the triangles'
    :func:`triangle_boxes`, where known."""
    lo, hi = triangle_boxes(corners) if boxes is None else boxes
    first = corners[:, 0].astype(np.float64)
    area2 = np.linalg.norm(np.cross(corners[:, 1] - first, corners[:, 2] - first), axis=1)
    boxes = box_area(lo, hi)
    candidate = (area2 > 0) & (boxes >= SPLIT_MIN_EXCESS * area2)
    waste = np.where(candidate, np.maximum(boxes - area2, 0.0), 0.0) ** (1.0 / 3.0)

    def counts(factor: float) -> np.ndarray:
        return np.minimum(1 + np.floor(factor * waste), MAX_PIECES).astype(np.int64)

    budget = MAX_REFERENCES * len(corners)
    if not candidate.any():
        return counts(0.0)
    # The largest factor within the budget, by bisection (the sum grows with it).
    low, high = 0.0, MAX_PIECES / waste[candidate].min()
    for _ in range(_BISECTION_STEPS):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if counts(middle).sum() <= budget else (low, middle)
    return counts(low)


def triangle_references(corners: np.ndarray, count: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The BVH items of a mesh's triangles (F, 3 corners, 3; float32 values, as the walk tests
    them), ``count`` references each (by default their :func:`piece_counts`): (each
    reference's triangle index (R,), its box lo (R, 3), hi (R, 3)), float64 boxes that hold
    the triangle's part they stand for. A triangle of one piece is its own box."""
    corners = np.asarray(corners, np.float64)
    count = piece_counts(corners) if count is None else count
    lo, hi = triangle_boxes(corners)
    whole = count == 1
    done = [(np.flatnonzero(whole), lo[whole], hi[whole])]
    pending = (np.flatnonzero(~whole), lo[~whole], hi[~whole], count[~whole])
    flat = device_array(Float64, corners.ravel()) if len(pending[0]) else None
    while len(pending[0]):
        halves = _halves(flat, *pending[:3])
        pending = _next_pieces(pending, *halves)
        whole = pending[3] == 1
        done.append(tuple(a[whole] for a in pending[:3]))
        pending = tuple(a[~whole] for a in pending)
    triangle, lo, hi = (np.concatenate(parts) for parts in zip(*done))
    slack = _CROSSING_SLACK * np.abs(corners).max(axis=(1, 2))[triangle, None]
    return triangle, lo - slack, hi + slack


def _halves(corners: Float64, triangle: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Each piece (triangle, box lo, hi) cut at the midpoint of its box's longest side: per
    half (below the plane, above it), its box (lo, hi) and whether it holds part of the
    triangle (not where the side is too short to cut); NumPy arrays, computed by one kernel."""
    t = UInt32(triangle.astype(np.uint32))
    box_lo, box_hi = (Array3f64(*[Float64(b[:, k]) for k in range(3)]) for b in (lo, hi))
    v = [dr.gather(Array3f64, corners, t * 3 + c) for c in range(3)]
    extent = box_hi - box_lo
    on_x = (extent.x >= extent.y) & (extent.x >= extent.z)
    on_y = ~on_x & (extent.y >= extent.z)
    on_z = ~on_x & ~on_y

    def along(p: Array3f64) -> Float64:
        return dr.select(on_x, p.x, dr.select(on_y, p.y, p.z))

    start, end = along(box_lo), along(box_hi)
    plane = Float64(Float(0.5 * (start + end)))
    cuttable = (plane > start) & (plane < end)
    x = [along(p) for p in v]
    inf = Array3f64(dr.inf)
    parts = [[inf, -inf], [inf, -inf]]  # (lo, hi) below and above the plane
    points = [(x[c] <= plane, x[c] >= plane, v[c]) for c in range(3)]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        crosses = (x[a] - plane) * (x[b] - plane) < 0
        point = dr.fma(v[b] - v[a], (plane - x[a]) / dr.select(crosses, x[b] - x[a], 1.0), v[a])
        point = Array3f64(dr.select(on_x, plane, point.x), dr.select(on_y, plane, point.y),
                          dr.select(on_z, plane, point.z))
        points.append((crosses, crosses, point))
    for below, above, point in points:
        for side, part in zip((below, above), parts):
            part[0] = dr.select(side, dr.minimum(part[0], point), part[0])
            part[1] = dr.select(side, dr.maximum(part[1], point), part[1])
    results = []
    for k, (part_lo, part_hi) in enumerate(parts):
        part_lo, part_hi = dr.maximum(part_lo, box_lo), dr.minimum(part_hi, box_hi)
        # The half's extent along the cut axis ends at the plane.
        if k == 0:
            part_hi = Array3f64(*[dr.select(on, dr.minimum(c, plane), c)
                                  for on, c in zip((on_x, on_y, on_z), part_hi)])
        else:
            part_lo = Array3f64(*[dr.select(on, dr.maximum(c, plane), c)
                                  for on, c in zip((on_x, on_y, on_z), part_lo)])
        holds = Bool(cuttable & dr.all(part_lo <= part_hi))
        results += [part_lo, part_hi, holds]
    dr.eval(*results)
    return tuple(np.asarray(r, np.float64).T if isinstance(r, Array3f64) else np.asarray(r) for r in results)


def _next_pieces(pending, lo0, hi0, has0, lo1, hi1, has1):
    """The pieces after a halving (:func:`_halves`): each half that holds part of the triangle,
    the references still to make shared between the halves (all to one where the other is
    empty); a piece that could not be cut goes on whole, as one reference."""
    triangle, lo, hi, count = pending
    count0 = np.where(has1, (count + 1) // 2, count)
    count1 = np.where(has0, count - (count + 1) // 2, count)
    uncut = ~(has0 | has1)
    return (np.concatenate([triangle[has0], triangle[has1], triangle[uncut]]),
            np.concatenate([lo0[has0], lo1[has1], lo[uncut]]),
            np.concatenate([hi0[has0], hi1[has1], hi[uncut]]),
            np.concatenate([count0[has0], count1[has1], np.ones(int(uncut.sum()), np.int64)]))


def mesh_forest(corners: list[np.ndarray], leaf_size: int) -> tuple[BVHArrays, list[int], list[np.ndarray]]:
    """One BVH per mesh (corners (F, 3 corners, 3) of float32 values each), over its triangles
    or, where that tree's surface cost (:func:`~instancing.accel.bvh.tree_costs`) is lower,
    over its references (tried where the triangles that split hold MIN_SPLIT_SHARE of the
    triangles' box area or more). Both trees of a mesh are built in one forest and the cheaper
    kept; above SAMPLE_WINDOWS x SAMPLE_WINDOW triangles, the choice is made on a sample of the
    mesh (:func:`_sample`) and only the chosen tree built. Returns the forest, each mesh's root
    reference and, per mesh, the triangle at each leaf position of its run."""
    runs, candidate = [], []
    for v in corners:
        lo, hi = triangle_boxes(v)
        count = piece_counts(v, (lo, hi))
        whole = (np.arange(len(v)), lo, hi)
        boxes = box_area(lo, hi)
        if boxes[count > 1].sum() < MIN_SPLIT_SHARE * boxes.sum():
            runs.append(whole)
            candidate.append(False)
        elif len(v) > SAMPLE_WINDOWS * SAMPLE_WINDOW:
            runs.append(triangle_references(v, count) if _splitting_pays(_sample(v), leaf_size) else whole)
            candidate.append(False)
        else:
            runs += [whole, triangle_references(v, count)]
            candidate += [False, True]
    forest, roots, sizes, cost = _forest(runs, leaf_size)
    keep = ~np.array(candidate)
    for k in np.flatnonzero(candidate):
        # The references' tree (run k) against the same mesh's triangles' (run k - 1).
        keep[k - 1], keep[k] = cost[k] >= cost[k - 1], cost[k] < cost[k - 1]
    forest, roots = select_trees(forest, roots, sizes, keep)
    offsets = np.cumsum(sizes) - sizes
    triangles, start = [], 0
    for k in np.flatnonzero(keep):
        run = forest.order[start:start + sizes[k]] - offsets[k]
        triangles.append(runs[k][0][run])
        start += sizes[k]
    return forest, roots, triangles


def _splitting_pays(corners: np.ndarray, leaf_size: int) -> bool:
    """Whether the tree over the triangles' references costs less than the one over the
    triangles."""
    cost = _forest([_whole(corners), triangle_references(corners)], leaf_size)[3]
    return bool(cost[1] < cost[0])


#: A large mesh's choice between its triangles and its references is made on this many runs
#: of this many triangles, spread along the Morton curve of their centres (the surface costs'
#: ratio on such samples of a million slivers, 116 000 triangles of low-poly trees, 135 000 of
#: teapots and 113 000 of Mitsuba's sliver dome: 0.63 / 1.09 / 1.00 / 0.75, the whole meshes'
#: 0.51 / 1.12 / 1.01 / 0.69; 4 runs of 8 192 triangles 0.59 / 1.10 / 1.00 / 0.75).
SAMPLE_WINDOWS, SAMPLE_WINDOW = 4, 4096


def _sample(corners: np.ndarray) -> np.ndarray:
    """SAMPLE_WINDOWS runs of SAMPLE_WINDOW triangles of a mesh, evenly spaced along the Morton
    curve of the triangles' centres (each a compact patch of the surface)."""
    order = np.argsort(morton_codes(corners.mean(axis=1)), kind="stable")
    starts = np.linspace(0, len(corners) - SAMPLE_WINDOW, SAMPLE_WINDOWS).astype(np.int64)
    return corners[np.concatenate([order[s:s + SAMPLE_WINDOW] for s in starts])]


def _whole(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles as their own items: (index, box lo, box hi)."""
    return (np.arange(len(corners)), *triangle_boxes(corners))


def _forest(runs, leaf_size: int):
    """The forest of runs (items, box lo, box hi) each: (forest, root references, sizes, each
    tree's surface cost)."""
    sizes = [len(items) for items, _, _ in runs]
    forest, roots = build_forest(np.concatenate([r[1] for r in runs]), np.concatenate([r[2] for r in runs]),
                                 sizes, leaf_size)
    cost = tree_costs(forest, roots, sizes, [box_area(lo.min(axis=0), hi.max(axis=0)) for _, lo, hi in runs])
    return forest, roots, sizes, cost
