"""Unidirectional path tracing with next-event estimation (Mitsuba's ``path``), and its
derivatives by path replay.

At every vertex the path gathers direct light exactly as the ``direct``
integrator does (shadow rays to delta lights, one environment-map and one area-emitter
sample with MIS), then continues in a direction drawn from the material's BSDF; area
emitters and an environment map found by that continuation are weighted against emitter
sampling by the power heuristic (weight 1 after a delta lobe), a constant environment
with weight 1 (it is found by BSDF sampling alone, see
:mod:`instancing.rendering.integrators.direct`).
``max_depth`` counts path segments as in Mitsuba (1: emitters seen directly,
2: direct illumination, -1: unbounded); from depth ``rr_depth`` on (Mitsuba's parameter,
default ``RR_DEPTH``),
Russian roulette stops paths with probability 1 - min(max(throughput) eta^2, 0.95), eta
the product of the relative indices of refraction the path crossed (as Mitsuba's), and
reweights the survivors. The bounce loop is one symbolic Dr.Jit loop.

**Derivatives: path replay backpropagation** (Vicini et al. 2021, "Path Replay
Backpropagation"; Mitsuba's ``prb``). A render with derivatives computes each path's
radiance L without AD (a :class:`drjit.CustomOp`). Its derivative pass replays the same
path, with the same random numbers, in a second symbolic loop, and at each vertex
propagates the adjoint radiance through that vertex's own contribution only,
``Lo = Le + L_direct + L_rest * rel(f cos) * rel(J)``, where ``L_rest`` is the radiance of
the rest of the path (L minus what the vertices so far gave) and ``rel(x)`` is 1 with the
derivative of log x. So memory does not grow with the depth. For the contributions to be
local, the interior term holds the next vertex fixed in world space (the area form of
Zhang et al. 2023 and Mitsuba's ``prb_projective``): each vertex moves with its surface
along its detached incoming ray, and the direction to the next vertex and the
solid-angle-to-area Jacobian J carry the derivative of the current vertex's motion; the
direction from the previous vertex (moving likewise) carries that vertex's motion into
this one's BSDF, as Mitsuba's recomputed ``si.wi`` does. A next vertex near the current one
slides with it instead (:func:`slide_weight`): held fixed there, it would give the light
bounced between touching surfaces an interior term of infinite variance. A delta lobe fixes where its ray
goes: the vertex after it moves with that ray, sent from the moving vertex in the
direction the lobe gives for the moving incoming direction and normal (a mirror's
reflection, a glass's refraction, chains of them up to ``HISTORY_CAP`` - 1 long; the
replay re-intersects the vertices of the chain in each step).
The boundary terms measure their curves' velocities relative to those fixed points
(:mod:`instancing.rendering.secondary_boundary`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...core.backend import Array3f, Bool, Float, UInt32, dr
from ...core.ray_offset import offset_origin
from ...core.warp import power_heuristic, to_frame
from ...scene.intersection import PreliminaryHit, reintersect
from ...scene.lights import LightSet
from ...scene.scene import Scene
from ...core.warp import to_local
from ...materials.bsdf import BSDFSample
from .direct import (differentiable_state, emitted, emitter_pdf, relative, sample_bsdf, sample_lights,
                     shading)

#: First depth at which Russian roulette may stop a path (Mitsuba's default rr_depth).
RR_DEPTH = 5
#: Survival probability cap of Russian roulette.
RR_MAX_SURVIVAL = 0.95


def _limit(max_depth: "int | UInt32") -> UInt32:
    """The depth limit as a UInt32 (unbounded: the largest); per lane when given per lane."""
    if isinstance(max_depth, UInt32):
        return max_depth
    return UInt32(0xFFFFFFFF if max_depth < 0 else max_depth)


def _vertex(scene: Scene, lights: LightSet, hit, d: Array3f, beta: Array3f, depth: UInt32,
            pdf_prev: Float, delta_prev: Bool, sampler, active: Bool, limit: UInt32,
            hide_emitters: bool):
    """One path vertex: (emission found there, MIS weighted, times beta, none by the camera
    ray with ``hide_emitters``; direct light gathered there times beta; its shading; whether
    it shades; the continuation ray and its BSDF sample)."""
    info = shading(scene, hit, d)
    # Emission found by the previous BSDF sample (or the camera ray): MIS weighted.
    with dr.suspend_grad():
        weight = dr.select((depth == 0) | delta_prev, 1.0,
                           power_heuristic(pdf_prev, emitter_pdf(lights, hit, d)))
        shade = active & dr.detach(info.lit) & (depth + 1 < limit)
    found = dr.select(active & (depth > 0) if hide_emitters else active,
                      beta * emitted(lights, hit, d) * weight, 0.0)
    # Stop at misses, sides that do not reflect and the depth limit; otherwise gather
    # direct light and draw the continuation.
    def scatter(sampler):
        direct = dr.select(shade, beta * sample_lights(scene, lights, hit, info, shade, sampler,
                                                       mis_derivatives=False), 0.0)
        with dr.suspend_grad():
            detached = dr.detach(hit)
            o_next, d_next, sample = sample_bsdf(scene, detached, shading(scene, detached, d),
                                                 sampler)
        return direct, o_next, d_next, tuple(vars(sample).values()), sampler

    if dr.grad_enabled(beta, info, differentiable_state(scene, lights)):
        # (A symbolic branch would carry the AD graph through a conditional.)
        direct, o_next, d_next, sample, _ = scatter(sampler)
    else:
        # A branch that SIMD packets in which no lane shades skip (a path's last vertex,
        # misses); their lanes end here and draw no more random numbers. Its condition and
        # results are given for every ray.
        lanes = dr.width(d)
        direct, o_next, d_next, sample, drawn = dr.if_stmt(
            (sampler,), shade | dr.zeros(Bool, lanes), scatter,
            lambda sampler: _dark(sampler, lanes), mode="symbolic")
        sampler.take_state(drawn)
    return found, direct, info, shade, o_next, d_next, BSDFSample(*sample)


def _dark(sampler, lanes: int) -> tuple:
    """What a vertex that does not shade gathers and continues with: nothing."""
    zero, none, no = dr.zeros(Array3f, lanes), dr.zeros(Float, lanes), dr.zeros(Bool, lanes)
    return zero, zero, zero, (zero, zero, none, no, no, (none,) * 3, no, none + 1.0), sampler


def _continue(beta: Array3f, eta: Float, sample: BSDFSample, depth: UInt32, shade: Bool,
              sampler, limit: UInt32, rr_depth: int) -> tuple[Array3f, Float, Bool]:
    """The throughput after the BSDF sample (its weight) and Russian roulette, the product
    of the relative indices of refraction crossed, and whether the path goes on."""
    beta = beta * sample.weight
    eta = dr.select(shade, eta * sample.eta, eta)
    survive = roulette_survival(beta, eta)
    roulette = depth + 1 >= rr_depth
    alive = ~roulette | (sampler.next_float32() < survive)
    beta = dr.select(roulette, beta / survive, beta)
    return beta, eta, shade & alive & sample.valid & (depth + 2 <= limit)


def roulette_survival(beta: Array3f, eta: Float) -> Float:
    """Russian roulette's survival probability, as Mitsuba's: the throughput's largest
    channel times eta^2 (the radiance a refraction scaled by 1 / eta^2 counted unscaled, so
    that paths inside glass are not cut short only for its index), at most RR_MAX_SURVIVAL."""
    return dr.minimum(dr.max(beta) * dr.square(eta), RR_MAX_SURVIVAL)


def _primal(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
            max_depth: "int | UInt32", rr_depth: int, hide_emitters: bool = False,
            alpha: bool = False) -> "Array3f | tuple[Array3f, Float]":
    """Radiance along the rays, without derivatives (one symbolic loop); with ``alpha``,
    also the paths' alpha (:func:`integrate_path`)."""
    limit = _limit(max_depth)
    width = dr.width(o)
    state = (dr.zeros(Array3f, width) + o, dr.zeros(Array3f, width) + d,
             dr.full(Array3f, 1.0, width), dr.zeros(Array3f, width),  # throughput, radiance
             dr.zeros(UInt32, width), dr.zeros(Float, width),         # depth, previous BSDF pdf
             dr.zeros(Bool, width), dr.opaque(Float, 1.0, width),       # previous lobe delta, eta
             sampler, dr.full(Bool, True, width))
    if alpha:
        # Rays that see the environment are covered from the start.
        state += (dr.full(Bool, not hide_emitters and lights.environment is not None, width),)

    def body(o, d, beta, radiance, depth, pdf_prev, delta_prev, eta, sampler, active, *covered):
        hit = scene.intersect_surface(o, d, active)
        found, direct, info, shade, o_next, d_next, sample = _vertex(
            scene, lights, hit, d, beta, depth, pdf_prev, delta_prev, sampler, active, limit,
            hide_emitters)
        if alpha:
            covered = (covered[0] | (active & _covers(scene, hit, info, sample, shade, sampler)),)
        radiance += found
        radiance += direct
        beta, eta, active = _continue(dr.detach(beta), eta, sample, depth, shade, sampler, limit,
                                      rr_depth)
        return (o_next, d_next, beta, radiance, depth + 1, sample.pdf, sample.delta, eta, sampler,
                active) + covered

    with dr.suspend_grad():
        result = dr.while_loop(state, lambda *s: s[9], body, labels=(
            "o", "d", "beta", "radiance", "depth", "pdf_prev", "delta_prev", "eta", "sampler",
            "active") + (("covered",) if alpha else ()))
    return (result[3], dr.select(result[10], 1.0, 0.0)) if alpha else result[3]


