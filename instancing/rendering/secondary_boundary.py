"""Boundary term of visibility seen from shading points: the penumbrae of area lights and of
the environment, and (in ``path``) what the first bounce's BSDF rays see.

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
:mod:`instancing.rendering.integrators.path`) the next vertex in world space. Each side
of a curve contributes by the curve's velocity relative to those points on that side
(Bangaru et al. 2020's relative velocity), so the jump splits by strategy: the
emitter-sampled part (the light reaching x directly from an area emitter, times its
MIS weight) moves with ``n . (w_s - w_y)``, the rest (the BSDF-sampled share of that
light, the environment and, in ``path``, all indirect light) with ``n . (w_s - w_b)``;
``w_s`` is the direction to the curve point, ``w_y`` to the emitter point seen on that
side and ``w_b`` the BSDF strategy's fixed direction or point. For static lamps and
shading points both reduce to the curve's own motion.

**Estimator.** One sample per camera sample (``sppi`` per pixel, through the film like
the interior): the shading point's hit (AD attached), a candidate, a curve point;
``g`` on both sides of the curve, ``SIDE_OFFSET`` of the occluder's size away,
with the same random numbers; the contribution has value 0 and derivative equal to
the boundary term.

Candidates, picked uniformly: the moving instances (every instance when an area emitter
moves: its light then slides behind static occluders), and every instance for shading
points on moving instances (x moves against static occluders). Left out: the
visibility changes seen from the second and later path vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.backend import Array3f, Bool, Float, Int32, UInt32, device_arrays, dr
from ..core.ray_offset import offset_origin
from ..core.rng import sample_streams
from ..core.transform import object_point, world_point, world_vector
from ..core.warp import INV_PI, power_heuristic, to_frame, to_local
from ..models.analytic import ANALYTIC_MODELS
from ..models.mesh import SilhouetteEdges
from ..scene.description import ConstantLight
from ..scene.instance_table import MESH_KIND
from .integrators.direct import emitted, emitter_pdf
from .integrators.path import integrate_path

#: Distance of the two side rays from the curve point, as a fraction of the occluder's
#: size (its largest axis): far above float32 rounding of the point, far below the
#: scale on which the light varies.
SIDE_OFFSET = 1e-4
#: Curve points nearer to the shading point than this multiple of the side offset are
#: skipped (edges through x itself: the cosine vanishes there).
NEAR_LIMIT = 10.0
#: Seed offset of the side rays' shared random numbers (path continuation).
SIDE_SEED = 0x7F4A7C15


@dataclass
class Occluders:
    """The frame's candidate occluders (padded to a power of two), with what sampling their
    curves needs: the model kinds present, each candidate's kind code, its edge range
    (meshes), its size and whether its model is convex."""

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

    def sample(self, table, u_pick: Float, u: Float, u_choice: Float, x: Array3f, on: Int32,
               creases: bool):
        """Per lane a candidate and a point on its curves seen from world point x on
        instance ``on``: (instance, world point (AD attached), d point / du (detached), its
        size, convex, valid, 1 / pdf of the candidate)."""
        moving = dr.gather(UInt32, self.moving, UInt32(dr.maximum(on, 0))) != 0
        count = dr.select(moving, self.count_all, self.count)
        k = dr.minimum(UInt32(u_pick * Float(count)), count - 1)
        instance = dr.gather(UInt32, self.instance, k)
        kind = dr.gather(UInt32, self.kind, k)
        with dr.suspend_grad():
            view = object_point(table.inverse(instance), dr.detach(x))
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
        rows = table.forward(instance)
        world = world_point(rows, point)
        with dr.suspend_grad():
            world_tangent = world_vector(rows, tangent)
        return (instance, world, world_tangent, dr.gather(Float, self.size, k),
                dr.gather(UInt32, self.convex, k) != 0, valid, Float(count))


def secondary_term_needed(scene, integrator: str) -> bool:
    """Whether light seen from shading points can jump across a moving curve: something
    moves, and the integrator gathers light along rays from them (``path``, or ``direct``
    with area emitters or an environment)."""
    if not len(scene.moving_instances) or integrator == "aov":
        return False
    has_environment = any(isinstance(light, ConstantLight) for light in scene.lights)
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
    return Occluders(capacity, kinds, dr.opaque(UInt32, len(first_choice)),
                     dr.opaque(UInt32, len(candidates)), on_moving, *ints[:4], sizes, ints[4], edges)


def secondary_boundary(scene, lights, occluders: Occluders, integrator: str, max_depth: int,
                       o: Array3f, d: Array3f, sampler) -> Array3f:
    """One sample of the secondary boundary term along camera rays (o, d): value 0,
    derivative the term (see the module docstring)."""
    hit = scene.intersect_surface(o, d)
    table = scene.instances
    with dr.suspend_grad():
        n, p = dr.detach(hit.n), dr.detach(hit.p)
        shade = hit.valid & (dr.dot(n, d) < 0)
        bsdf = scene.albedo(hit) * INV_PI
    instance, s, tangent, size, convex, valid, inverse_pdf = occluders.sample(
        table, sampler.next_float32(), sampler.next_float32(), sampler.next_float32(), hit.p,
        hit.instance,
        creases=integrator == "path")
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
        ok = shade & valid & ~own & (r > NEAR_LIMIT * offset) & (speed > 0) & (dr.dot(n, w_s) > 0)
        # Step 1: both sides' light, split into the emitter-sampled part and the rest,
        # with what each part's sampling holds fixed there (see Step 2).
        key = sampler.next_uint32()
        sides = []
        for sign in (-1.0, 1.0):
            w = dr.normalize(w_s * r + n_w * (sign * offset))
            cos = dr.maximum(dr.dot(n, w), 0.0)
            origin = offset_origin(p, n, hit.error, w)
            first = scene.intersect_surface(origin, w, ok)
            arriving = emitted(lights, first, w)
            weight = power_heuristic(emitter_pdf(lights, first, w), cos * INV_PI)
            direct_share = arriving * weight
            if integrator == "path":
                arriving = integrate_path(scene, lights, origin, w, sample_streams(key, SIDE_SEED),
                                          max_depth - 1, detached=True)
            # The emitter point seen there, in its instance's object space.
            lamp = UInt32(dr.maximum(first.instance, 0))
            sides.append((bsdf * cos * direct_share, bsdf * cos * (arriving - direct_share),
                          weight > 0, lamp, object_point(table.inverse(lamp), first.p), first, w))
        scale = speed * inverse_pdf
        local = to_local(n, w_s)
    # Step 2: velocities (AD) of the curve relative to what the interior term holds fixed
    # on each side, each 0 in value: the emitter sample's point on the lamp; for the rest,
    # `direct`'s BSDF-sampled direction in the frame of the normal, or `path`'s next
    # vertex, fixed in world space (its area form, integrators.path; a direction where
    # the ray escapes).
    v_curve = dr.dot(n_w, dr.normalize(s - hit.p))
    result = Array3f(0.0)
    for side, (light_part, rest, on_lamp, lamp, y_obj, first, w) in zip((1.0, -1.0), sides):
        w_lamp = dr.normalize(world_point(table.forward(lamp), y_obj) - hit.p)
        if integrator == "path":
            w_rest = dr.select(first.valid, dr.normalize(first.p - hit.p), w)
        else:
            w_rest = to_frame(hit.n, local)
        v_light = _derivative(v_curve - dr.dot(n_w, w_lamp))
        v_rest = _derivative(v_curve - dr.dot(n_w, w_rest))
        result += side * (dr.select(on_lamp, light_part * v_light, 0.0) + rest * v_rest)
    # (Selected, not multiplied: lanes without a sample may hold NaN directions.)
    return dr.select(ok, scale * result, 0.0)


def _derivative(x: Float) -> Float:
    """0 in value, with the derivative of x."""
    return x - dr.detach(x)
