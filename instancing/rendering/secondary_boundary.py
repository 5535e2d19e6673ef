"""Boundary term of visibility seen from shading points: the penumbrae of area lights and of
the environment, and (in ``path``) what the BSDF rays see, at every bounce.

At a shading point x the integrators estimate ``I(x) = int_{S^2} g(w) dw`` with
``g = f_r cos L_i(x, w)`` (one-sided diffuse). Across the silhouette curves of the
scene as seen from x, ``L_i`` jumps (an occluder in front of a lamp, of the sky, of a
lit wall); where a curve moves with theta, the derivative gains a line integral on the
sphere of directions (Li et al. 2018, "Differentiable Monte Carlo Ray Tracing through
Edge Sampling", secondary edges)::

    dI/dtheta = int dg/dtheta dw  +  oint (g(w-) - g(w+)) v_rel dl

**Curves per lane.** The silhouette of an instance seen from x is the image of its
model's silhouette seen from ``M^-1 x`` (affine maps keep tangent rays tangent): each
lane picks one candidate occluder uniformly and one point on its model's curves from
the object-space viewpoint, in closed form
(:meth:`~instancing.models.analytic.AnalyticModel.sample_silhouette`; mesh edges by
:class:`~instancing.models.mesh.SilhouetteEdges`), with density 1 per unit of the
curve parameter; the world point ``s = M(theta) s_obj`` carries the derivatives.

**Velocity relative to the interior's parameterisation.** The interior term holds
fixed what each sampling strategy holds fixed: emitter sampling a point of the
emitter's own surface (it moves with a moving lamp); BSDF sampling, in ``direct``, a
direction in the frame of the shading normal, in ``path`` (path replay's area form,
:mod:`instancing.rendering.integrators.path`) the next vertex in world space, or near x
its slide with x (:func:`~instancing.rendering.integrators.path.slide_weight`). Each side
of a curve contributes by the curve's velocity relative to those points on that side
(Bangaru et al. 2020's relative velocity), so the jump splits by strategy: the
emitter-sampled part (the light reaching x directly from an area emitter, times its
MIS weight) moves with ``n . (w_s - w_y)``, the rest (the BSDF-sampled share of that
light, the environment and, in ``path``, all indirect light) with ``n . (w_s - w_b)``;
``w_s`` is the direction to the curve point, ``w_y`` to the emitter point seen on that
side and ``w_b`` the BSDF strategy's fixed direction or point. For static lamps and
shading points both reduce to the curve's own motion.

**Estimator.** One sample per camera sample (``sppi`` per pixel, through the film like
the interior): the shading point's hit (AD attached), a candidate and a curve point;
``g`` on both sides of the curve, ``SIDE_OFFSET`` of the occluder's size away,
with the same random numbers; the contribution has value 0 and derivative equal to
the boundary term.

**Choosing the curve point** (resampled importance sampling, Talbot et al. 2005):
``PROPOSALS`` proposals, each a uniform candidate and a uniform curve parameter, are
weighed by the curve's speed on the sphere of directions (its length there) times a
guide: 1 per area emitter whose bounding sphere the direction meets, 1 for an
environment, ``GUIDE_FLOOR`` otherwise; one is kept in proportion to its weight, its
contribution scaled by the proposals' mean weight over its own (unbiased, since the
weight is positive wherever a jump can be). Candidates: the moving instances (every instance when an area
emitter moves: its light then slides behind static occluders), and every instance for
shading points on moving instances (x moves against static occluders).

**Hard shadows seen from shading points** (``path``): the light that the next vertex
gathers from a point or directional light jumps at that light's shadow edges, curves on the
surfaces that a vertex x sees. Where the path goes on past the next vertex, a sample takes
such a curve with probability SHADOW_SHARE (1 when no instance moves) instead of a
silhouette (:class:`ShadowCurves`): a silhouette an instance shows the light, picked by its
world length, a point on it uniformly, carried to the surface it shadows as for the camera
(:func:`~instancing.rendering.boundary_term.shadow_receivers`); jump and velocity then as
above, with the shadow point as the curve point.

**Every bounce** (``path``): besides the first vertex, each sample evaluates the term at
one later vertex k, uniform among those that gather light (2 .. max_depth - 1;
geometric for unbounded paths), reached by cosine-sampled bounces from the camera ray
and weighted by their throughput over the probability of k. There the vertex moves with
its surface along its detached incoming ray, and slides near the vertex before it, as in
path replay's interior term.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.backend import Array3f, Bool, Float, Int32, UInt32, device_arrays, dr
from ..core.ray_offset import offset_origin
from ..core.rng import sample_streams
from ..core.transform import object_point, world_point, world_vector
from ..core.warp import power_heuristic, to_frame, to_local
from ..models.analytic import ANALYTIC_MODELS
from ..models.curves import Curves
from ..models.mesh import SilhouetteEdges
from ..scene.description import ENVIRONMENTS, DirectionalLight, PointLight
from ..scene.instance_table import MESH_KIND
from ..scene.intersection import reintersect
from .boundary_term import (RECEIVER_SEARCH_OFFSET, BoundarySampler, shadow_casters,
                            shadow_curves, shadow_receivers, world_length_weights)
from .integrators.direct import emitted, emitter_pdf, sample_bsdf, shading
from .integrators.path import integrate_path, slid, slide_reach, slide_share, slide_weight

#: Distance of the two side rays from the curve point, as a fraction of the occluder's
#: size (its largest axis): far above float32 rounding of the point, far below the
#: scale on which the light varies.
SIDE_OFFSET = 1e-4
#: Curve points nearer to the shading point than this multiple of the side offset are
#: skipped (edges through x itself: the cosine vanishes there).
NEAR_LIMIT = 10.0
#: Seed offset of the side rays' shared random numbers (path continuation).
SIDE_SEED = 0x7F4A7C15
#: Unbounded paths: the later vertex k is picked with probability (1 - r) r^(k - 2).
LATER_VERTEX_RATIO = 0.75
#: Curve-point proposals per sample, of which one is kept (resampled importance sampling).
PROPOSALS = 8
#: Guide weight of a proposal whose direction meets no emitter (1 per emitter met).
GUIDE_FLOOR = 0.1
#: Area emitters whose bounding spheres guide the proposals, at most (beyond, none do).
MAX_GUIDING_EMITTERS = 16
#: Probability that a sample takes a shadow curve of a point or directional light rather
#: than an occluder's silhouette, where both can jump (see ShadowCurves).
SHADOW_SHARE = 0.5


@dataclass
class ShadowCurves:
    """The silhouettes that instances show the point and directional lights, whose shadows
    (where the lights' rays graze them, on the next surface) the shading points of ``path``
    can see: there the light that the next vertex gathers jumps. One curve set
    (:class:`~instancing.rendering.boundary_term.BoundarySampler`, chosen by world
    length): first the curves whose shadows move for static shading points (those of
    :func:`~instancing.rendering.boundary_term.shadow_casters`), then the other instances'
    (their shadows move against shading points on moving instances). ``first`` is the
    first group's share of the selection (its cumulative probability, as the kernels
    store it) and ``below_first`` the float32 number just below it."""

    curves: BoundarySampler
    first: Float
    below_first: Float

    @staticmethod
    def build(scene) -> "ShadowCurves | None":
        """The frame's shadow curves (host work), or None when no light casts any."""
        lit = [(i, light) for i, light in enumerate(scene.rendering_lights)
               if isinstance(light, (PointLight, DirectionalLight))]
        if not lit:
            return None
        everything = np.arange(len(scene.instance_ids))
        first = [shadow_casters(scene, i, light) for i, light in lit]
        rest = [np.setdiff1d(everything, who) if len(scene.moving_instances) else who[:0]
                for who in first]
        groups = [shadow_curves(scene, lit, casters) for casters in (first, rest)]
        curves = Curves.joined([g[0] for g in groups])
        if not len(curves):
            return None
        weights = world_length_weights(curves, scene.instances.to_world_of(curves.instance))
        sampler = BoundarySampler.build(curves, weights, np.concatenate([g[1] for g in groups]),
                                        np.concatenate([g[2] for g in groups]))
        # The first group's share as the kernels hold it: its last cumulative probability,
        # rounded to float32 as the stored table is (1 where there is no second group).
        count = len(groups[0][0])
        share = (np.float32(np.cumsum(weights)[count - 1] / weights.sum())
                 if 0 < count < len(curves) else np.float32(1.0 if count else 0.0))
        below = np.nextafter(share, np.float32(0.0))
        return ShadowCurves(sampler, dr.opaque(Float, float(share)),
                            dr.opaque(Float, float(below)))

    def sample(self, scene, lights, sampler, moving: Bool, active: Bool):
        """Per lane a shadow curve point where it falls, for shading points on a moving
        instance (``moving``) from all curves, else from the first group: (world point on
        the receiver (AD attached: it moves with the caster, the receiver and the light),
        d point / du there (detached), the caster's size, found, 1 / pdf)."""
        with dr.suspend_grad():
            share = dr.select(moving, 1.0, self.first)
            u_pick = dr.minimum(sampler.next_float32() * share,
                                dr.select(moving, 1.0, self.below_first))
            curve, instance, x_obj, tangent, probability, _ = self.curves.sample(
                u_pick, sampler.next_float32())
            offset = dr.gather(Float, self.curves.offset, curve)
            light = dr.gather(UInt32, self.curves.light, curve)
        rows = scene.instances.forward(instance)
        p = world_point(rows, x_obj)
        with dr.suspend_grad():
            p_tangent = world_vector(rows, tangent)
        z, dz, found = shadow_receivers(scene, lights, light, offset, p, p_tangent, active)
        return (z, dz, offset * (1.0 / RECEIVER_SEARCH_OFFSET), found & (share > 0),
                share / probability)


