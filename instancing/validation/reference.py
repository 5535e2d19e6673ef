"""Independent float64 NumPy reference ray intersector.

This module is the ground truth against which the Dr.Jit (float32)
implementation of ``instancing`` is measured (by the test suite and the
``crosscheck`` command).  It deliberately shares no code with the rest of the
package: every formula is re-derived here, evaluated in float64 with
numerically careful expressions (stable quadratic roots, Newton polishing,
exact slab tests, inclusive barycentric bounds) and vectorised over rays.

Conventions (Mitsuba 3 canonical shapes, object space)
------------------------------------------------------
``sphere``     unit sphere at the origin; normal = hit point (outward).
``cube``       solid box [-1, 1]^3; normal = outward normal of the face hit.
``rectangle``  [-1, 1]^2 in the plane z = 0; normal +z from either side.
``disk``       unit disk in the plane z = 0; normal +z from either side.
``cylinder``   radius 1 around the z axis, 0 <= z <= 1, no caps;
               normal = (x, y, 0) (outward, also when hit from inside).
``mesh``       triangles (vertices (V,3), faces (F,3)); normal =
               normalize(cross(v1 - v0, v2 - v0)), never flipped; prim is
               the triangle index.
``linearcurve`` tubes along polylines: each segment the convex hull of the
               spheres at its two control points (radius per point; a joint's
               sphere belongs to the segment that ends there); seen only
               from outside (no hit on a segment whose hull holds the origin, nor
               where a neighbouring segment of the same curve holds both the
               origin and the hit); normal from the centre of the sphere that
               touches the tube at the hit; prim the segment index.
``bsplinecurve`` tubes along uniform cubic B-splines: segment s the spline of
               four consecutive control points (radius per point, interpolated
               alike); the surface the circles of radius r(v) about c(v) in the
               planes normal to c'(v), open at the ends; only hits whose
               normal ``(|c'|^2 - (p - c) . c'') (p - c) - r r' c'`` faces the
               ray; prim the segment index.
``sdfgrid``    the zero set of the trilinear interpolant of values (nz, ny, nx)
               at the corners of a regular grid over [0, 1]^3 (x fastest);
               normal = its normalized gradient in the voxel that holds the
               hit (floor of p times the voxel counts, clamped); prim 0.

For every shape the reported hit is the nearest one with ``t > 0`` along
``o + t d``; ``d`` need not be normalised and ``t`` is measured in units of
``d``.  Rays starting inside a closed shape report the exit hit.  Misses have
``t = inf``.  Rays parallel to a plane miss it.  ``prim`` is 0 for analytic
shapes.

Public API
----------
``intersect_object(kind, o, d, mesh=None, grid=None, curve=None) -> (t, n_obj, prim)``
``intersect_instances(instances, o, d) -> {"t", "p", "n", "instance", "prim"}``
"""

from __future__ import annotations

import numpy as np

__all__ = ["KINDS", "intersect_object", "intersect_instances", "transform_rays"]

KINDS = ("sphere", "cube", "rectangle", "disk", "cylinder", "mesh", "sdfgrid", "linearcurve",
         "bsplinecurve")

# Upper bound on (#rays x #triangles) handled at once by the mesh kernel, and on its rays:
# each temporary in the kernel is at most 3x this many float64 values, kept within cache.
_MESH_BLOCK_ELEMS = 1 << 16
_MESH_BLOCK_RAYS = 1 << 10
# Samples of an SDF grid's interpolant per ray between its entry into [0, 1]^3 and its exit,
# before the first sign change is bisected: two roots closer than a sample's spacing (a
# ray grazing the surface) are missed.
_GRID_SAMPLES = 4096
# Samples of a B-spline segment's parameter per ray before the sign changes of the circle
# equation are bisected (two crossings closer than a sample's spacing are missed), and rays
# per block.
_BSPLINE_SAMPLES = 512
_BSPLINE_BLOCK_RAYS = 256


# ---------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------