def _covers(scene: Scene, hit, info, sample: BSDFSample, shade: Bool, sampler) -> Bool:
    """Whether a path vertex makes its pixel sample opaque (the valid ray of Mitsuba's
    ``path``, as its JIT variants set it): a surface whose BSDF sample did not pass straight
    through. Where the path stops there (its last vertex, an unlit side), the BSDF is sampled
    for this alone where some material passes light, from a copy of the sampler: the path's
    own numbers stay as they are."""
    if not scene.bsdfs.passes_light:
        return hit.valid
    # (Only the sampled lobe is needed: no continuation ray, no weight's derivatives.)
    last = scene.bsdfs.sample(info.material, dr.detach(info.wi), sampler.copy(), *info.detached())
    return hit.valid & ~dr.select(shade, sample.null, last.null)


def integrate_path(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
                   max_depth: "int | UInt32" = -1, detached: bool = False,
                   rr_depth: int = RR_DEPTH, hide_emitters: bool = False,
                   alpha: bool = False) -> "Array3f | tuple[Array3f, Float]":
    """RGB radiance along unit-direction rays (see the module docstring); with derivatives
    (grad-enabled scene parameters, not ``detached``) by path replay. A per-lane
    ``max_depth`` (UInt32) is taken detached. ``hide_emitters``: without the emitters the
    rays see (rays that start :func:`~instancing.rendering.integrators.direct.past_emitters`).
    With ``alpha``, also each path's alpha (1 or 0, no derivative), as Mitsuba's ``path``
    sets it: 1 where the environment is seen, or where the path meets a surface whose BSDF
    sample does not pass straight through (:func:`_covers`)."""
    if isinstance(max_depth, UInt32):
        return _primal(scene, lights, o, d, sampler, max_depth, rr_depth, hide_emitters, alpha)
    if max_depth == 0:
        black = dr.zeros(Array3f, dr.width(o))
        return (black, dr.zeros(Float, dr.width(o))) if alpha else black
    state = differentiable_state(scene, lights)
    if detached or not dr.grad_enabled(state):
        return _primal(scene, lights, o, d, sampler, max_depth, rr_depth, hide_emitters, alpha)
    return dr.custom(_PathReplay, scene, lights, o, d, sampler.copy(),
                     (max_depth, rr_depth, hide_emitters), alpha,
                     sampler, state)