@dataclass
class Occluders:
    """The frame's candidate occluders (padded to a power of two), with what sampling their
    curves needs: the model kinds present, each candidate's kind code, its edge range
    (meshes), its size and whether its model is convex; and what guides the choice of
    curve points: the area emitters' bounding spheres and whether an environment lights
    every direction."""

    capacity: int
    kinds: tuple
    #: Opaque counts: the candidates of static shading points (the first ones), and of
    #: shading points on moving instances (all).
    count: UInt32
    count_all: UInt32
    #: Per instance, 1 where it moves.
    moving: UInt32
    instance: UInt32
    kind: UInt32
    edge_first: UInt32
    edge_count: UInt32
    size: Float
    convex: UInt32
    edges: SilhouetteEdges | None
    lamp_centre: Array3f | None
    lamp_radius: Float | None
    lamp_count: int
    environment: bool
    #: Whether any instance moves (else only shadow curves are sampled).
    silhouettes: bool
    #: The point and directional lights' shadow curves (``path`` only), or None.
    shadows: ShadowCurves | None

    def _proposal(self, table, k: UInt32, u: Float, u_choice: Float, x: Array3f, creases: bool):
        """Candidate k's curve point at (u, u_choice) seen from world point x (detached):
        (instance, object point, object d point / du, valid)."""
        instance = dr.gather(UInt32, self.instance, k)
        kind = dr.gather(UInt32, self.kind, k)
        view = object_point(table.inverse(instance), x)
        point, tangent, valid = Array3f(0.0), Array3f(0.0), Bool(False)
        for code, name in enumerate(self.kinds):
            mine = kind == code
            if name == MESH_KIND:
                p_k, t_k, ok_k = self.edges.sample(dr.gather(UInt32, self.edge_first, k),
                                                   dr.gather(UInt32, self.edge_count, k), view, u,
                                                   u_choice, creases)
            else:
                p_k, t_k, ok_k = ANALYTIC_MODELS[name].sample_silhouette(view, u, creases)
            point = dr.select(mine, p_k, point)
            tangent = dr.select(mine, t_k, tangent)
            valid = dr.select(mine, ok_k, valid)
        return instance, point, tangent, valid

    def _guide(self, table, k: UInt32, instance: UInt32, point: Array3f, tangent: Array3f,
               valid: Bool, x: Array3f, n: Array3f, on: Int32) -> Float:
        """The resampling weight of a proposal (detached): 0 where it cannot contribute
        (no curve point, behind the shading point, a convex model's own curve), else the
        curve's speed on the sphere of directions around x (its length there per unit of
        the parameter) times GUIDE_FLOOR, plus 1 if an environment lights every direction,
        plus 1 per area emitter whose bounding sphere the direction to the point meets."""
        rows = table.forward(instance)
        w = world_point(rows, point) - x
        t = world_vector(rows, tangent)
        r2 = dr.squared_norm(w)
        speed = dr.sqrt(dr.maximum(dr.squared_norm(t) - dr.square(dr.dot(w, t)) / r2, 0.0) / r2)
        own = (dr.gather(UInt32, self.convex, k) != 0) & (Int32(instance) == on)
        weight = Float(GUIDE_FLOOR + (1.0 if self.environment else 0.0))
        for e in range(self.lamp_count):
            to_c = dr.gather(Array3f, self.lamp_centre, UInt32(e)) - x
            radius = dr.gather(Float, self.lamp_radius, UInt32(e))
            d2, r2 = dr.squared_norm(to_c), radius * radius
            # Inside the cone from x around the sphere: angle to its centre below asin(r / d).
            cos_w = dr.dot(w, to_c)
            meets = (d2 <= r2) | ((cos_w > 0) & (cos_w * cos_w >= (d2 - r2) * dr.squared_norm(w)))
            weight += dr.select(meets, 1.0, 0.0)
        return dr.select(valid & ~own & (dr.dot(n, w) > 0), weight * speed, 0.0)

    def sample(self, table, sampler, x: Array3f, n: Array3f, on: Int32, creases: bool):
        """Per lane a candidate and a point on its curves seen from world point x (normal n)
        on instance ``on``, by resampled importance sampling: PROPOSALS proposals, each a
        uniform candidate and a uniform curve parameter, one kept in proportion to its
        guide weight (:meth:`_guide`). Returns (instance, world point (AD attached),
        d point / du (detached), its size, convex, valid, 1 / pdf)."""
        moving = dr.gather(UInt32, self.moving, UInt32(dr.maximum(on, 0))) != 0
        count = dr.select(moving, self.count_all, self.count)
        width = dr.width(x)
        with dr.suspend_grad():
            x0, n0 = dr.detach(x), dr.detach(n)

            def body(j, total, k_kept, u_kept, c_kept, w_kept, rng):
                k = dr.minimum(UInt32(rng.next_float32() * Float(count)), count - 1)
                u, u_choice = rng.next_float32(), rng.next_float32()
                instance, point, tangent, valid = self._proposal(table, k, u, u_choice, x0,
                                                                 creases)
                weight = self._guide(table, k, instance, point, tangent, valid, x0, n0, on)
                total = total + weight
                # Weighted reservoir: keep the new proposal with probability weight / total.
                keep = (weight > 0) & (rng.next_float32() * total < weight)
                return (j + 1, total, dr.select(keep, k, k_kept), dr.select(keep, u, u_kept),
                        dr.select(keep, u_choice, c_kept), dr.select(keep, weight, w_kept), rng)

            state = (dr.zeros(UInt32, width), dr.zeros(Float, width), dr.zeros(UInt32, width),
                     dr.zeros(Float, width), dr.zeros(Float, width), dr.zeros(Float, width),
                     sampler)
            _, total, k, u, u_choice, w_kept, rng = dr.while_loop(
                state, lambda j, *rest: j < PROPOSALS, body,
                labels=("j", "total", "k", "u", "u_choice", "w", "sampler"))
            sampler.take_state(rng)
            instance, point, tangent, valid = self._proposal(table, k, u, u_choice, x0, creases)
            valid &= w_kept > 0
            # RIS: 1 / pdf = (mean of weight / proposal pdf) / kept weight; pdf = 1 / count.
            inverse_pdf = Float(count) * total / (PROPOSALS * dr.select(valid, w_kept, 1.0))
        rows = table.forward(instance)
        world = world_point(rows, point)
        with dr.suspend_grad():
            world_tangent = world_vector(rows, tangent)
        return (instance, world, world_tangent, dr.gather(Float, self.size, k),
                dr.gather(UInt32, self.convex, k) != 0, valid, inverse_pdf)