def _as_rays(o, d):
    """Return float64 (N,3) copies of o and d, broadcast against each other."""
    o = np.asarray(o, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    o, d = np.broadcast_arrays(np.atleast_2d(o), np.atleast_2d(d))
    if o.shape[-1] != 3 or o.ndim != 2:
        raise ValueError(f"rays must have shape (N, 3), got {o.shape}")
    return np.array(o), np.array(d)


def _normalize(v):
    """Row-wise normalisation; zero/nan rows stay nan (only used on hits)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def _stable_quadratic(f, dv):
    """Roots of |f + t dv|^2 = 1 with a cancellation-free formulation.

    Works for any dimension of the last axis (3 for the sphere, 2 for the
    infinite cylinder).  Returns (t_lo, t_hi, has_roots); the roots are nan
    where there are none.
    """
    # Coefficients of a t^2 - 2 b' t + c = 0.
    a = _dot(dv, dv)
    bp = -_dot(f, dv)
    c = _dot(f, f) - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        # Closest-approach point l = f + (b'/a) dv; |l|^2 is the squared
        # distance of the line from the centre.  disc = b'^2 - a c computed as
        # a (1 - |l|^2) avoids the catastrophic cancellation of b'^2 - a c.
        l = f + (bp / a)[..., None] * dv
        disc = a * (1.0 - _dot(l, l))
        has = (a > 0) & (disc >= 0)
        sq = np.sqrt(np.where(has, disc, np.nan))
        # q = b' + sign(b') sqrt(disc): no cancellation between the terms.
        sgn = np.where(bp >= 0, 1.0, -1.0)
        q = bp + sgn * sq
        # The two roots are q/a and c/q (Vieta).  q == 0 only for a double
        # root at t = 0 (tangent line through a surface point), where c/q is
        # 0/0 and q/a = 0 is the answer.
        r1 = q / a
        r2 = np.where(q != 0, c / q, r1)
        t_lo = np.minimum(r1, r2)
        t_hi = np.maximum(r1, r2)
    return t_lo, t_hi, has


def _newton_polish(f, dv, t, steps=2):
    """Refine roots of g(t) = |f + t dv|^2 - 1 by Newton steps in float64.

    A step is taken only where the derivative is not tiny compared with its
    natural scale (i.e. the ray is not grazing), so near-double roots are
    left untouched rather than thrown off.
    """
    t = t.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dn = np.sqrt(_dot(dv, dv))
        for _ in range(steps):
            p = f + t[..., None] * dv
            g = _dot(p, p) - 1.0              # residual
            gp = 2.0 * _dot(p, dv)             # derivative dg/dt
            ok = np.isfinite(t) & (np.abs(gp) > 1e-4 * dn * np.sqrt(_dot(p, p)))
            step = np.where(ok, g / np.where(ok, gp, 1.0), 0.0)
            # Guard: a polish step must be a tiny correction, never a jump.
            ok &= np.abs(step) <= 1e-6 * np.maximum(np.abs(t), 1e-300) + 1e-300
            t = np.where(ok, t - step, t)
    return t


# ---------------------------------------------------------------------------
# Canonical shapes (object space)
# ---------------------------------------------------------------------------

def _sphere(o, d):
    t_lo, t_hi, has = _stable_quadratic(o, d)
    # Polish both roots, then keep the smallest positive one.
    t_lo = _newton_polish(o, d, t_lo)
    t_hi = _newton_polish(o, d, t_hi)
    t = np.where(has & (t_lo > 0), t_lo, np.where(has & (t_hi > 0), t_hi, np.inf))
    hit = np.isfinite(t)
    # Normal = hit point (radius 1), normalised to absorb rounding.
    with np.errstate(invalid="ignore"):
        n = _normalize(o + np.where(hit, t, 0.0)[:, None] * d)
    n[~hit] = np.nan
    return t, n


def _cylinder(o, d):
    f, dv = o[:, :2], d[:, :2]
    t_lo, t_hi, has = _stable_quadratic(f, dv)
    t_lo = _newton_polish(f, dv, t_lo)
    t_hi = _newton_polish(f, dv, t_hi)
    with np.errstate(invalid="ignore", over="ignore"):
        # z-range check 0 <= z <= 1 (inclusive) for each candidate root.
        z_lo = o[:, 2] + t_lo * d[:, 2]
        z_hi = o[:, 2] + t_hi * d[:, 2]
        ok_lo = has & (t_lo > 0) & (z_lo >= 0) & (z_lo <= 1)
        ok_hi = has & (t_hi > 0) & (z_hi >= 0) & (z_hi <= 1)
    # Nearest valid root (the far one is used from inside or when the near
    # one falls outside the z range).
    t = np.where(ok_lo, t_lo, np.where(ok_hi, t_hi, np.inf))
    hit = np.isfinite(t)
    # Normal = radial direction (x, y, 0) at the hit, outward in all cases.
    ts = np.where(hit, t, 0.0)
    n = np.zeros_like(o)
    n[:, :2] = f + ts[:, None] * dv
    n = _normalize(n)
    n[~hit] = np.nan
    return t, n


def _planar(o, d, inside):
    """Plane z = 0 hit, filtered by inside(x, y)."""
    dz = d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Parallel rays (dz == 0) never hit, even when lying in the plane.
        t = np.where(dz != 0, -o[:, 2] / np.where(dz != 0, dz, 1.0), np.inf)
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        hit = (dz != 0) & (t > 0) & inside(x, y)
    t = np.where(hit, t, np.inf)
    n = np.zeros_like(o)
    n[:, 2] = 1.0                              # +z from either side
    n[~hit] = np.nan
    return t, n


def _rectangle(o, d):
    return _planar(o, d, lambda x, y: (np.abs(x) <= 1) & (np.abs(y) <= 1))


def _disk(o, d):
    return _planar(o, d, lambda x, y: x * x + y * y <= 1)


def _cube(o, d):
    n_rays = o.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Slab method: per-axis parameter interval where |o_i + t d_i| <= 1.
        nz = d != 0
        dd = np.where(nz, d, 1.0)
        ta = (-1.0 - o) / dd
        tb = (1.0 - o) / dd
        t_in = np.where(nz, np.minimum(ta, tb), -np.inf)
        t_out = np.where(nz, np.maximum(ta, tb), np.inf)
        # Axis-parallel component: inside the slab -> whole line, else empty.
        outside_slab = ~nz & (np.abs(o) > 1)
        t_in = np.where(outside_slab, np.inf, t_in)
        t_out = np.where(outside_slab, -np.inf, t_out)
    # Interval intersection across the three slabs; ties -> lowest axis.
    ax_in = np.argmax(t_in, axis=1)
    ax_out = np.argmin(t_out, axis=1)
    rows = np.arange(n_rays)
    tn = t_in[rows, ax_in]
    tf = t_out[rows, ax_out]
    # Non-empty interval reaching t > 0 (tf is inf only for d == 0).
    valid = (tn <= tf) & (tf > 0) & np.isfinite(tf)
    # Entering face if it lies ahead of the origin, else the exit face.
    enter = valid & (tn > 0)
    t = np.where(enter, tn, np.where(valid, tf, np.inf))
    axis = np.where(enter, ax_in, ax_out)
    daxis = d[rows, axis]
    # Entering face normal opposes d; exit face normal goes along d.
    sign = np.where(enter, -np.sign(daxis), np.sign(daxis))
    n = np.zeros_like(o)
    n[rows, axis] = sign
    n[~valid] = np.nan
    return t, n


def _mesh(o, d, mesh):
    verts = np.asarray(mesh[0], dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(mesh[1], dtype=np.int64).reshape(-1, 3)
    n_rays, n_tri = o.shape[0], faces.shape[0]
    v0 = verts[faces[:, 0]]
    e1 = verts[faces[:, 1]] - v0
    e2 = verts[faces[:, 2]] - v0
    best_t = np.full(n_rays, np.inf)
    best_prim = np.full(n_rays, -1, dtype=np.int64)
    rows = min(n_rays, _MESH_BLOCK_RAYS)
    block = max(1, _MESH_BLOCK_ELEMS // max(rows, 1))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for r in range(0, n_rays, rows):
            ray = slice(r, min(r + rows, n_rays))
            D, O = d[ray, None, :], o[ray, None, :]
            for s in range(0, n_tri, block):
                sl = slice(s, min(s + block, n_tri))
                E1, E2, V0 = e1[None, sl], e2[None, sl], v0[None, sl]
                # Möller–Trumbore: pvec = d x e2, det = e1 . pvec.
                pvec = np.cross(D, E2)
                det = _dot(E1, pvec)
                inv_det = 1.0 / det
                # First barycentric u = (o - v0) . pvec / det.
                tvec = O - V0
                u = _dot(tvec, pvec) * inv_det
                # Second barycentric v = d . (tvec x e1) / det.
                qvec = np.cross(tvec, E1)
                v = _dot(D, qvec) * inv_det
                # Ray parameter t = e2 . qvec / det.
                t = _dot(E2, qvec) * inv_det
                # Exact inclusive barycentric bounds, strictly positive t.
                hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
                t = np.where(hit, t, np.inf)
                # Nearest triangle in this block (ties -> lowest index) ...
                j = np.argmin(t, axis=1)
                tj = t[np.arange(t.shape[0]), j]
                # ... replaces the running best only if strictly nearer.
                upd = tj < best_t[ray]
                best_t[ray] = np.where(upd, tj, best_t[ray])
                best_prim[ray] = np.where(upd, j + s, best_prim[ray])
    hit = np.isfinite(best_t)
    # Geometric normal of the hit triangle, never flipped toward the ray.
    n = np.full((n_rays, 3), np.nan)
    if hit.any():
        p = best_prim[hit]
        n[hit] = _normalize(np.cross(e1[p], e2[p]))
    return best_t, n, best_prim


def _trilinear(values, p):
    """The interpolant of ``values`` (nz, ny, nx) at points ``p`` (..., 3) of [0, 1]^3, and its
    gradient there, each in the voxel floor(p * counts) clamped into the grid."""
    counts = np.array(values.shape[::-1]) - 1
    scaled = p * counts
    cell = np.clip(np.floor(scaled), 0, counts - 1).astype(np.int64)
    w = scaled - cell
    x0, y0, z0 = cell[..., 0], cell[..., 1], cell[..., 2]
    corner = {(i, j, k): values[z0 + k, y0 + j, x0 + i] for i in (0, 1) for j in (0, 1) for k in (0, 1)}
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]

    def lerp(a, b, t):
        return a + t * (b - a)
    x00, x10 = lerp(corner[0, 0, 0], corner[1, 0, 0], wx), lerp(corner[0, 1, 0], corner[1, 1, 0], wx)
    x01, x11 = lerp(corner[0, 0, 1], corner[1, 0, 1], wx), lerp(corner[0, 1, 1], corner[1, 1, 1], wx)
    value = lerp(lerp(x00, x10, wy), lerp(x01, x11, wy), wz)
    dx = lerp(lerp(corner[1, 0, 0] - corner[0, 0, 0], corner[1, 1, 0] - corner[0, 1, 0], wy),
              lerp(corner[1, 0, 1] - corner[0, 0, 1], corner[1, 1, 1] - corner[0, 1, 1], wy), wz)
    dy = lerp(lerp(corner[0, 1, 0] - corner[0, 0, 0], corner[1, 1, 0] - corner[1, 0, 0], wx),
              lerp(corner[0, 1, 1] - corner[0, 0, 1], corner[1, 1, 1] - corner[1, 0, 1], wx), wz)
    dz = lerp(lerp(corner[0, 0, 1] - corner[0, 0, 0], corner[1, 0, 1] - corner[1, 0, 0], wx),
              lerp(corner[0, 1, 1] - corner[0, 1, 0], corner[1, 1, 1] - corner[1, 1, 0], wx), wy)
    return value, np.stack([dx, dy, dz], axis=-1) * counts


def _sdf_grid(o, d, values, block=256):
    """First zero of the interpolant along each ray: sampled densely inside [0, 1]^3, the
    first sign change bisected to float64 precision."""
    values = np.asarray(values, np.float64)
    n_rays = o.shape[0]
    best_t = np.full(n_rays, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0, t1 = (0.0 - o) * inv, (1.0 - o) * inv
        t_in = np.maximum(np.nanmax(np.minimum(t0, t1), axis=1), 0.0)
        t_out = np.nanmin(np.maximum(t0, t1), axis=1)
    steps = np.linspace(0.0, 1.0, _GRID_SAMPLES)
    for s in range(0, n_rays, block):
        rows = np.arange(s, min(s + block, n_rays))
        rows = rows[t_in[rows] < t_out[rows]]
        if not len(rows):
            continue
        ts = t_in[rows, None] + (t_out - t_in)[rows, None] * steps
        f = _trilinear(values, np.clip(o[rows, None] + ts[..., None] * d[rows, None], 0.0, 1.0))[0]
        change = (f[:, :-1] * f[:, 1:] <= 0) & (ts[:, 1:] > 0)
        found = change.any(axis=1)
        k = np.argmax(change, axis=1)
        lo, hi = ts[np.arange(len(rows)), k], ts[np.arange(len(rows)), k + 1]
        f_lo = f[np.arange(len(rows)), k]
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            f_mid = _trilinear(values, np.clip(o[rows] + mid[:, None] * d[rows], 0.0, 1.0))[0]
            same = f_mid * f_lo > 0
            lo, f_lo = np.where(same, mid, lo), np.where(same, f_mid, f_lo)
            hi = np.where(same, hi, mid)
        best_t[rows[found]] = np.where(f_lo[found] == 0, lo[found], 0.5 * (lo + hi)[found])
    hit = np.isfinite(best_t)
    n = np.full((n_rays, 3), np.nan)
    if hit.any():
        p = np.clip(o[hit] + best_t[hit, None] * d[hit], 0.0, 1.0)
        n[hit] = _normalize(_trilinear(values, p)[1])
    return best_t, n, np.where(hit, 0, -1).astype(np.int64)


def _hull_parts(p0, r0, p1, r1):
    """Unit axis, length, slope k = (r1 - r0) / L and whether the segment's tangent cone
    exists (else its hull is its larger sphere)."""
    length = float(np.linalg.norm(p1 - p0))
    if length <= abs(r1 - r0):
        return None
    return (p1 - p0) / length, length, (r1 - r0) / length


def _inside_hull(x, p0, r0, p1, r1):
    """Whether points x lie inside the hull of the spheres (p0, r0) and (p1, r1)."""
    inside = (np.linalg.norm(x - p0, axis=1) < r0) | (np.linalg.norm(x - p1, axis=1) < r1)
    cone = _hull_parts(p0, r0, p1, r1)
    if cone is not None:
        axis, length, k = cone
        z = (x - p0) @ axis
        rho = np.linalg.norm(x - p0 - z[:, None] * axis, axis=1)
        inside |= (z >= -r0 * k) & (z <= length - r1 * k) & (rho * np.sqrt(1 - k * k) < r0 + k * z)
    return inside


def _sphere_entry(o, d, c, r):
    """Entry t > 0 into a sphere from outside it (inf otherwise)."""
    oc = o - c
    a, b, cc = _dot(d, d), _dot(oc, d), _dot(oc, oc) - r * r
    disc = b * b - a * cc
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc >= 0) & (cc > 0) & (t > 0), t, np.inf)


def _cone_entry(o, d, p0, r0, p1, r1):
    """Entry t > 0 through the tangent cone's surface between its tangency circles."""
    cone = _hull_parts(p0, r0, p1, r1)
    if cone is None:
        return np.full(len(o), np.inf)
    axis, length, k = cone
    q, s2 = o - p0, 1.0 - k * k
    qa, da = q @ axis, d @ axis
    a = (_dot(d, d) - da * da) * s2 - (k * da) ** 2
    b = 2.0 * ((_dot(q, d) - qa * da) * s2 - (r0 + k * qa) * k * da)
    c = (_dot(q, q) - qa * qa) * s2 - (r0 + k * qa) ** 2
    disc = b * b - 4 * a * c
    best = np.full(len(o), np.inf)
    for t in ((-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), (-b + np.sqrt(np.maximum(disc, 0))) / (2 * a)):
        x = q + t[:, None] * d
        z = x @ axis
        w = r0 + k * z
        entering = _dot((x - z[:, None] * axis) * s2 - (w * k)[:, None] * axis, d) < 0
        ok = (disc >= 0) & (t > 0) & (w >= 0) & (z >= -r0 * k) & (z <= length - r1 * k) & entering
        best = np.where(ok & (t < best), t, best)
    return best


def _linear_curve(o, d, curve):
    """Nearest entry into the segments' hulls (module docstring)."""
    points, radii, first, left, right = curve
    n_rays = o.shape[0]
    best_t, best_prim = np.full(n_rays, np.inf), np.full(n_rays, -1, dtype=np.int64)
    best_n = np.full((n_rays, 3), np.nan)

    def segment(s):
        return points[first[s]], radii[first[s]], points[first[s] + 1], radii[first[s] + 1]

    with np.errstate(divide="ignore", invalid="ignore"):
        for s in range(len(first)):
            p0, r0, p1, r1 = segment(s)
            # A joint's sphere is the segment's that ends there.
            start = np.full(len(o), np.inf) if left[s] else _sphere_entry(o, d, p0, r0)
            t = np.minimum(np.minimum(start, _sphere_entry(o, d, p1, r1)), _cone_entry(o, d, p0, r0, p1, r1))
            t = np.where(_inside_hull(o, p0, r0, p1, r1), np.inf, t)
            x = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
            for other, exists in ((s - 1, left[s]), (s + 1, right[s])):
                if exists:
                    hull = segment(other)
                    t = np.where(_inside_hull(o, *hull) & _inside_hull(x, *hull), np.inf, t)
            upd = t < best_t
            if not upd.any():
                continue
            # The centre of the sphere touching the hull at the hit: on the cone, the one
            # whose tangency circle holds it (axial coordinate z = s - r(s) k, solved for s);
            # beyond either circle, the end's (s clipped to the segment).
            x = o[upd] + t[upd, None] * d[upd]
            cone = _hull_parts(p0, r0, p1, r1)
            if cone is None:
                centre = np.where((r0 >= r1), p0, p1)[None].repeat(upd.sum(), 0)
            else:
                axis, length, k = cone
                v = np.clip(((x - p0) @ axis + r0 * k) / (1 - k * k) / length, 0.0, 1.0)
                centre = p0 + v[:, None] * (p1 - p0)
            best_t[upd], best_prim[upd], best_n[upd] = t[upd], s, _normalize(x - centre)
    return best_t, best_n, best_prim


def _bspline_basis(v):
    """The uniform cubic B-spline weights of v (..., 4) and their first and second
    derivatives."""
    v2, v3 = v * v, v * v * v
    weights = np.stack([1 - 3 * v + 3 * v2 - v3, 4 - 6 * v2 + 3 * v3, 1 + 3 * v + 3 * v2 - 3 * v3, v3], -1)
    first = np.stack([-3 + 6 * v - 3 * v2, -12 * v + 9 * v2, 3 + 6 * v - 9 * v2, 3 * v2], -1)
    second = np.stack([6 - 6 * v, -12 + 18 * v, 6 - 18 * v, 6 * v], -1)
    return weights / 6, first / 6, second / 6


def _bspline_segment(o, d, control):
    """Nearest front-facing crossing of rays (B, 3) with one segment's tube (control (4, 4)
    rows x, y, z, r): (t, unit normal), t inf where none."""
    def at(v):
        w, w1, w2 = _bspline_basis(v)
        return w @ control, w1 @ control, w2 @ control

    def circle(v, o, d):
        # The ray's crossing of the circle's plane, times d . a (a polynomial in v), against
        # the circle: its squared distance from the centre minus r^2, times (d . a)^2.
        c, a, _ = at(v)
        w = c[..., :3] - o
        da = (d * a[..., :3]).sum(-1)
        q = (w * a[..., :3]).sum(-1)[..., None] * d - da[..., None] * w
        return (q * q).sum(-1) - (c[..., 3] * da) ** 2

    grid = np.linspace(0.0, 1.0, _BSPLINE_SAMPLES)
    values = circle(grid[None, :], o[:, None], d[:, None])
    ray, k = np.nonzero(np.sign(values[:, :-1]) != np.sign(values[:, 1:]))
    lo, hi, sign_lo = grid[k], grid[k + 1], np.sign(values[ray, k])
    # A dip below zero narrower than the grid's spacing (a ray nearly normal to the tangent,
    # whose two crossings of one circle lie at nearly the same v): the positive local minima
    # of the samples, refined by golden-section search, bracketed where negative.
    m_ray, m = np.nonzero((values[:, 1:-1] > 0) & (values[:, 1:-1] <= values[:, :-2])
                          & (values[:, 1:-1] <= values[:, 2:]))
    a, b = grid[m], grid[m + 2]
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        x1, x2 = b - golden * (b - a), a + golden * (b - a)
        left = circle(x1, o[m_ray], d[m_ray]) < circle(x2, o[m_ray], d[m_ray])
        a, b = np.where(left, a, x1), np.where(left, x2, b)
    dip = 0.5 * (a + b)
    deep = circle(dip, o[m_ray], d[m_ray]) < 0
    m_ray, m, dip = m_ray[deep], m[deep], dip[deep]
    ray = np.concatenate([ray, m_ray, m_ray])
    lo = np.concatenate([lo, grid[m], dip])
    hi = np.concatenate([hi, dip, grid[m + 2]])
    sign_lo = np.concatenate([sign_lo, np.ones(len(m)), -np.ones(len(m))])
    o_r, d_r = o[ray], d[ray]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        same = np.sign(circle(mid, o_r, d_r)) == sign_lo
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    c, a, b = at(0.5 * (lo + hi))
    t = ((c[:, :3] - o_r) * a[:, :3]).sum(1) / (d_r * a[:, :3]).sum(1)
    q = o_r + t[:, None] * d_r - c[:, :3]
    n = (((a[:, :3] ** 2).sum(1) - (q * b[:, :3]).sum(1))[:, None] * q
         - (c[:, 3] * a[:, 3])[:, None] * a[:, :3])
    ok = (t > 0) & ((n * d_r).sum(1) < 0)
    best_t, best_n = np.full(len(o), np.inf), np.full((len(o), 3), np.nan)
    ray, t, n = ray[ok], t[ok], n[ok]
    order = np.lexsort((t, ray))
    first = order[np.unique(ray[order], return_index=True)[1]]
    best_t[ray[first]], best_n[ray[first]] = t[first], _normalize(n[first])
    return best_t, best_n


def _bspline_curve(o, d, curve):
    """Nearest front-facing hit on the segments' tubes (module docstring), by the sign
    changes of the circle equation on a grid of each segment's parameter, bisected."""
    points, radii, first = curve
    rows = np.concatenate([points, radii[:, None]], axis=1)
    best_t, best_n = np.full(len(o), np.inf), np.full((len(o), 3), np.nan)
    best_prim = np.full(len(o), -1, dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for start in range(0, len(o), _BSPLINE_BLOCK_RAYS):
            block = slice(start, start + _BSPLINE_BLOCK_RAYS)
            for s, f in enumerate(first):
                t, n = _bspline_segment(o[block], d[block], rows[f:f + 4])
                upd = t < best_t[block]
                best_t[block][upd], best_n[block][upd], best_prim[block][upd] = t[upd], n[upd], s
    return best_t, best_n, best_prim


def intersect_object(kind, o, d, mesh=None, grid=None, curve=None):
    """Intersect object-space rays with a canonical shape, in float64.

    Parameters
    ----------
    kind : one of ``KINDS``.
    o, d : (N, 3) ray origins and directions (d need not be unit length).
    mesh : ``(vertices (V,3), faces (F,3))`` when ``kind == "mesh"``.
    grid : the values (nz, ny, nx) when ``kind == "sdfgrid"``.
    curve : (points (K, 3), radii (K,), first (S,), left (S,), right (S,)) when ``kind ==
           "linearcurve"``: segment s joins points first[s] and first[s] + 1; left / right
           whether its neighbours belong to the same curve. (points, radii, first) when
           ``kind == "bsplinecurve"``: segment s is the spline of points first[s] .. first[s] + 3.

    Returns
    -------
    t : (N,) float64, nearest hit parameter with t > 0 in units of d, inf on miss.
    n_obj : (N, 3) float64 unit object-space normal (nan rows on miss).
    prim : (N,) int64, triangle index for meshes, 0 otherwise (-1 on miss).
    """
    o, d = _as_rays(o, d)
    if kind == "mesh":
        if mesh is None:
            raise ValueError("kind='mesh' requires mesh=(vertices, faces)")
        return _mesh(o, d, mesh)
    if kind == "linearcurve":
        if curve is None:
            raise ValueError("kind='linearcurve' requires curve=(points, radii, first, left, right)")
        return _linear_curve(o, d, curve)
    if kind == "bsplinecurve":
        if curve is None:
            raise ValueError("kind='bsplinecurve' requires curve=(points, radii, first)")
        return _bspline_curve(o, d, curve)
    if kind == "sdfgrid":
        if grid is None:
            raise ValueError("kind='sdfgrid' requires grid=values")
        return _sdf_grid(o, d, grid)
    funcs = {"sphere": _sphere, "cube": _cube, "rectangle": _rectangle,
             "disk": _disk, "cylinder": _cylinder}
    if kind not in funcs:
        raise ValueError(f"unknown shape kind {kind!r}; expected one of {KINDS}")
    t, n = funcs[kind](o, d)
    prim = np.where(np.isfinite(t), 0, -1).astype(np.int64)
    return t, n, prim


# ---------------------------------------------------------------------------
# Instances (world space)
# ---------------------------------------------------------------------------

def _affine_inverse(m):
    """Inverse of an affine 4x4 matrix in float64 (linear part via LAPACK)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"to_world must be 4x4, got {m.shape}")
    if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("to_world must be affine (last row [0, 0, 0, 1])")
    a_inv = np.linalg.inv(m[:3, :3])
    inv = np.eye(4)
    inv[:3, :3] = a_inv
    inv[:3, 3] = -a_inv @ m[:3, 3]
    return inv


def transform_rays(to_world, o, d):
    """World rays -> object rays of an instance (d is NOT renormalised).

    Returns (o_obj, d_obj, inv) where inv is the float64 inverse of to_world.
    """
    o, d = _as_rays(o, d)
    inv = _affine_inverse(to_world)
    o_obj = o @ inv[:3, :3].T + inv[:3, 3]     # inv @ [o, 1]
    d_obj = d @ inv[:3, :3].T                  # inv @ [d, 0]
    return o_obj, d_obj, inv


def instance_list(kinds, matrices, meshes, rounding=np.float64, vertex_rounding=None, grids=None,
                  curves=None):
    """Instances for :func:`intersect_instances`, transforms and mesh vertices first rounded
    to ``rounding`` (np.float32: the scene as the renderers store it; np.float64: as given);
    the vertices to ``vertex_rounding`` where it is given.

    kinds    : model kind per instance ("mesh" for triangle meshes).
    matrices : (4, 4) to-world matrix per instance.
    meshes   : (vertices, faces) per instance (None for analytic kinds), or one
               (vertices, faces) shared by every "mesh" instance.
    grids    : an "sdfgrid" instance's values per instance (None for the others).
    curves   : a "linearcurve" or "bsplinecurve" instance's curve per instance (None for the
               others; see :func:`intersect_object`).
    """
    per_instance = meshes if isinstance(meshes, list) else [meshes] * len(kinds)
    grids = grids if grids is not None else [None] * len(kinds)
    curves = curves if curves is not None else [None] * len(kinds)
    rounded = {}  # id(vertices) -> (rounded vertices, faces): each mesh rounded once

    def rounded_mesh(mesh):
        if id(mesh[0]) not in rounded:
            rounded[id(mesh[0])] = (np.asarray(mesh[0]).astype(vertex_rounding or rounding)
                                    .astype(np.float64), mesh[1])
        return rounded[id(mesh[0])]

    return [{"kind": kind, "to_world": np.asarray(m).astype(rounding).astype(np.float64),
             "mesh": rounded_mesh(mesh) if kind == "mesh" else None, "grid": grid, "curve": curve}
            for kind, m, mesh, grid, curve in zip(kinds, matrices, per_instance, grids, curves)]


def intersect_instances(instances, o, d):
    """Brute-force nearest hit over all instances, in float64.

    instances : list of dicts ``{"kind": str, "to_world": (4,4) array,
                "mesh": (vertices, faces) or None}``.
    o, d      : (N, 3) world-space rays.

    Returns a dict with
      ``t``        (N,) nearest t > 0 in units of d (inf on miss),
      ``p``        (N, 3) o + t d (nan rows on miss),
      ``n``        (N, 3) unit world normal = normalize(inv[:3,:3].T @ n_obj)
                   (nan rows on miss),
      ``instance`` (N,) int64 instance index (-1 on miss),
      ``prim``     (N,) int64 primitive index (-1 on miss).
    Ties in t go to the lowest instance index.
    """
    o, d = _as_rays(o, d)
    n_rays = o.shape[0]
    best_t = np.full(n_rays, np.inf)
    best_n = np.full((n_rays, 3), np.nan)
    best_inst = np.full(n_rays, -1, dtype=np.int64)
    best_prim = np.full(n_rays, -1, dtype=np.int64)
    for k, inst in enumerate(instances):
        # World -> object: same t in both spaces since d is not renormalised.
        o_obj, d_obj, inv = transform_rays(inst["to_world"], o, d)
        t, n_obj, prim = intersect_object(inst["kind"], o_obj, d_obj,
                                          mesh=inst.get("mesh"), grid=inst.get("grid"),
                                          curve=inst.get("curve"))
        # Keep the strictly nearer hit.
        upd = t < best_t
        if not upd.any():
            continue
        # Normals transform with the inverse transpose of the linear part.
        n_world = _normalize(n_obj[upd] @ inv[:3, :3])
        best_t[upd] = t[upd]
        best_n[upd] = n_world
        best_inst[upd] = k
        best_prim[upd] = prim[upd]
    hit = np.isfinite(best_t)
    p = np.full((n_rays, 3), np.nan)
    p[hit] = o[hit] + best_t[hit, None] * d[hit]
    return {"t": best_t, "p": p, "n": best_n, "instance": best_inst,
            "prim": best_prim}