def _install(scene: Scene, lights: LightSet, state: dict) -> None:
    """Make ``state`` (as :func:`_differentiable_state` returns it) the scene's arrays."""
    scene.instances.restore_rows((state["inverse_rows"], state["forward_linear"]))
    scene.bsdfs.restore({key.split(".", 1)[1]: value for key, value in state.items()
                         if key.startswith("material.")})
    lights.delta = [dataclasses.replace(light, vector=vector, power=power) for light, vector, power
                    in zip(lights.delta, state["vectors"], state["powers"])]
    lights.texture_arrays = state["light_textures"]
    if lights.area_instances:
        lights.radiance = state["emitted"][0]
    if lights.environment is not None:
        lights.environment.values = state["environment"][0]


class _PathReplay(dr.CustomOp):
    """Path radiance as one differentiable operation: primal without AD, derivatives by
    replaying the paths (see the module docstring)."""

    def eval(self, scene, lights, o, d, replay_stream, depths, alpha, sampler, state):
        self.scene, self.lights, self.o, self.d = scene, lights, o, d
        self.stream, self.depths, self.alpha = replay_stream, depths, alpha
        primal = _primal(scene, lights, o, d, sampler, *depths, alpha)
        self.radiance = primal[0] if alpha else primal
        return primal

    def _leaves(self, gradients: dict | None) -> dict:
        """Detached copies of the scene's differentiable arrays, grad-enabled where the
        scene's own array is (with ``gradients`` as their forward-mode derivatives)."""
        current = differentiable_state(self.scene, self.lights)
        leaves = {}
        for key, value in current.items():
            values = value if isinstance(value, list) else [value]
            copies = [dr.detach(v) for v in values]
            for i, (v, copy) in enumerate(zip(values, copies)):
                if dr.grad_enabled(v):
                    dr.enable_grad(copy)
                    if gradients is not None:
                        dr.set_grad(copy, gradients[key][i] if isinstance(value, list)
                                    else gradients[key])
            leaves[key] = copies if isinstance(value, list) else copies[0]
        return leaves

    def _replay(self, leaves: dict, adjoint: Array3f | None) -> Array3f:
        """Replay the paths with the leaves installed: backward (``adjoint``: the radiance's
        adjoint, gradients accumulate in the leaves) or forward (returns the radiance's
        derivative)."""
        scene, lights = self.scene, self.lights
        saved = differentiable_state(scene, lights)
        _install(scene, lights, leaves)
        try:
            return _replay_loop(scene, lights, self.o, self.d, self.stream.copy(),
                                *self.depths, self.radiance, adjoint)
        finally:
            _install(scene, lights, saved)

    def forward(self):
        radiance = self._replay(self._leaves(self.grad_in("state")), None)
        # (The alpha is piecewise constant: its derivative is the boundary terms'.)
        self.set_grad_out((radiance, dr.zeros(Float, dr.width(radiance))) if self.alpha else radiance)

    def backward(self):
        leaves = self._leaves(None)
        self._replay(leaves, self.grad_out()[0] if self.alpha else self.grad_out())
        self.set_grad_in("state", {k: dr.grad(v) for k, v in leaves.items()})

    def name(self):
        return "PathReplay"