def secondary_term_needed(scene, integrator: str) -> bool:
    """Whether light seen from shading points can jump across a moving curve: something
    moves, and the integrator gathers light along rays from them (``path``, or ``direct``
    with area emitters or an environment); in ``path``, a moving point or directional
    light moves its shadows under the path's later vertices."""
    if integrator == "path" and len(scene.moving_lights):
        return True
    if not len(scene.moving_instances) or integrator == "aov":
        return False
    has_environment = any(isinstance(light, ENVIRONMENTS) for light in scene.lights)
    return integrator == "path" or bool(scene.description.emitters) or has_environment


def occluder_set(scene, integrator: str) -> Occluders | None:
    """The frame's candidate occluders for the secondary boundary term (host work), or
    None when it is not needed (:func:`secondary_term_needed`)."""
    if not secondary_term_needed(scene, integrator):
        return None
    moving, desc = scene.moving_instances, scene.description
    everything = np.arange(len(desc.instance_ids))
    if set(desc.emitters) & set(moving.tolist()):
        first_choice = everything
    else:
        first_choice = np.asarray(moving, np.int64)
    # The first choice first, then the others (the candidates of moving shading points).
    candidates = np.concatenate([first_choice, np.setdiff1d(everything, first_choice)])
    model = np.asarray(desc.instance_model)[candidates]
    kind_of = [desc.models[m].kind for m in model]
    kinds = tuple(sorted(set(kind_of)))
    edges, first, count = None, np.zeros(len(candidates), np.int64), np.zeros(len(candidates), np.int64)
    if MESH_KIND in kinds:
        meshes = sorted({scene.mesh_index(m) for m, kind in zip(model, kind_of) if kind == MESH_KIND})
        edges = scene.instances.meshes.silhouette_edges(meshes)
        for j, (m, kind) in enumerate(zip(model, kind_of)):
            if kind == MESH_KIND:
                slot = meshes.index(scene.mesh_index(m))
                first[j], count[j] = edges.first[slot], edges.count[slot]
    convex = np.array([kind != MESH_KIND and ANALYTIC_MODELS[kind].convex for kind in kind_of])
    size = np.linalg.norm(scene.instances.to_world_of(candidates)[:, :3, :3], axis=1).max(axis=1)
    capacity = 1 << max(0, int(len(candidates) - 1).bit_length())

    def padded(values):
        return np.concatenate([np.asarray(values), np.zeros(capacity - len(candidates))])

    ints = device_arrays(UInt32, *[padded(a).astype(np.int64) for a in (
        candidates, [kinds.index(k) for k in kind_of], first, np.maximum(count, 1), convex)])
    (sizes,) = device_arrays(Float, padded(size))
    flags = np.zeros(len(everything), np.int64)
    flags[moving] = 1
    (on_moving,) = device_arrays(UInt32, flags)
    lamps = sorted(desc.emitters)
    centre, radius, lamp_count = None, None, 0
    if 0 < len(lamps) <= MAX_GUIDING_EMITTERS:
        lo, hi = scene.instance_bounds(lamps)
        floats = device_arrays(Float, *(0.5 * (lo + hi)).T, 0.5 * np.linalg.norm(hi - lo, axis=1))
        centre, radius, lamp_count = Array3f(*floats[:3]), floats[3], len(lamps)
    environment = any(isinstance(light, ENVIRONMENTS) for light in scene.lights)
    return Occluders(capacity, kinds, dr.opaque(UInt32, len(first_choice)),
                     dr.opaque(UInt32, len(candidates)), on_moving, *ints[:4], sizes, ints[4], edges,
                     centre, radius, lamp_count, environment, len(moving) > 0,
                     ShadowCurves.build(scene) if integrator == "path" else None)


