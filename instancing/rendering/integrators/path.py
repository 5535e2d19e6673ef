"""Unidirectional path tracing with next-event estimation (Mitsuba's ``path``).

At every diffuse vertex the path gathers direct light exactly as the
``direct`` integrator does (shadow rays to delta lights, one area-emitter
sample with MIS), then continues in a cosine-weighted direction; area emitters
found by that continuation are weighted against emitter sampling by the power
heuristic, and the environment it escapes to with weight 1 (the environment is
found by BSDF sampling alone, see :mod:`instancing.rendering.integrators.direct`).
``max_depth`` counts path segments as in Mitsuba (1: emitters seen directly,
2: direct illumination, -1: unbounded); from depth ``RR_DEPTH`` on,
Russian roulette stops paths with probability 1 - min(max(throughput), 0.95)
and reweights the survivors. The bounce loop is one symbolic Dr.Jit loop.
"""

from __future__ import annotations

from ...core.backend import Array3f, Bool, Float, UInt32, dr
from ...core.warp import power_heuristic
from ...scene.lights import LightSet
from ...scene.scene import Scene
from .direct import emitted, emitter_pdf, sample_bsdf, sample_lights

#: First depth at which Russian roulette may stop a path (Mitsuba's default rr_depth).
RR_DEPTH = 5
#: Survival probability cap of Russian roulette.
RR_MAX_SURVIVAL = 0.95


def integrate_path(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
                   max_depth: int = -1, detached: bool = False) -> Array3f:
    """RGB radiance along unit-direction rays (see the module docstring); ``detached``:
    the caller wants no derivatives (the loop then stays symbolic)."""
    if max_depth == 0:
        return dr.zeros(Array3f, dr.width(o))
    limit = UInt32(0xFFFFFFFF if max_depth < 0 else max_depth)
    width = dr.width(o)
    state = (dr.zeros(Array3f, width) + o, dr.zeros(Array3f, width) + d,
             dr.full(Array3f, 1.0, width), dr.zeros(Array3f, width),  # throughput, radiance
             dr.zeros(UInt32, width), dr.zeros(Float, width),         # depth, previous BSDF pdf
             sampler, dr.full(Bool, True, width))

    def condition(o, d, beta, radiance, depth, pdf_prev, sampler, active):
        return active

    def body(o, d, beta, radiance, depth, pdf_prev, sampler, active):
        hit = scene.intersect_surface(o, d, active)
        # Emission found by the previous BSDF sample (or the camera ray): MIS weighted.
        weight = dr.select(depth == 0, 1.0, power_heuristic(pdf_prev, emitter_pdf(lights, hit, d)))
        radiance += dr.select(active, beta * emitted(lights, hit, d) * weight, 0.0)
        # Stop at misses, back faces and the depth limit; otherwise gather direct light.
        shade = active & hit.valid & (dr.dot(hit.n, d) < 0) & (depth + 1 < limit)
        albedo = scene.albedo(hit)
        direct = sample_lights(scene, lights, hit, shade, albedo, sampler)
        radiance += dr.select(shade, beta * direct, 0.0)
        # Continue the path: BSDF sample (weight albedo), then Russian roulette.
        o_next, d_next, pdf_bsdf = sample_bsdf(hit, sampler)
        beta = beta * albedo
        survive = dr.minimum(dr.max(beta), RR_MAX_SURVIVAL)
        roulette = depth + 1 >= RR_DEPTH
        alive = ~roulette | (sampler.next_float32() < survive)
        beta = dr.select(roulette, beta / survive, beta)
        active = shade & alive & (pdf_bsdf > 0) & (depth + 2 <= limit)
        return o_next, d_next, beta, radiance, depth + 1, pdf_bsdf, sampler, active

    # Reverse-mode AD through an unbounded loop needs the evaluated form (one kernel
    # per bounce, states kept for the backward pass); plain renders stay symbolic.
    mode = "evaluated" if scene.differentiable and not detached else "symbolic"
    result = dr.while_loop(state, condition, body, labels=(
        "o", "d", "beta", "radiance", "depth", "pdf_prev", "sampler", "active"), mode=mode)
    return result[3]