#: Vertices a replayed vertex looks back through for its derivatives, at most: each one
#: a delta lobe passed on its motion to the next (a mirror, a glass's two faces) costs
#: one more re-intersection per vertex in the replay; longer chains of delta lobes keep
#: the motion of their last HISTORY_CAP - 1 vertices only.
HISTORY_CAP = 4
#: Reach of the slide near a vertex, as a fraction of the scene's bounding-box diagonal:
#: a next vertex nearer than this slides with the vertex before it (see :func:`slide_weight`).
SLIDE_REACH = 0.01


def _history_length(scene: Scene, max_depth: int) -> int:
    """How many earlier vertices the replay keeps: where instances move, the previous one
    (whose motion slides a near vertex, :func:`slide_weight`) and the one before it where a
    BSDF reads the incoming direction (the previous vertex's own slide moves it); else the
    previous one where a BSDF reads it; and where delta lobes may chain vertices, as many as
    a path of ``max_depth`` can chain (at most HISTORY_CAP). None where nothing needs one."""
    if len(scene.moving_instances):
        needed = 2 if scene.bsdfs.reads_incoming else 1
    else:
        needed = int(scene.bsdfs.reads_incoming)
    if scene.bsdfs.has_delta:
        needed = max(needed, HISTORY_CAP)
    return needed if max_depth < 0 else min(max(1, max_depth - 1), needed)