def secondary_boundary(scene, lights, occluders: Occluders, integrator: str, max_depth: int,
                       o: Array3f, d: Array3f, sampler) -> Array3f:
    """One sample of the secondary boundary term along camera rays (o, d): value 0,
    derivative the term (see the module docstring); in ``path``, at the first vertex and
    at one later vertex picked per sample."""
    result = _vertex_term(scene, lights, occluders, integrator, max_depth - 1 if max_depth > 0
                          else max_depth, o, d, sampler)
    if integrator == "path" and (max_depth < 0 or max_depth > 2):
        result += later_vertex_term(scene, lights, occluders, max_depth, o, d, sampler)
    return result


def later_vertex_term(scene, lights, occluders: Occluders, max_depth: int, o: Array3f,
                      d: Array3f, sampler) -> Array3f:
    """The term at one vertex k >= 2 of each camera ray's path: k uniform among the vertices
    that gather light (2 .. max_depth - 1), or geometric (LATER_VERTEX_RATIO) for unbounded
    paths; the path is walked there by cosine sampling (throughput: the albedos) and the
    term evaluated as at the first vertex, divided by the probability of k."""
    u = sampler.next_float32()
    if max_depth > 0:
        count = max_depth - 2
        k = 2 + dr.minimum(UInt32(u * count), count - 1)
        inverse_pdf = Float(count)
        remaining = UInt32(max_depth) - k
    else:
        # P(k) = (1 - r) r^(k - 2), k >= 2 (cut at k = 66, beyond which P < 1e-8).
        steps = dr.minimum(dr.floor(dr.log(1.0 - u) / math.log(LATER_VERTEX_RATIO)), 64.0)
        k = 2 + UInt32(steps)
        inverse_pdf = 1.0 / ((1.0 - LATER_VERTEX_RATIO) * dr.power(LATER_VERTEX_RATIO, steps))
        remaining = UInt32(0xFFFFFFFF)
    o_k, d_k, before, beta, alive = _walk(scene, o, d, k - 1, sampler)
    # (Vertices slide only with moving instances.)
    term = _vertex_term(scene, lights, occluders, "path", remaining, o_k, d_k, sampler,
                        before if len(scene.moving_instances) else None)
    return dr.select(alive, beta * inverse_pdf * term, 0.0)


