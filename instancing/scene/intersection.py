"""Two-phase ray intersection with instanced models.

Phase 1 (preliminary, detached from AD): the acceleration structure walks
the candidate instances; each candidate's ray is transformed into object
space with the instance's inverse and tested against the untransformed
model. The discrete answer is (t, instance, primitive).

Phase 2 (re-intersection, AD attached): only the winning instance is tested
again, with the inverse matrix gathered from the (possibly differentiable)
per-instance arrays. The hit point is computed in object space by the model
(re-projected onto its surface, barycentric on triangles) and mapped to world
space by the forward matrix with the translation added last; it still lies
on the world ray ``o + t d`` up to rounding, and carries a componentwise
error bound (pbrt-v4) from which spawned rays are offset
(:mod:`instancing.core.error_bounds`, :mod:`instancing.core.ray_offset`). The object-space
normal is mapped by the inverse transpose and normalized. Derivatives of t,
p and n with respect to transform parameters are exact on surface
interiors; gradients never flow through traversal loops.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..accel.grid import ENTRY_KEY_BITS, GridKernel, WalkState
from ..accel.ray_order import counting_sort_order, gather_rays, scatter_back
from ..core.backend import (Array2f, Array2f64, Array3f, Array3f64, Array4f, Array4f64, Bool, Float, Float64,
                            Int32, Matrix3f64, UInt32, dr)
from ..core.box import ray_box, within
from ..core.error_bounds import gamma, transformed_point_error
from ..core.transform import object_ray, world_normal, world_point, world_vector
from ..core.warp import frame, shading_tangent
from ..models.analytic import ANALYTIC_MODELS
from .instance_table import BSPLINE_KIND, CURVE_KIND, GRID_KIND, MESH_KIND, InstanceTable

#: Instance index reported for rays that hit nothing.
MISS = 0xFFFFFFFF


@dataclass(frozen=True)
class PreliminaryHit:
    """Result of traversal: distance, instance and leaf-order primitive (detached)."""

    t: Float
    instance: UInt32
    position: UInt32

    @property
    def valid(self) -> Bool:
        return self.instance != MISS


@dataclass(frozen=True)
class SurfaceHit:
    """Full, differentiable surface record of the nearest hit.

    Attributes:
        t: ray parameter in units of the ray direction (inf on a miss).
        p: world hit point, on the ray ``o + t d`` up to rounding (0 on a miss).
        n: unit world geometric normal, outward as the model defines it (0 on a miss).
        sn: unit world shading normal: ``n`` but on smooth meshes, where it is the
            corner normals interpolated (as Mitsuba's ``sh_frame.n``); it only shades,
            hits and ray offsets use ``n`` (0 on a miss).
        ss: unit world shading tangent, the first axis of the shading frame around ``sn``
            (Mitsuba's ``sh_frame.s``, from the surface's dp/du: it orients anisotropic
            BSDFs) where some material of the scene is anisotropic, else the first
            tangent of :func:`~instancing.core.warp.frame` of ``sn`` (0 on a miss).
        error: componentwise bound of p's distance from the surface as rays see it
            (0 on a miss; see :mod:`instancing.core.error_bounds`).
        instance: index into the scene's instance list (-1 on a miss).
        prim: triangle index in the mesh file for meshes, 0 for analytic models (-1 on a miss).
        uv: Mitsuba's surface coordinates of the hit (each shape's own parameterisation, a
            mesh's texture coordinates or else its barycentrics), where the scene's
            materials read textures; 0 otherwise (not computed) and on a miss.
        dpdu, dpdv: world derivatives of the hit point by u and v (Mitsuba's, with their
            lengths), where some material is bump-mapped; 0 otherwise and on a miss.
        prim_uv: the barycentrics (b1, b2) of a mesh hit on its triangle (Mitsuba's
            ``prim_uv``), where some material reads mesh attributes; 0 otherwise, on
            analytic models and on a miss.
        triangle: the hit triangle's position in the scene's mesh library (what mesh
            attributes are looked up by), where some material reads them; 0 otherwise.
        valid: lanes that hit something.
    """

    t: Float
    p: Array3f
    n: Array3f
    sn: Array3f
    ss: Array3f
    error: Array3f
    instance: Int32
    prim: Int32
    uv: Array2f
    dpdu: Array3f
    dpdv: Array3f
    prim_uv: Array2f
    triangle: UInt32
    valid: Bool


#: A traversal: (o, d, active, state, t_of, test_item) -> state, as BVHKernel/GridKernel.traverse.
Traversal = Callable


class WorldBoxes:
    """A few instances with their world boxes and inverse rows, tested in code unrolled
    at trace time (see :func:`_unrolled`).

    Each box coordinate and each entry of the rows of an instance tested on its own (the
    table's float32 inverse rows, as a walk gathers them; instances tested in rounds
    gather theirs per lane, see :func:`_rounds`) is an opaque float32 scalar: a kernel loads
    it once per packet (no per-lane gather), and the kernel stays the same when the
    instances move (a move builds new boxes). Read from one flat array at trace-time
    indices instead, the boxes were scalar loads in plain kernels but 16-lane gathers
    inside a ``dr.freeze`` recording (Dr.Jit 1.5; measured: 90 of the 130 gathers of
    light_area's recorded ``direct`` kernel, which ran 2.1x slower than the plain one);
    and the rows, gathered per lane at a literal index, were three 16-lane packet
    gathers per instance a packet tests (2^20 random rays through 10 spheres /
    rectangles / cubes, full record 1.26x / 1.32x / 1.39x slower than with opaque rows).

    Args:
        instances: the K instance indices.
        lo, hi: (K, 3) float32 corners of their boxes, rounded outward.
        table: the scene's instance table, whose stored rows of these instances are read.
    """

    def __init__(self, instances: list[int], lo: np.ndarray, hi: np.ndarray, table: InstanceTable):
        self.instances = [int(i) for i in instances]
        corners = np.concatenate([lo, hi], axis=1).astype(np.float32)  # (K, 6)
        self.corners = [[dr.opaque(Float, float(v)) for v in box] for box in corners]
        # Which instances are tested on their own and which in rounds, by slot.
        self.singles, self.rounds = _unrolled_order(table, self.instances)
        self.inverse_rows = {slot: tuple(Array4f(*[dr.opaque(Float, float(v)) for v in row])
                                         for row in rows.reshape(3, 4))
                             for slot, rows in zip(self.singles, table.inverse_rows_of(
                                 [self.instances[slot] for slot in self.singles]))}

    def box(self, slot: int) -> tuple[Array3f, Array3f]:
        """(lo, hi) of box ``slot``."""
        c = self.corners[slot]
        return Array3f(*c[:3]), Array3f(*c[3:])


def intersect_preliminary(table: InstanceTable, traverse: Traversal | None, items: UInt32 | None,
                          o: Array3f, d: Array3f, active: Bool | bool = True,
                          t_max: Float | float = dr.inf, any_hit: bool = False,
                          unrolled: WorldBoxes | None = None) -> PreliminaryHit:
    """Phase 1: nearest hit over all instances, detached from AD.

    Args:
        table: the scene's instances.
        traverse: the acceleration structure's traversal, or None for brute
            force over ``items``.
        items: instance indices that the structure's leaves point into (None
            for brute force, which visits the instances by index).
        o, d: world rays (Array3f); d need not be unit length.
        active: lanes to trace.
        t_max: only hits with t < t_max count (shadow rays).
        any_hit: stop at the first hit found instead of the nearest (shadow rays: the
            result is that hit, not necessarily the nearest).
        unrolled: a few instances with their world boxes, to test them in a loop
            unrolled at trace time instead of ``traverse`` (see :func:`_unrolled`),
            ignoring all others: every instance of a small scene, or a subset (the
            area emitters, see :mod:`instancing.rendering.integrators.direct`).
    """
    with dr.suspend_grad():
        o, d = dr.detach(o), dr.detach(d)
        state = (Float(t_max) + dr.zeros(Float, dr.width(o)), UInt32(MISS), UInt32(0))
        test_item = _item_test(table, items, o, d, any_hit)
        if unrolled is not None:
            return _unrolled(table, unrolled, o, d, Bool(active), state, any_hit)
        if traverse is None:
            t, instance, position = _brute_force(table.count, Bool(active), state, test_item)
        else:
            t, instance, position = traverse(o, d, Bool(active), state, lambda s: s[0], test_item)
    return PreliminaryHit(dr.abs(t) if any_hit else t, instance, position)


#: Fewest instances of an analytic kind tested in rounds rather than one after the other
#: in an unrolled scene: the crossover on random rays (docs/how-it-works.md).
ROUNDS_MIN_INSTANCES = 5

#: Loop iterations per pass of :func:`intersect_preliminary_in_passes`: the fastest of 8 -
#: 32 at 1 000 and 100 000 instances (benchmarks/intersect.py; docs/how-it-works.md).
PASS_STEPS = 16


def intersect_preliminary_in_passes(table: InstanceTable, grid: GridKernel, o: Array3f,
                                    d: Array3f, pass_steps: int = PASS_STEPS,
                                    sort_rays: bool = False) -> PreliminaryHit:
    """Phase 1 through the grid for a large batch of rays, in passes (wavefront tracing).

    A SIMD packet's loop runs until its slowest ray is done, so where ray lengths vary
    (incoherent rays: most hit within a few cells, some cross the whole grid) most
    lanes idle. Here each pass runs the walks for at most ``pass_steps`` loop
    iterations; the rays still walking are then packed densely (``dr.compress``) and
    go on in the next pass from their saved walk state, until none is left (Laine,
    Karras and Aila, "Megakernels Considered Harmful", 2013). With ``sort_rays``, the
    rays are first ordered by where they enter the grid (:mod:`instancing.accel.ray_order`),
    which pays where the grid and the instances' rows do not fit in cache. The result
    equals :func:`intersect_preliminary`'s. The passes evaluate between them, so this
    is for evaluated batches (:meth:`Scene.intersect`), not for traced or recorded kernels.
    """
    if not (isinstance(pass_steps, int) and pass_steps >= 1):
        # A pass of no steps would never finish a walk.
        raise ValueError(f"pass_steps must be a positive integer, got {pass_steps!r}")
    with dr.suspend_grad():
        o, d = dr.detach(o), dr.detach(d)
        if not sort_rays:
            return PreliminaryHit(*_walk_in_passes(table, grid, o, d, pass_steps))
        order = counting_sort_order(grid.entry_keys(o, d), 1 << (3 * ENTRY_KEY_BITS))
        hit = _walk_in_passes(table, grid, *gather_rays(o, d, order), pass_steps)
        return PreliminaryHit(*scatter_back(hit, order))


def _walk_in_passes(table, grid, o, d, pass_steps):
    """The passes of :func:`intersect_preliminary_in_passes`: the hit state (t, instance,
    position) of every ray, evaluated."""
    n = dr.width(o)
    hit = (dr.full(Float, dr.inf, n), dr.full(UInt32, MISS, n), dr.zeros(UInt32, n))
    walk, state, rays = grid.start(o, d, True), hit, None
    while True:
        ray_o, ray_d = (o, d) if rays is None else (dr.gather(Array3f, o, rays),
                                                    dr.gather(Array3f, d, rays))
        walk, state = grid.resume(ray_d, walk, state, lambda s: s[0],
                                  _item_test(table, grid.items, ray_o, ray_d), pass_steps)
        if rays is None:
            hit = state
        else:
            for target, value in zip(hit, state):
                dr.scatter(target, value, rays)
        dr.eval(hit, walk, state)
        going = dr.compress(walk.active)
        if dr.width(going) == 0:
            return hit
        # Step to the next pass: the rays still walking, packed, with their state.
        rays = going if rays is None else dr.gather(UInt32, rays, going)
        walk = dr.gather(WalkState, walk, going)
        state = tuple(dr.gather(type(v), v, going) for v in state)


def _item_test(table, items, o, d, any_hit=False):
    """The ``test_item(position, state)`` a traversal calls: the instance at ``position``
    of ``items`` (the instance ``position`` itself for None) against the rays."""
    def test_item(position, st):
        instance = position if items is None else dr.gather(UInt32, items, position)
        st = _test_instance(table, instance, o, d, st, any_hit)
        if any_hit:
            # A hit ends the lane's search, recorded as -t: every traversal loop runs
            # while t_of >= 0 (and t > 0).
            st = (dr.select(st[1] != MISS, -st[0], st[0]),) + st[1:]
        return st

    return test_item


def _test_instance(table, instance, o, d, state, any_hit=False, active=True, rows=None, kind=None):
    """Test one candidate instance per lane; keep the closer hit (lecture: inverse-transform the ray).

    ``instance`` is a per-lane UInt32, or a Python int for one instance in all lanes
    (whose model kind is then known at trace time, see :func:`_unrolled`), whose inverse
    ``rows`` the caller may give (else they are gathered from the table). ``kind``: the
    model kind of every lane's instance, where the caller knows it (see :func:`intersect_object`).
    """
    o_obj, d_obj = object_ray(table.inverse(UInt32(instance)) if rows is None else rows, o, d)
    t, position = intersect_object(table, instance, o_obj, d_obj, _search_limit(state), any_hit, active,
                                   kind)
    return _keep_nearer(state, t, instance, position, active)


def _search_limit(state) -> Float:
    """How far a candidate's test looks: up to the nearest hit so far, and once something
    is hit, one ulp beyond it, so that a tie at exactly that distance is reported too (the
    models accept t < limit only)."""
    t_best, best_instance, _ = state
    return dr.select(best_instance == MISS, t_best,
                     dr.reinterpret_array(Float, dr.reinterpret_array(UInt32, t_best) + 1))


def _keep_nearer(state, t, instance, position, active):
    """The state (t, instance, position) with the candidate's hit where it is nearer.

    Exact ties (coincident surfaces) go to the lower instance index, so that every
    acceleration structure (and the float64 reference) returns the same instance
    whatever its visiting order."""
    t_best, best_instance, best_position = state
    closer = active & ((t < t_best) | ((t == t_best) & (instance < best_instance)
                                       & (best_instance != MISS)))
    return (dr.select(closer, t, t_best), dr.select(closer, instance, best_instance),
            dr.select(closer, position, best_position))


def _unrolled_order(table, instances: list[int]) -> tuple[list[int], list[list[int]]]:
    """How :func:`_unrolled` tests ``instances`` (by slot): (the slots tested one after the
    other, the groups tested in rounds). The groups: all meshes, and every analytic kind
    with ROUNDS_MIN_INSTANCES or more instances; rounds run after the single tests, the
    meshes' last."""
    by_kind: dict[str, list[int]] = {}
    for slot, instance in enumerate(instances):
        by_kind.setdefault(table.kind_of(instance), []).append(slot)
    rounds = [slots for kind, slots in by_kind.items()
              if kind != MESH_KIND and len(slots) >= ROUNDS_MIN_INSTANCES]
    if MESH_KIND in by_kind:
        rounds.append(by_kind[MESH_KIND])
    in_rounds = {slot for group in rounds for slot in group}
    return [slot for slot in range(len(instances)) if slot not in in_rounds], rounds


def _unrolled(table, boxes, o, d, active, state, any_hit):
    """Test the instances of ``boxes`` in code unrolled at trace time: some one after the
    other, the others kind by kind nearest box first (:func:`_rounds`; which, see
    :func:`_unrolled_order`).

    Per instance tested on its own, the lanes whose ray meets its world box in front of
    their nearest hit so far run its test, in a branch that the whole SIMD packet skips
    when none of its lanes needs it. The instance's rows are one broadcast load and its
    model kind is known when the kernel is traced, so a lane runs exactly one model test,
    with no traversal loop, no per-lane gathers and no dispatch over kinds. The kernel
    grows with the instance count (see ``UNROLL_MAX_INSTANCES`` in
    :mod:`instancing.scene.scene`).
    """
    inv_d = dr.rcp(d)
    for slot in boxes.singles:
        lo, hi = boxes.box(slot)
        searching = active & ray_box(lo, hi, o, inv_d, state[0])[1]
        if any_hit:
            # A lane that has found a hit has its answer.
            searching &= state[1] == MISS
        state = dr.if_stmt(
            (state, searching), searching,
            lambda st, mask, k=boxes.instances[slot], rows=boxes.inverse_rows[slot]: _test_instance(
                table, k, o, d, st, any_hit, mask, rows),
            lambda st, mask: st)
    for slots in boxes.rounds:
        state = _rounds(table, boxes, slots, o, d, inv_d, active, state, any_hit)
    return PreliminaryHit(*state)


def _rounds(table, boxes, slots, o, d, inv_d, active, state, any_hit):
    """Test the instances at ``slots`` of ``boxes``, all of one kind, nearest world box
    first, in rounds.

    Step 1: each lane's entry distance into every one of their boxes (inf where the ray
    misses it or enters it behind the nearest hit so far). Step 2, round r: each lane takes
    its nearest box not yet tested and, where that box begins no farther than its nearest
    hit so far, tests the instance (its rows, and a mesh's BVH root, gathered per lane), all
    the lanes of a packet in one test (for meshes one walk loop) whichever instance each is
    in. A box behind a hit is never tested. The rounds are the iterations of one symbolic
    loop, which runs while some lane of the packet has a box left to test; its body, the
    model test or mesh walk, is traced once, however many instances the rounds cover.
    (Tested one after the other instead, each instance's test is a branch, or a mesh's
    walk a loop, of its own that a packet runs for the few of its lanes in that box.)
    """
    entries = []
    for slot in slots:
        lo, hi = boxes.box(slot)
        t_near, hit = ray_box(lo, hi, o, inv_d, state[0])
        entries.append(dr.select(active & hit, t_near, dr.inf))
    instances = [boxes.instances[slot] for slot in slots]
    kind = table.kind_of(instances[0])
    no_pick = len(slots)

    def nearest_untested(st, entries):
        # The nearest box not yet tested (ties to the lower slot), and whether the lane
        # tests it in this round.
        nearest, pick = Float(dr.inf), UInt32(no_pick)
        for j, entry in enumerate(entries):
            nearer = entry < nearest
            nearest, pick = dr.select(nearer, entry, nearest), dr.select(nearer, j, pick)
        searching = active & (pick != no_pick) & within(nearest, st[0])
        if any_hit:
            searching &= st[1] == MISS
        return searching, pick

    def round_(st, entries, searching, pick):
        instance = UInt32(instances[0])
        for j in range(1, no_pick):
            instance = dr.select(pick == j, instances[j], instance)
        st = _test_instance(table, instance, o, d, st, any_hit, searching, kind=kind)
        entries = [dr.select(pick == j, dr.inf, e) for j, e in enumerate(entries)]
        return (st, entries) + nearest_untested(st, entries)

    state, *_ = dr.while_loop((state, entries) + nearest_untested(state, entries),
                              lambda st, entries, searching, pick: searching, round_)
    return state


@dr.syntax
def _brute_force(count, active, state, test_item):
    """Test every instance (validation reference for the acceleration structures)."""
    item = dr.zeros(UInt32, dr.width(active))
    while dr.hint(active & (item < count) & (state[0] >= 0), exclude=[active, count, test_item]):
        state = test_item(item, state)
        item += 1
    return state


def _inverse_rows(forward):
    """Rows (A^-1 row i, b_i) of the exact inverse of the affine map with float64 rows
    (A row i, b_i): ``dr.rcp`` of the 3x3 linear part (as :func:`~instancing.core.transform.from_matrix`
    inverts per-lane matrices), differentiable."""
    a_inv = dr.rcp(Matrix3f64([[r.x, r.y, r.z] for r in forward]))
    return tuple(Array4f64(a_inv[k][0], a_inv[k][1], a_inv[k][2], forward[k].w) for k in range(3))


def reintersect(table: InstanceTable, o: Array3f, d: Array3f, hit: PreliminaryHit,
                uv: bool | None = None) -> SurfaceHit:
    """Phase 2: differentiable surface record of the preliminary winner (see
    :func:`_surface_record`).

    Where no derivatives are tracked, phase 2 runs in a branch that a SIMD packet whose
    rays all missed skips (rays into the sky, random rays through a sparse scene): the
    same record, for less work. Measured, 2^20 random rays through 100 000 clustered
    spheres (0.1 % hit): 28 -> 19 ms per full record; renders, ms: showcase ``direct``
    16 spp 389 -> 355, affine_shapes ``direct`` 16 spp 119 -> 114; uniform fields and
    the forest unchanged (every packet has a hit); images bit-identical. With
    derivatives, every lane runs it (a symbolic branch would carry the AD graph
    through a conditional that the gradient code paths have not been checked with).
    """
    if dr.grad_enabled(table.inverse_rows, table.forward_linear, o, d):
        return _surface_record(table, o, d, hit, uv)

    def on_hit(o, d, t, instance, position):
        record = _surface_record(table, o, d, PreliminaryHit(t, instance, position), uv)
        return (record.t, record.p, record.n, record.sn, record.ss, record.error, record.instance,
                record.prim, record.uv, record.dpdu, record.dpdv, record.prim_uv, record.triangle)

    def on_miss(o, d, t, instance, position):
        return _miss_fields(dr.width(t))

    fields = dr.if_stmt((o, d, hit.t, hit.instance, hit.position), hit.valid, on_hit, on_miss,
                        mode="symbolic")
    return SurfaceHit(*fields, valid=hit.valid)


def _surface_record(table: InstanceTable, o: Array3f, d: Array3f, hit: PreliminaryHit,
                    uv: bool | None = None) -> SurfaceHit:
    """Phase 2 on every lane (surface coordinates where ``uv``, by default where the
    table's materials read textures).

    It runs in float64, for the winner only, on the stored float32 forward
    matrix and the float32 ray. The inverse is the exact one of that matrix
    (not the separately rounded float32 inverse that traversal uses), so the
    surface intersected is the stored instance's to float64 precision; the
    object-space origin ``A^-1 (o - b)`` is exact to ~1e-16 even hundreds of
    model sizes away (a small instance seen from afar, a nearly degenerate
    axis); the quadric is solved and its normal taken without float32
    cancellation; and the world hit point and normal are rounded to float32
    once, at the end. Traversal, where the work is, stays float32.
    """
    valid = hit.valid
    instance = dr.select(valid, hit.instance, 0)
    # The winner's forward rows (AD-attached when parameters are) and their exact inverse.
    forward = table.forward(instance)

    def retest(forward, o, d):
        forward64 = tuple(Array4f64(r) for r in forward)
        rows = _inverse_rows(forward64)
        o_obj, d_obj = object_ray(rows, Array3f64(o), Array3f64(d))
        return (forward64, rows, o_obj, d_obj,
                *reintersect_object(table, instance, o_obj, d_obj, hit.position, valid, uv,
                                    Float64(dr.detach(hit.t))))

    if dr.grad_enabled(forward, o, d):
        # Grazing hits can miss on the second test, and their lanes then hold non-finite
        # values: in reverse mode the zero gradient of such a lane becomes NaN through
        # them (0 * inf) and the gathers' scatter-add carries it into the winner's rows
        # (seen: NaN gradients of one sphere's translation among 1 000). The lanes are
        # found by a detached test first and get detached inputs.
        with dr.suspend_grad():
            grazing = ~dr.isfinite(retest(forward, o, d)[4])
        forward = tuple(dr.select(grazing, dr.detach(r), r) for r in forward)
        o, d = dr.select(grazing, dr.detach(o), o), dr.select(grazing, dr.detach(d), d)
    (forward64, rows, o_obj, d_obj, t, p_obj, p_error, n_obj, sn_obj, uv, dpdu,
     dpdv, prim_uv) = retest(forward, o, d)
    # Grazing hits can round differently on the second test; keep phase 1's distance there
    # and take the point on the object-space ray, with the rounding bound of o + t d.
    missed = ~dr.isfinite(t)
    t = dr.select(missed, Float64(dr.detach(hit.t)), t)
    p_obj = dr.select(missed, dr.fma(d_obj, t, o_obj), p_obj)
    p_error = dr.select(missed, gamma(3) * (dr.abs(o_obj) + dr.abs(d_obj * t)), p_error)
    # Map the object-space hit point to world space (translation added last), and its
    # float32 error bound, which stays valid (conservative) for the float64 map.
    p = Array3f(world_point(forward64, p_obj))
    error = transformed_point_error(forward, Array3f(p_obj), Array3f(p_error),
                                    dr.gather(Float, table.remap_error, instance))
    n = Array3f(world_normal(rows, n_obj))
    # The shading normal, by the same inverse transpose, where a smooth mesh can be hit.
    smooth = any(any(library.smooth) for library in table.libraries.values())
    sn = Array3f(world_normal(rows, sn_obj)) if smooth else n
    # The shading tangent: dp/du (a vector: the linear part maps it), made orthogonal to sn.
    ss = (shading_tangent(sn, Array3f(world_vector(forward64, dpdu))) if table.surface_tangents
          else frame(sn)[0])
    t = Float(t)
    prim = prim_index(table, instance, hit.position)
    # The derivatives are vectors: the linear part maps them.
    derivatives = ((Array3f(world_vector(forward64, dpdu)), Array3f(world_vector(forward64, dpdv)))
                   if table.surface_derivatives else (Array3f(0.0), Array3f(0.0)))
    triangle = UInt32(hit.position) if table.surface_attributes else UInt32(0)
    fields = (t, p, n, sn, ss, error, Int32(hit.instance), Int32(prim), Array2f(uv), *derivatives,
              Array2f(prim_uv), triangle)
    return SurfaceHit(*(dr.select(valid, value, miss)
                        for value, miss in zip(fields, _miss_fields(dr.width(valid)))), valid=valid)


# -- per-kind dispatch --------------------------------------------------------------------------

def intersect_object(table: InstanceTable, instance: UInt32 | int, o: Array3f, d: Array3f, t_max: Float,
                     any_hit: bool = False, active: Bool | bool = True,
                     kind: str | None = None) -> tuple[Float, UInt32]:
    """Intersect object-space rays with each lane's untransformed model.

    ``instance`` is per lane, or a Python int: one instance for all lanes,
    whose kind (and mesh) is then read now and only its test is traced; so is
    only ``kind``'s where the caller gives the kind of every lane's instance.
    Returns ``(t, position)``: t in (0, t_max) or inf; position is the
    leaf-order triangle for meshes and 0 otherwise. With ``any_hit``, a mesh
    stops at the first triangle found (its t is then not the nearest). A mesh
    walks its BVH for the ``active`` lanes only.
    """
    t = Float(dr.inf)
    position = UInt32(0)
    kinds = list(enumerate(table.kind_names))
    if isinstance(instance, int):
        kind = table.kind_of(instance)
    if kind is not None:
        kinds = [(table.kind_names.index(kind), kind)]
    for code, name in kinds:
        mask = True if kind is not None else table.kind_mask(instance, code)
        if name in table.libraries:
            t_k, pos_k = table.libraries[name].intersect(o, d, t_max, active & Bool(mask),
                                                         _mesh_root(table, instance), any_hit)
            position = dr.select(mask, pos_k, position)
        else:
            t_k = ANALYTIC_MODELS[name].intersect(o, d, t_max, table.wide_scales)
        t = dr.select(mask, t_k, t)
    return t, position


def _mesh_root(table: InstanceTable, instance: UInt32 | int) -> UInt32:
    """The BVH root reference of each lane's mesh or grid instance (one opaque scalar where
    one such model is shared by all or ``instance`` is a Python int)."""
    if isinstance(table.mesh_root, int):
        return dr.opaque(UInt32, table.mesh_root)
    if isinstance(instance, int):
        return dr.opaque(UInt32, int(table.host_codes[1][instance]))
    return dr.gather(UInt32, table.mesh_root, instance)


def reintersect_object(table: InstanceTable, instance: UInt32, o: Array3f64, d: Array3f64, position: UInt32,
                       active: Bool | bool = True, uv: bool | None = None,
                       t_first: Float64 | None = None
                       ) -> tuple[Float64, Array3f64, Array3f64, Array3f64, Array3f64, Array2f64,
                                  Array3f64, Array3f64, Array2f64]:
    """Differentiable t, object-space hit point, its error bound, object-space geometric
    normal and shading normal (not normalized; the geometric one but on smooth meshes),
    surface coordinates (0 unless ``uv``, by default ``table.surface_uv``), the
    derivatives dp/du (0 unless ``table.surface_tangents`` or ``table.surface_derivatives``)
    and dp/dv (0 unless ``table.surface_derivatives``), and a mesh hit's barycentrics (0
    unless ``table.surface_attributes``, and on analytic models) for a known instance and
    triangle, in float64. Where an analytic model's second test misses (a ray through its
    edge), its point, normal, coordinates and derivatives are taken at phase 1's distance
    ``t_first`` (t stays inf: the caller keeps phase 1's), so that none is NaN.

    No traversal: the winning model (and triangle) is tested once more
    with AD attached, in float64 (see :func:`instancing.scene.intersection.reintersect`).
    The hit point is the model's own, re-projected onto its surface
    (barycentric for triangles), with the model's error bound.
    """
    record = (Float64(dr.inf), Array3f64(0.0), Array3f64(0.0), Array3f64(0.0), Array3f64(0.0),
              Array2f64(0.0), Array3f64(0.0), Array3f64(0.0), Array2f64(0.0))
    with_uv = table.surface_uv if uv is None else uv
    tangents, both = table.surface_tangents or table.surface_derivatives, table.surface_derivatives

    def derivatives(compute):
        dpdu, dpdv = compute() if tangents else (Array3f64(0.0), Array3f64(0.0))
        return dpdu, dpdv if both else Array3f64(0.0)
    for code, name in enumerate(table.kind_names):

        def surface(o, d, position, *record, name=name):
            if name == MESH_KIND:
                t_k, p_k, shading, (b1, b2) = table.meshes.surface_point(o, d, position)
                uv = Array2f64(*table.meshes.uv(position, b1, b2)) if with_uv else Array2f64(0.0)
                dpdu, dpdv = derivatives(lambda: table.meshes.derivatives(position, Array3f64))
                prim_uv = Array2f64(b1, b2) if table.surface_attributes else Array2f64(0.0)
                return (t_k, p_k, Array3f64(table.meshes.point_error(position)),
                        table.meshes.normal(position, Array3f64), shading, uv, dpdu, dpdv, prim_uv)
            if name in (CURVE_KIND, BSPLINE_KIND):
                t_k, p_k, n_k, e_k, uv, dpdu, dpdv = table.libraries[name].surface_point(
                    o, d, position, dr.inf if t_first is None else t_first, with_uv, tangents)
                return (t_k, p_k, e_k, n_k, n_k, uv, dpdu, dpdv if both else Array3f64(0.0),
                        Array2f64(0.0))
            if name == GRID_KIND:
                # No surface coordinates nor derivatives (Mitsuba's grids have none).
                t_k, p_k, n_k, sn_k = table.grids.surface_point(
                    o, d, position, dr.inf if t_first is None else t_first)
                zero = Array3f64(0.0)
                return (t_k, p_k, Array3f64(table.grids.point_error(p_k)), n_k, sn_k, Array2f64(0.0),
                        zero, zero, Array2f64(0.0))
            model = ANALYTIC_MODELS[name]
            t_k = model.intersect(o, d, dr.inf)
            p_k = model.surface_point(o, d, t_k if t_first is None
                                      else dr.select(dr.isfinite(t_k), t_k, t_first))
            n_k = table.oriented(instance, model.normal(p_k, position))
            uv = Array2f64(*model.uv(p_k)) if with_uv else Array2f64(0.0)
            dpdu, dpdv = derivatives(lambda: model.derivatives(p_k))
            return t_k, p_k, model.point_error(p_k), n_k, n_k, uv, dpdu, dpdv, Array2f64(0.0)

        if len(table.kind_names) == 1:
            record = surface(o, d, position)
        else:
            # Only the kinds present in a SIMD packet run their float64 test: a branch
            # per kind (AD flows through it), which a packet skips when none of its
            # lanes hit that kind.
            record = dr.if_stmt((o, d, position) + record,
                                table.kind_mask(instance, code) & active,
                                surface, lambda o, d, position, *record: record)
    return record


def prim_index(table: InstanceTable, instance: UInt32, position: UInt32) -> UInt32:
    """User-facing primitive index: the triangle's file index for meshes, the voxel's rank
    among the grid's voxels that hold surface for grids, the segment's file index for
    curves, else 0."""
    index = UInt32(0)
    for name, library in table.libraries.items():
        index = dr.select(table.kind_mask(instance, table.kind_names.index(name)),
                          library.prim_index(position), index)
    return index


def _miss_fields(width: int) -> tuple:
    """What a record reports for a ray that hit nothing: (t, p, n, sn, ss, error, instance,
    prim, uv, dpdu, dpdv, prim_uv, triangle) = (inf, 0, 0, 0, 0, 0, -1, -1, 0, 0, 0, 0, 0)."""
    zero = dr.zeros(Array3f, width)
    return (dr.full(Float, dr.inf, width), zero, zero, zero, zero, zero, dr.full(Int32, -1, width),
            dr.full(Int32, -1, width), dr.zeros(Array2f, width), zero, zero, dr.zeros(Array2f, width),
            dr.zeros(UInt32, width))