def slide_reach(scene: Scene) -> Float:
    """The distance within which a next vertex slides with its predecessor (SLIDE_REACH of
    the scene's bounding-box diagonal)."""
    lo, hi = scene.bounds
    return dr.opaque(Float, max(SLIDE_REACH * float(np.linalg.norm(hi - lo)), 1e-30))


def slide_weight(r: Float, reach: Float) -> tuple[Float, Float]:
    """The share s(r) of a next vertex's slide at distance r from its predecessor, and ds/dr:
    1 at r = 0, falling smoothly (cubic) to 0 at ``reach``.

    A vertex y held fixed while its predecessor x moves makes the interior term's relative
    derivatives grow like 1 / r (the direction x -> y and the geometry term): where two
    surfaces meet, paths that bounce between them near their contact line have an interior
    term of infinite variance. Any motion of the path's vertices along their surfaces gives
    the same derivative (the boundary terms measuring velocities relative to it), so a near
    y instead moves with s(r) times the motion that the ray from the moving x, its direction
    fixed, gives it (:func:`slid`): then the direction x -> y and the geometry term times
    y's area element do not change with x's motion but for that share. The change of area
    of this motion adds ds/dr (w . q) (w the unit direction x -> y, q the slide of y).
    The slide is taken from x's own motion (along its own detached ray, or with the delta
    lobe before it), not from x's slide, so that it is known from the previous vertex."""
    u = dr.minimum(r / reach, 1.0)
    return 1.0 - u * u * (3.0 - 2.0 * u), 6.0 * u * (u - 1.0) / reach


def slide_share(o: Array3f, d: Array3f, t: Float, before: Array3f, reach: Float) -> tuple[Float, Float]:
    """slide_weight of the hit at distance t along the ray (o, d) from the point ``before``
    (0 where the ray escapes; detached values, the same in every replay step that needs it)."""
    found = dr.isfinite(t)
    share, slope = slide_weight(dr.norm(o + d * dr.select(found, t, 0.0) - before), reach)
    return dr.select(found, share, 0.0), dr.select(found, slope, 0.0)


def slid(motion: Array3f, d: Array3f, n: Array3f) -> Array3f:
    """How far the hit of a ray with direction d moves on a surface of normal n (detached)
    when the ray's origin moves by ``motion``, to first order (0 where the ray grazes it or
    n is 0: no hit)."""
    across = dr.dot(n, d)
    return dr.select(across != 0, motion - d * (dr.dot(n, motion) / across), 0.0)


def _empty_history(length: int, width: int) -> tuple:
    """Loop state of :func:`_replayed_hit`'s history: per earlier vertex its detached ray,
    preliminary hit, whether it scattered by a delta lobe, and that sample's random numbers."""
    return tuple((dr.zeros(Array3f, width), dr.zeros(Array3f, width),
                  (dr.zeros(Float, width), dr.zeros(UInt32, width), dr.zeros(UInt32, width)),
                  dr.zeros(Bool, width), (dr.zeros(Float, width),) * 3) for _ in range(length))