def _walk(scene, o: Array3f, d: Array3f, bounces: UInt32, sampler
          ) -> tuple[Array3f, Array3f, tuple[Array3f, Array3f], Array3f, Bool]:
    """Follow the rays (o, d) for ``bounces`` bounces, each drawn from the BSDF there
    (detached): the last ray, the one before it, the throughput (the product of the sample
    weights) and whether the path got there."""
    width = dr.width(o)

    def body(o, d, o_before, d_before, beta, step, sampler, alive):
        hit = scene.intersect_surface(o, d, alive)
        info = shading(scene, hit, d)
        alive &= info.lit
        o_next, d_next, sample = sample_bsdf(scene, hit, info, sampler)
        alive &= sample.valid
        beta = dr.select(alive, beta * sample.weight, beta)
        return (dr.select(alive, o_next, o), dr.select(alive, d_next, d), dr.select(alive, o, o_before),
                dr.select(alive, d, d_before), beta, step + 1, sampler, alive)

    with dr.suspend_grad():
        state = (dr.zeros(Array3f, width) + o, dr.zeros(Array3f, width) + d, dr.zeros(Array3f, width) + o,
                 dr.zeros(Array3f, width) + d, dr.full(Array3f, 1.0, width), dr.zeros(UInt32, width),
                 sampler, dr.full(Bool, True, width))
        o, d, o_before, d_before, beta, _, _, alive = dr.while_loop(
            state, lambda *s: s[-1] & (s[5] < bounces), body,
            labels=("o", "d", "o_before", "d_before", "beta", "step", "sampler", "alive"))
    return o, d, (o_before, d_before), beta, alive