@dataclasses.dataclass
class _Before:
    """The vertex before the one being re-entered: its own motion (AD; its slide left out),
    its whole motion (AD), and whether it exists."""

    own: Array3f
    whole: Array3f
    exists: Bool


def _replayed_hit(scene: Scene, history: tuple, o: Array3f, d: Array3f, preliminary: tuple,
                  depth: UInt32, reach: Float):
    """The replayed vertex's surface record and incoming direction d (values unchanged) with
    the derivatives of the vertices before it, oldest first through ``history``, and its own
    motion (AD). A vertex after a delta lobe moves with the ray that lobe sends from the
    (moving) vertex before it; any other vertex moves along its detached ray, and near the
    vertex before it slides with that one's own motion (:func:`slide_weight`); the direction
    from the vertex before it carries that vertex's motion into the BSDF here (as Mitsuba's
    recomputed ``si.wi``)."""
    chained, o_sent, d_sent = Bool(False), Array3f(0.0), Array3f(0.0)
    before = _Before(Array3f(0.0), Array3f(0.0), Bool(False))
    for i, (o_j, d_j, preliminary_j, delta_j, u_j) in enumerate(history):
        exists = depth >= len(history) - i
        hit, d_in, own = _entered(scene, o_j, d_j, preliminary_j, chained, o_sent, d_sent, before, reach)
        if scene.bsdfs.has_delta:
            info = shading(scene, hit, d_in)
            sample = scene.bsdfs.sample_from(info.material, info.wi, u_j, info.point, info.surface)
            d_sent = to_frame(hit.sn, sample.wo, hit.ss)
            o_sent = offset_origin(hit.p, hit.n, hit.error, d_sent)
            chained = exists & delta_j
        before = _Before(own, hit.p, exists & hit.valid)
    return _entered(scene, o, d, preliminary, chained, o_sent, d_sent, before, reach)


def _entered(scene: Scene, o: Array3f, d: Array3f, preliminary: tuple, chained: Bool, o_sent: Array3f,
             d_sent: Array3f, before: _Before, reach: Float):
    """One step of :func:`_replayed_hit`: the hit of the detached ray (o, d), moving with the
    ray (o_sent, d_sent) where ``chained``, else sliding with ``before`` where near; its
    incoming direction; its own motion (the hit's, its slide left out)."""
    with dr.suspend_grad():
        near = before.exists & ~chained
        share = dr.select(near, slide_share(o, d, preliminary[0], dr.detach(before.whole), reach)[0], 0.0)
    moved_before = before.own - dr.detach(before.own)
    o_in = dr.select(chained, dr.replace_grad(o, o_sent), o + share * moved_before)
    d_ray = dr.select(chained, dr.replace_grad(d, d_sent), d)
    hit = reintersect(scene.instances, o_in, d_ray, PreliminaryHit(*preliminary))
    # (The slide moves the hit as the ray's origin moves it; across d, by share times the
    # previous vertex's own motion.)
    own = hit.p - share * slid(moved_before, d, dr.detach(hit.n))
    to_here = dr.detach(hit.p) + share * moved_before - before.whole
    moved = dr.replace_grad(d, to_here / dr.norm(to_here))
    return hit, dr.select(chained, d_ray, dr.select(before.exists & hit.valid, moved, d)), own