def _slid_hit(scene, o: Array3f, d: Array3f, before: tuple[Array3f, Array3f]):
    """The hit of the detached ray (o, d), moving along it with its surface and, near the
    vertex that the ray ``before`` found, sliding with that one's own motion (as in path
    replay, :func:`~instancing.rendering.integrators.path.slide_weight`)."""
    previous = scene.intersect_surface(*before)
    found = scene.intersect_preliminary(o, d)
    with dr.suspend_grad():
        share = dr.select(previous.valid, slide_share(o, d, found.t, dr.detach(previous.p),
                                                      slide_reach(scene))[0], 0.0)
    return reintersect(scene.instances, o + share * (previous.p - dr.detach(previous.p)), d, found)


def _vertex_term(scene, lights, occluders: Occluders, integrator: str,
                 remaining: "int | UInt32", o: Array3f, d: Array3f, sampler,
                 before: tuple[Array3f, Array3f] | None = None) -> Array3f:
    """The term at the shading points the rays (o, d) find (their hits re-attached along
    the detached rays; sliding near the vertex that the ray ``before`` found, for later
    vertices), with ``remaining`` path segments after them (``path``)."""
    hit = scene.intersect_surface(o, d) if before is None else _slid_hit(scene, o, d, before)
    table = scene.instances
    reach = slide_reach(scene)
    with dr.suspend_grad():
        # The geometric normal offsets rays; the shading normal orients the BSDF. Mirrors
        # (delta lobes) see one direction: no curve of directions to jump across.
        n, sn, ss, p = dr.detach(hit.n), dr.detach(hit.sn), dr.detach(hit.ss), dr.detach(hit.p)
        info = shading(scene, dr.detach(hit), d)
        shade = info.lit & ~scene.bsdfs.mirror(info.material, info.wi)
    if occluders.silhouettes:
        instance, s, tangent, size, convex, valid, inverse_pdf = occluders.sample(
            table, sampler, hit.p, sn, hit.instance, creases=integrator == "path")
    else:
        instance, s, tangent, size = UInt32(0), Array3f(0.0), Array3f(0.0), Float(0.0)
        convex, valid, inverse_pdf = Bool(False), Bool(False), Float(0.0)
    if occluders.shadows is not None and _gathers_twice(remaining):
        # A shadow curve instead, with probability SHADOW_SHARE (1 where nothing moves):
        # the jump of the light that the next vertex gathers from a point or directional
        # light (only where the path goes on past that vertex).
        moving = dr.gather(UInt32, occluders.moving, UInt32(dr.maximum(hit.instance, 0))) != 0
        with dr.suspend_grad():
            share = SHADOW_SHARE if occluders.silhouettes else 1.0
            eligible = Bool(True) if isinstance(remaining, int) else remaining >= 2
            chosen = eligible & (sampler.next_float32() < share)
        z, dz, caster_size, found, shadow_inverse_pdf = occluders.shadows.sample(
            scene, lights, sampler, moving, shade & chosen)
        s = dr.select(chosen, z, s)
        with dr.suspend_grad():
            tangent = dr.select(chosen, dz, tangent)
            size = dr.select(chosen, caster_size, size)
            convex = ~chosen & convex
            valid = dr.select(chosen, found, valid)
            # A silhouette is kept with probability 1 - share where a shadow curve could be
            # taken, else always.
            silhouette_share = dr.select(eligible, 1.0 - share, 1.0)
            inverse_pdf = dr.select(chosen, shadow_inverse_pdf / share,
                                    inverse_pdf / dr.maximum(silhouette_share, 1e-30))
    with dr.suspend_grad():
        # The curve on the sphere of directions around x: direction, unit normal, speed.
        to_s = dr.detach(s) - p
        r = dr.norm(to_s)
        w_s = to_s / r
        t_w = (tangent - w_s * dr.dot(w_s, tangent)) / r
        speed = dr.norm(t_w)
        n_w = dr.normalize(dr.cross(w_s, t_w))
        # A convex model never occludes itself.
        own = convex & (Int32(instance) == hit.instance)
        offset = SIDE_OFFSET * size
        ok = shade & valid & ~own & (r > NEAR_LIMIT * offset) & (speed > 0) & (dr.dot(sn, w_s) > 0)
        # Step 1: both sides' light, split into the emitter-sampled part and the rest,
        # with what each part's sampling holds fixed there (see Step 2).
        key = sampler.next_uint32()
        sides = []
        for sign in (-1.0, 1.0):
            w = dr.normalize(w_s * r + n_w * (sign * offset))
            wo = to_local(sn, w, ss)
            f_cos = scene.bsdfs.evaluate(info.material, info.wi, wo, info.point, info.surface)
            origin = offset_origin(p, n, hit.error, w)
            first = scene.intersect_surface(origin, w, ok)
            arriving = emitted(lights, first, w)
            weight = power_heuristic(
                emitter_pdf(lights, first, w),
                scene.bsdfs.pdf(info.material, info.wi, wo, info.point, info.surface))
            direct_share = arriving * weight
            if integrator == "path":
                arriving = integrate_path(scene, lights, origin, w, sample_streams(key, SIDE_SEED),
                                          remaining, detached=True)
            # The emitter point seen there, in its instance's object space.
            lamp = UInt32(dr.maximum(first.instance, 0))
            sides.append((f_cos * direct_share, f_cos * (arriving - direct_share),
                          weight > 0, lamp, object_point(table.inverse(lamp), first.p), first, w))
        scale = speed * inverse_pdf
        local = to_local(sn, w_s, ss)
    # Step 2: velocities (AD) of the curve relative to what the interior term holds fixed
    # on each side, each 0 in value: the emitter sample's point on the lamp; for the rest,
    # `direct`'s BSDF-sampled direction in the frame of the normal, or `path`'s next
    # vertex, fixed in world space or near x sliding with it (integrators.path; a
    # direction where the ray escapes).
    v_curve = dr.dot(n_w, dr.normalize(s - hit.p))
    moved = hit.p - dr.detach(hit.p)
    result = Array3f(0.0)
    for side, (light_part, rest, on_lamp, lamp, y_obj, first, w) in zip((1.0, -1.0), sides):
        # An area lamp's sample is a point on it; the environment's, a direction.
        w_lamp = dr.select(first.valid, dr.normalize(world_point(table.forward(lamp), y_obj) - hit.p), w)
        if integrator == "path":
            # (A next vertex near x slides with x's motion, as in path replay.)
            with dr.suspend_grad():
                share = dr.select(first.valid, slide_weight(dr.norm(first.p - p), reach)[0], 0.0)
            y = first.p + share * slid(moved, w, first.n)
            w_rest = dr.select(first.valid, dr.normalize(y - hit.p), w)
        else:
            w_rest = to_frame(hit.sn, local, hit.ss)
        v_light = _derivative(v_curve - dr.dot(n_w, w_lamp))
        v_rest = _derivative(v_curve - dr.dot(n_w, w_rest))
        result += side * (dr.select(on_lamp, light_part * v_light, 0.0) + rest * v_rest)
    # (Selected, not multiplied: lanes without a sample may hold NaN directions.)
    return dr.select(ok, scale * result, 0.0)


def _gathers_twice(remaining: "int | UInt32") -> bool:
    """Whether paths with ``remaining`` segments after a vertex may go on past the next
    one (a Python int: -1 unbounded; per-lane counts are tested in the kernel)."""
    return not isinstance(remaining, int) or remaining < 0 or remaining >= 2


def _derivative(x: Float) -> Float:
    """0 in value, with the derivative of x."""
    return x - dr.detach(x)