def _replay_loop(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
                 max_depth: int, rr_depth: int, hide_emitters: bool, radiance: Array3f,
                 adjoint: Array3f | None) -> Array3f:
    """The derivative pass of path replay: backward when ``adjoint`` is given, else
    forward (returns the derivative of the radiance)."""
    limit = _limit(max_depth)
    width = dr.width(o)
    reach = slide_reach(scene)
    first = scene.intersect_preliminary(o, d)
    # (The preliminary hit travels as its three fields: loop state must be assignable.)
    state = (dr.zeros(Array3f, width) + o, dr.zeros(Array3f, width) + d,
             (first.t, first.instance, first.position),
             _empty_history(_history_length(scene, max_depth), width),
             dr.full(Array3f, 1.0, width), dr.zeros(Array3f, width) + radiance,
             dr.zeros(UInt32, width), dr.zeros(Float, width), dr.zeros(Bool, width),
             dr.opaque(Float, 1.0, width), sampler, dr.full(Bool, True, width), dr.zeros(Array3f, width))

    def body(o, d, preliminary, history, beta, rest, depth, pdf_prev, delta_prev, eta, sampler, active,
             tangent):
        with dr.resume_grad():
            # The vertex moves with its surface along the detached ray (after a delta lobe,
            # along the ray the lobe sends; near the previous vertex, sliding with it).
            hit, d_in, own = _replayed_hit(scene, history, o, d, preliminary, depth, reach)
            found, direct, info, shade, o_next, d_next, sample = _vertex(
                scene, lights, hit, d_in, beta, depth, pdf_prev, delta_prev, sampler, active, limit,
                hide_emitters)
            rest = rest - dr.detach(found + direct)
            # The next vertex, fixed in world space: the direction to it and the
            # solid-angle-to-area Jacobian carry this vertex's motion; a near one slides
            # with its own motion (slide_weight), which leaves them that share unchanged.
            with dr.suspend_grad():
                following = scene.intersect_preliminary(o_next, d_next, shade)
                y = reintersect(scene.instances, o_next, d_next, following)
                share, share_slope = slide_share(o_next, d_next, following.t, dr.detach(hit.p), reach)
                sliding = y.valid & ~sample.delta
                share, share_slope = dr.select(sliding, share, 0.0), dr.select(sliding, share_slope, 0.0)
            moved = own - dr.detach(own)
            to_y = y.p - (hit.p - share * moved)
            distance2 = dr.squared_norm(to_y)
            w = dr.select(y.valid, to_y / dr.sqrt(distance2), d_next)
            jacobian = dr.select(y.valid, dr.abs(dr.dot(y.n, w)) / distance2, 1.0)
            # The slide's change of area at y: ds/dr (w . q), q its slide.
            area = 1.0 + share_slope * dr.dot(dr.detach(w), slid(moved, d_next, y.n))
            f_cos = scene.bsdfs.evaluate(info.material, info.wi, to_local(hit.sn, w, hit.ss), info.point,
                                         info.surface)
            # (After a delta lobe the next vertex cannot be held fixed: it moves with the
            # ray the lobe sends (_replayed_hit), and here the lobe's weight, redone with the
            # moving wi, carries the materials' parameters and the Fresnel choice.)
            scattered = dr.select(shade & ~sample.delta, rest * relative(f_cos)
                                  * relative(jacobian) * relative(area), 0.0)
            if scene.bsdfs.has_delta:
                redone = scene.bsdfs.sample_from(info.material, info.wi, sample.u, *info.detached())
                scattered += dr.select(shade & sample.delta, rest * relative(redone.weight), 0.0)
            contribution = found + direct + scattered
            # (A parameter may reach no vertex: a polarizer's angle, which unpolarized light
            # does not see, gives derivative 0, as in `direct`.)
            no_grad = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
            if adjoint is not None:
                dr.backward_from(adjoint * contribution, flags=no_grad)
            else:
                tangent += dr.forward_to(contribution, flags=no_grad)
        beta, eta, active = _continue(dr.detach(beta), eta, sample, depth, shade, sampler, limit,
                                      rr_depth)
        return (o_next, d_next, (following.t, following.instance, following.position),
                (history + ((o, d, preliminary, sample.delta, sample.u),))[1:], beta, rest, depth + 1,
                sample.pdf, sample.delta, eta, sampler, active, tangent)

    result = dr.while_loop(state, lambda *s: s[11], body, labels=(
        "o", "d", "preliminary", "history", "beta", "rest", "depth", "pdf_prev", "delta_prev", "eta",
        "sampler", "active", "tangent"))
    return result[-1]
