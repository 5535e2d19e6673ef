"""Direct illumination: emitted light seen by the camera plus one bounce of light.

At each camera hit, on the side its material reflects (Mitsuba's BSDFs are
one-sided unless ``twosided``: :mod:`instancing.materials.bsdf`), the integrator adds

* every point and directional light through a shadow ray (delta lights: no MIS);
* one sample of an environment map (:mod:`instancing.scene.environment`) and one of
  one area emitter picked uniformly, each weighted by the power heuristic against the
  BSDF's density;
* one BSDF sample, whose ray may hit an area emitter's front or escape to the
  environment (weighted by the power heuristic against the emitter-sampling density;
  Veach 1997, multiple importance sampling; weight 1 after a delta lobe).

Mitsuba's ``emitter_samples`` and ``bsdf_samples`` (:func:`strategy_samples`) take E
emitter samples (environment and area emitter) and B BSDF samples instead, each weighted
by the power heuristic of the densities times the counts and divided by its count; E = 0
samples no lights at all (point and directional lights neither, as Mitsuba), B = 0 no BSDF
rays (emitter samples then have weight 1).

The constant environment is found by BSDF sampling alone, with weight 1 (as
pbrt-v4's uniform infinite light when the integrator allows incomplete pdfs):
for a diffuse surface the cosine-weighted direction is the ideal importance
sample of an unoccluded constant environment, so a uniform-sphere emitter
sample with its own shadow ray (Mitsuba's ``constant`` emitter sampling) adds
a ray and no accuracy. Measured, 128x96, kernel time with / without that emitter
sample: forest path (4 spp) 234 -> 182 ms, forest direct (16 spp) 298 -> 212 ms,
light_constant direct (64 spp) 53 -> 36 ms, at equal or lower error per sample.

Only the light types present in the scene are traced; without lights the
integrator casts no shadow or BSDF rays at all. The pieces are shared with
the path tracer, which repeats them at every vertex.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

from ...core.arguments import integer
from ...core.backend import Array2f, Array3f, Bool, Float, Int32, UInt32, dr
from ...core.errors import SceneError
from ...core.ray_offset import SHADOW_SHORTENING, offset_origin, shadow_distance
from ...core.warp import power_heuristic, to_frame, to_local
from ...materials.bsdf import BSDFSample
from ...materials.bump_map import SurfaceFrame
from ...materials.texture import Coordinates
from ...scene.intersection import MISS, PreliminaryHit, intersect_preliminary, reintersect
from ...scene.lights import LightSet
from ...scene.scene import Scene


def emitted(lights: LightSet, hit, d: Array3f, escaped: Bool | None = None) -> Array3f:
    """Radiance the ray sees directly: area emitters' fronts and, where it escaped (by
    default: where ``hit`` is not valid), the environment."""
    escaped = ~hit.valid if escaped is None else escaped
    radiance = Array3f(0.0)
    if lights.environment is not None:
        radiance += dr.select(escaped, lights.environment.radiance(d), 0.0)
    if lights.area_instances:
        is_emitter, slot = lights.is_area_emitter(hit.instance)
        seen = is_emitter & (dr.dot(hit.n, d) < 0)
        radiance += dr.select(seen, lights.emitter_radiance(slot, hit.uv, seen), 0.0)
    return radiance


def past_emitters(scene: Scene, lights: LightSet, o: Array3f, d: Array3f) -> Array3f:
    """Ray origins moved past the area emitters that the rays (o, d) meet before any other
    surface, front or back (Mitsuba's ``hide_emitters``: camera rays see through them)."""
    if not lights.area_instances:
        return o

    def body(o, active):
        hit = scene.intersect_surface(o, d, active)
        active &= hit.valid & lights.is_area_emitter(hit.instance)[0]
        return dr.select(active, offset_origin(hit.p, hit.n, hit.error, d), o), active

    return dr.while_loop((dr.zeros(Array3f, dr.width(d)) + o, dr.full(Bool, True, dr.width(d))),
                         lambda o, active: active, body, labels=("o", "active"))[0]


def emitter_pdf(lights: LightSet, hit, w: Array3f, escaped: Bool | None = None,
                origin: Array3f | None = None, environment_pick: Float | None = None) -> Float:
    """Solid-angle density with which emitter sampling would have produced the ray (o, w)
    that found ``hit``: on the fronts of area emitters, and where it escaped (by default:
    where ``hit`` is not valid) an environment map's (a constant environment's only with
    ``environment_pick``, per lane the factor on the environment's density that
    :func:`gather_light` took where the ray left). ``origin``: where the ray left (by default
    ``hit.t`` back from the hit's point), from which a round sphere is sampled by its cone."""
    density = Float(0.0)
    if lights.environment is not None and (lights.environment.sampled or (
            environment_pick is not None and lights.environment.constant is not None)):
        escaped = ~hit.valid if escaped is None else escaped
        density = lights.environment.pdf(w)
        if environment_pick is not None:
            density *= environment_pick
        density = dr.select(escaped, density, 0.0)
    area_count = len(lights.area_instances)
    if not area_count:
        return density
    is_emitter, slot = lights.is_area_emitter(hit.instance)
    cos_y = -dr.dot(hit.n, w)
    area = lights.area_pdf(slot, hit.n) * hit.t * hit.t / dr.abs(cos_y)
    if lights.cones_sampled:
        cone = lights.cone_pdf(slot, hit.p - w * hit.t if origin is None else origin)
        area = dr.select(cone > 0, cone, area)
    area = area / area_count
    return dr.select(is_emitter & (cos_y > 0), area, density)


@dataclass(frozen=True)
class Shading:
    """What the BSDF reads at a hit: the material, the direction towards the viewer in the
    shading frame (+z the shading normal), whether the side it sees reflects, and where its
    textures are looked up (:meth:`Scene.lookup_point <instancing.scene.scene.Scene.lookup_point>`)."""

    material: UInt32
    wi: Array3f
    lit: Bool
    point: Coordinates
    surface: SurfaceFrame | None = None

    def detached(self) -> tuple[Coordinates, SurfaceFrame | None]:
        """The lookup point and surface derivatives, detached (for a sample's direction)."""
        return dr.detach(self.point), None if self.surface is None else dr.detach(self.surface)


def shading(scene: Scene, hit, d: Array3f) -> Shading:
    """The :class:`Shading` of rays with directions ``d`` at their hits (with the surface's
    derivatives and geometric normal in the shading frame where a material is bump-mapped)."""
    material = scene.material_of(hit)
    wi = to_local(hit.sn, -d, hit.ss)
    surface = (SurfaceFrame(*(to_local(hit.sn, v, hit.ss) for v in (hit.dpdu, hit.dpdv, hit.n)))
               if scene.bsdfs.bump_mapped else None)
    return Shading(material, wi, hit.valid & scene.bsdfs.reflects(material, wi), scene.lookup_point(hit),
                   surface)


#: Samples per strategy of the direct integrator at most (each is traced in the kernel).
MAX_STRATEGY_SAMPLES = 64


def strategy_samples(emitter_samples: Any, bsdf_samples: Any, where: str = "") -> tuple[int, int]:
    """The direct integrator's (emitter samples, BSDF samples) per camera hit, checked:
    integers from 0 to :data:`MAX_STRATEGY_SAMPLES`, not both 0 (Mitsuba's
    ``emitter_samples`` and ``bsdf_samples``)."""
    counts = tuple(integer(name, value, 0, MAX_STRATEGY_SAMPLES, where)
                   for name, value in (("emitter_samples", emitter_samples), ("bsdf_samples", bsdf_samples)))
    if counts == (0, 0):
        raise SceneError(f"{where + ': ' if where else ''}emitter_samples and bsdf_samples are both "
                         "0: nothing would sample the light")
    return counts


def strategy_weight(pdf: Float, count: int, pdf_other: Float, other: int) -> Float:
    """MIS weight of one of ``count`` samples of a strategy against ``other`` samples of
    another: the power heuristic of the densities times the counts, divided by ``count``
    (1 / count where the other strategy takes no samples)."""
    if other == 0:
        return dr.select(pdf > 0, 1.0 / count, 0.0)
    weight = (power_heuristic(pdf, pdf_other) if count == other
              else power_heuristic(pdf * count, pdf_other * other))
    return weight if count == 1 else weight / count


def sample_lights(scene: Scene, lights: LightSet, hit, info: Shading, shade: Bool,
                  sampler, mis_derivatives: bool = True,
                  transmittance: Callable | None = None,
                  strategies: tuple[int, int] = (1, 1)) -> Array3f:
    """Light arriving directly from the lights at a hit, reflected towards the viewer.

    Delta lights by one shadow ray each; one area emitter (picked uniformly) by one
    sample (a point by area, or on a round sphere by its cone: ``LightSet.sphere_cones``)
    weighted against BSDF sampling; an environment map by one sample likewise (the
    terms of :func:`surface_terms`). A shadow ray is traced only where the BSDF reflects
    that light. ``mis_derivatives``: whether the MIS weights
    carry derivatives (they must where the BSDF strategy holds its direction in the
    shading frame, :func:`sample_bsdf`; not where both strategies hold the next vertex
    fixed, as path replay does: there the two weights sum to 1 for every path and their
    derivatives cancel). ``transmittance``, ``strategies``: see :func:`gather_light`.
    """
    return gather_light(scene, lights, hit.p, *surface_terms(scene, hit, info), shade, sampler,
                        mis_derivatives, transmittance, strategies)


def surface_terms(scene: Scene, hit, info: Shading) -> tuple[Callable, Callable, Callable]:
    """The ``spawn``, ``scatter`` and ``density`` of :func:`gather_light` at surface hits:
    shadow rays start off the surface (the geometric normal ``n``) by the hit's error bound
    (:mod:`instancing.core.ray_offset`); the BSDF and its density are evaluated in the frame
    of the shading normal ``sn``."""
    bsdfs = scene.bsdfs

    def local(w: Array3f) -> Array3f:
        return to_local(hit.sn, w, hit.ss)

    return (lambda towards: offset_origin(hit.p, hit.n, hit.error, towards),
            lambda w: bsdfs.evaluate(info.material, info.wi, local(w), info.point, info.surface),
            lambda w: bsdfs.pdf(info.material, info.wi, local(w), info.point, info.surface))


def gather_light(scene: Scene, lights: LightSet, p: Array3f, spawn: Callable, scatter: Callable,
                 density: Callable, shade: Bool, sampler, mis_derivatives: bool = True,
                 transmittance: Callable | None = None,
                 strategies: tuple[int, int] = (1, 1), point_lights: Bool | None = None,
                 environment_pick: Float | None = None) -> Array3f:
    """Light arriving directly from the lights at points ``p`` and scattered there (as
    :func:`sample_lights` describes for surfaces): ``spawn(towards)`` is the origin of a
    shadow ray leaving towards ``towards``; ``scatter(w)`` what the point scatters of light
    arriving from world direction w (a BSDF value times the cosine, a phase function);
    ``density(w)`` the solid-angle density of the point's own sampling of w, for MIS.
    ``transmittance(origin, w, t_max, active)``: the fraction of light that reaches the point
    along each shadow ray (per channel; by default 1 where nothing lies on the ray, else 0).
    ``strategies``: (E, B), E >= 1 samples of the environment and the area emitters, weighted
    against B samples of the point's own (:func:`strategy_weight`). ``point_lights``: where
    the point lights are gathered (None: everywhere). ``environment_pick``: per lane, the
    factor on the environment's density in the MIS weights (any factor keeps the weights of
    both strategies summing to 1, where :func:`emitter_pdf` takes the same), and a constant
    environment is drawn too (uniformly over the sphere) where it is above 0; without it, a
    constant environment is drawn only where the point takes no samples of its own (B = 0).
    :mod:`.volpath` gives Mitsuba's chance of picking the environment among its emitters in
    media that no surface bounds, whose points' own samples never reach the environment.
    """
    result = Array3f(0.0)
    emitters, scatters = strategies

    def mis(pdf_light: Float, pdf_scatter: Float) -> Float:
        weight = strategy_weight(pdf_light, emitters, pdf_scatter, scatters)
        return weight if mis_derivatives else dr.detach(weight)

    def unblocked(origin: Array3f, w: Array3f, t_max: Float, ok: Bool, value: Array3f) -> Array3f:
        if transmittance is None:
            return dr.select(ok & ~scene.occluded(origin, w, t_max, ok), value, 0.0)
        return dr.select(ok, value * transmittance(origin, w, t_max, ok), 0.0)

    # Step 1: point and directional lights, one shadow ray each.
    for light in lights.delta:
        if light.kind == "point":
            position = light.vector
            origin = spawn(position - p)
            # Aim from the offset origin, so that the shadow ray ends at the light.
            w, t_max = shadow_distance(origin, position)
            irradiance = light.irradiance_at(p)
        else:
            w, t_max = -light.vector, Float(dr.inf)
            origin = spawn(w)
            irradiance = light.power
        f = scatter(w)
        ok = shade & dr.any(f > 0)
        if light.kind == "point" and point_lights is not None:
            ok &= point_lights
        result += unblocked(origin, w, t_max, ok, f * irradiance)
    # A constant environment is found by the point's own samples, and drawn where it takes none
    # (or where environment_pick asks for it).
    environment = lights.environment
    drawn = environment is not None and (environment.sampled or (environment.constant is not None and (
        not scatters or environment_pick is not None)))
    share = None if not drawn else 1.0 if environment_pick is None else environment_pick
    for _ in range(emitters):
        result = _emitter_sample(result, scene, lights, p, spawn, scatter, density, shade, sampler, mis,
                                 unblocked, share)
    return result


def _emitter_sample(result: Array3f, scene: Scene, lights: LightSet, p: Array3f, spawn: Callable,
                    scatter: Callable, density: Callable, shade: Bool, sampler, mis: Callable,
                    unblocked: Callable, environment_share: Float | float | None) -> Array3f:
    """``result`` plus one emitter sample of :func:`gather_light`: a direction drawn from the
    environment (unless ``environment_share`` is None; per lane, where it is above 0, its
    density scaled by it in the MIS weight), a point on one area emitter picked uniformly,
    each weighted by ``mis``."""
    # Step 2: the environment, one direction drawn from it.
    environment = lights.environment
    if environment_share is not None:
        (u1, u2), u3 = sampler.next_pair(), sampler.next_float32()
        w, pdf_light, radiance = environment.sample(u1, u2, u3)
        origin = spawn(w)
        f = scatter(w)
        ok = shade & dr.any(f > 0) & (pdf_light > 0)
        if not isinstance(environment_share, float):
            ok &= environment_share > 0
        weight = mis(pdf_light * environment_share, density(w))
        result += unblocked(origin, w, Float(dr.inf), ok, f * radiance * weight / pdf_light)
    area_count = len(lights.area_instances)
    if not area_count:
        return result

    # Step 3: emitter sampling, one area emitter picked uniformly.
    slot, (u1, u2) = sampler.next_choice_and_pair(area_count)
    y, n_y, pdf_area, y_error, y_uv, pdf_cone = lights.sample_area_emitter(slot, u1, u2, p)
    # Offset both ends off their surfaces (pbrt-v4's SpawnRayTo), then aim from the
    # offset origin, so that the shadow ray ends just before the sampled point.
    origin = spawn(y - p)
    target = offset_origin(y, n_y, y_error, p - y)
    w, t_max = shadow_distance(origin, target)
    cos_y = -dr.dot(n_y, w)
    pdf_light = dr.select(pdf_cone > 0, pdf_cone, pdf_area * dr.squared_norm(y - p) / cos_y) / area_count
    f = scatter(w)
    ok = shade & dr.any(f > 0) & (cos_y > 0) & (pdf_light > 0)
    weight = mis(pdf_light, density(w))
    radiance = lights.emitter_radiance(slot, y_uv)
    return result + unblocked(origin, w, t_max, ok, f * radiance * weight / pdf_light)


def sample_bsdf(scene: Scene, hit, info: Shading, sampler) -> tuple[Array3f, Array3f, BSDFSample]:
    """A continuation ray drawn from the hit's BSDF: (origin, world direction, the sample).

    The direction is drawn from the detached wi and held fixed in the shading frame, which
    moves with the surface; where derivatives are tracked, the weight f cos / pdf carries
    those of f (as ``weight * relative(f)``: its value unchanged), and the density those
    of the BSDF's density in that direction (for the MIS weight: the emitter-sampling
    strategy differentiates its own weight, and the two weights' derivatives must cancel
    for the estimate to stay unbiased). After a delta lobe, the weight carries the
    derivatives of the materials' parameters only (the sample redone from the same random
    numbers and the detached wi). The secondary boundary term measures velocities
    relative to that fixed local direction.
    """
    with dr.suspend_grad():
        sample = scene.bsdfs.sample(info.material, dr.detach(info.wi), sampler, *info.detached())
    w = to_frame(hit.sn, sample.wo, hit.ss)
    materials = scene.bsdfs.differentiable
    if materials or dr.grad_enabled(info.wi):
        f = scene.bsdfs.evaluate(info.material, info.wi, sample.wo, info.point, info.surface)
        delta = sample.weight
        if materials and scene.bsdfs.has_delta:
            delta = scene.bsdfs.sample_from(info.material, dr.detach(info.wi), sample.u,
                                            *info.detached()).weight
        weight = dr.select(sample.delta, delta, sample.weight * relative(f))
        pdf = scene.bsdfs.pdf(info.material, info.wi, sample.wo, info.point, info.surface)
        sample = dataclasses.replace(sample, weight=weight, pdf=dr.select(
            sample.delta, sample.pdf, sample.pdf * relative(pdf)))
    return offset_origin(hit.p, hit.n, hit.error, w), w, sample


def relative(x: Float | Array3f) -> Float | Array3f:
    """1 in value, with the derivative of log x (0 where x is 0; per channel)."""
    safe = dr.select(dr.detach(x) != 0, dr.detach(x), 1.0)
    return 1.0 + (x - dr.detach(x)) / safe


def bsdf_mis_weight(sample: BSDFSample, pdf_emitter: Float, strategies: tuple[int, int] = (1, 1)) -> Float:
    """MIS weight of a BSDF-sampled ray that found an emitter: the power heuristic against
    emitter sampling (of ``strategies`` (E, B): :func:`strategy_weight`), 1 / B after a delta
    lobe (which emitter sampling cannot produce)."""
    emitters, bsdfs = strategies
    return dr.select(sample.delta, 1.0 / bsdfs, strategy_weight(sample.pdf, bsdfs, pdf_emitter, emitters))


@dataclass(frozen=True)
class EmitterHit:
    """What :func:`emitted` and :func:`emitter_pdf` read of a ray's hit on an area emitter."""

    t: Float
    n: Array3f
    instance: Int32  # -1 where the ray found no area emitter
    valid: Bool
    uv: Array2f  # the surface coordinates where some emitter is textured, else 0


def emitter_hit(scene: Scene, lights: LightSet, o: Array3f, d: Array3f,
                first: PreliminaryHit) -> EmitterHit:
    """The record of rays (o, d) where their preliminary hit ``first`` is an area emitter.

    Flat emitters (rectangles, disks) have one world normal each: t is phase 1's
    and the normal the light set's, with no re-intersection (measured: light_area,
    direct, 128x96 at 64 spp: kernel time 67.8 -> 61.1 ms). That record is detached, so
    where transforms carry derivatives (a moving emitter's hits move) and for other
    emitters, and where some emitter is textured (its surface coordinates), the hit
    emitters are re-intersected (phase 2).
    """
    on_emitter, slot = lights.is_area_emitter(Int32(first.instance))
    if lights.flat_normals is not None and not lights.moving() and lights.emitter_textures is None:
        return EmitterHit(first.t, dr.select(on_emitter, lights.flat_normal(slot), 0.0),
                          dr.select(on_emitter, Int32(first.instance), -1), on_emitter,
                          dr.zeros(Array2f, dr.width(first.t)))
    hit = reintersect(scene.instances, o, d, PreliminaryHit(
        first.t, dr.select(on_emitter, first.instance, MISS), first.position))
    return EmitterHit(hit.t, hit.n, hit.instance, hit.valid, hit.uv)


def bsdf_ray_to_emitters(scene: Scene, lights: LightSet, o: Array3f, w: Array3f,
                         active: Bool) -> tuple[PreliminaryHit, Bool]:
    """What a BSDF ray (o, w) of the direct integrator finds: its preliminary hit where that
    is an area emitter (elsewhere a miss), and whether it escapes the scene.

    Only an emitter (or the environment) can contribute. With a few emitters (the light
    set keeps their boxes), each is tested first; the scene is then asked only whether
    something lies in front of the nearest emitter hit (an any-hit query on a ray
    shortened as shadow rays are) or, with an environment, whether a ray that found no
    emitter escapes. Without an environment, rays that find no emitter trace nothing
    more. Otherwise: the scene's nearest hit.
    """
    if lights.boxes is None:
        first = scene.intersect_preliminary(o, w, active)
        return first, ~first.valid
    # The nearest emitter hit, all other instances ignored.
    nearest = intersect_preliminary(scene.instances, None, None, o, w, active, unrolled=lights.boxes)
    found = active & nearest.valid
    t_front = nearest.t * (1.0 - SHADOW_SHORTENING)
    if lights.environment is None:
        blocked = scene.occluded(o, w, t_front, found)
        escaped = Bool(False)
    else:
        blocked = scene.occluded(o, w, dr.select(found, t_front, dr.inf), active)
        escaped = active & ~found & ~blocked
    reached = found & ~blocked
    return PreliminaryHit(nearest.t, dr.select(reached, nearest.instance, MISS),
                          nearest.position), escaped


def differentiable_state(scene: Scene, lights: LightSet) -> dict:
    """The scene's arrays that may carry derivatives: instance rows, the materials' columns,
    texels and mesh attributes, delta lights' vectors and powers, the lights' textures, area
    emitters' radiances, the environment's radiance or texels."""
    inverse_rows, forward_linear = scene.instances.rows()
    return {"inverse_rows": inverse_rows, "forward_linear": forward_linear,
            **{"material." + key: value for key, value in scene.bsdfs.state().items()},
            "vectors": [light.vector for light in lights.delta],
            "powers": [light.power for light in lights.delta],
            "light_textures": lights.texture_arrays,
            "emitted": [lights.radiance] if lights.area_instances else [],
            "environment": [] if lights.environment is None else [lights.environment.values]}


def integrate_direct(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
                     hide_emitters: bool = False, strategies: tuple[int, int] = (1, 1),
                     alpha: bool = False) -> "Array3f | tuple[Array3f, Float]":
    """RGB radiance along unit-direction camera rays (see the module docstring); with
    ``hide_emitters``, without the emitters the rays see (rays that start
    :func:`past_emitters`); ``strategies``: (emitter samples, BSDF samples) per hit
    (:func:`strategy_samples`). With ``alpha``, also each ray's alpha: 1 where it hit a
    surface, else 0 (as Mitsuba's ``direct``: an environment seen counts for nothing)."""
    hit = scene.intersect_surface(o, d)
    if alpha:
        coverage = dr.select(hit.valid, 1.0, 0.0)
        return _direct(scene, lights, hit, d, sampler, hide_emitters, strategies), coverage
    return _direct(scene, lights, hit, d, sampler, hide_emitters, strategies)


def _direct(scene: Scene, lights: LightSet, hit, d: Array3f, sampler, hide_emitters: bool,
            strategies: tuple[int, int]) -> Array3f:
    """:func:`integrate_direct`'s radiance at the camera rays' ``hit``."""
    result = Array3f(0.0) if hide_emitters else emitted(lights, hit, d)
    emitters, bsdfs = strategies
    has_area, has_environment = bool(lights.area_instances), lights.environment is not None
    if not (lights.delta and emitters) and not has_area and not has_environment:
        return result
    # Only the side the material reflects shades (Mitsuba's one-sided BSDFs: the front,
    # the shading normal's side).
    info = shading(scene, hit, d)
    shade = info.lit

    def gathered(result, sampler):
        if emitters:
            result += sample_lights(scene, lights, hit, info, shade, sampler, strategies=strategies)
        if has_area or has_environment:
            for _ in range(bsdfs):
                result += _bsdf_sample(scene, lights, hit, info, shade, sampler, strategies)
        return result, sampler

    if dr.grad_enabled(hit, info, differentiable_state(scene, lights)):
        # (A symbolic branch would carry the AD graph through a conditional.)
        return gathered(result, sampler)[0]
    # A branch that SIMD packets in which no lane shades (misses, unlit sides) skip; its
    # condition and inputs given for every ray (a branch never taken returns its inputs).
    lanes = dr.width(d)
    result, drawn = dr.if_stmt((result + dr.zeros(Array3f, lanes), sampler),
                               shade | dr.zeros(Bool, lanes), gathered, lambda *state: state,
                               mode="symbolic")
    if sampler is not None:
        sampler.take_state(drawn)
    return result


def _bsdf_sample(scene: Scene, lights: LightSet, hit, info: Shading, shade: Bool, sampler,
                 strategies: tuple[int, int]) -> Array3f:
    """Step 4: one BSDF sample of :func:`integrate_direct`: area emitters and an environment
    map weighted against their sampling, a constant environment with weight 1 / B (where
    there are B BSDF samples, the only ones that find it)."""
    origin, w, sample = sample_bsdf(scene, hit, info, sampler)
    if lights.area_instances:
        # A record only where the ray found an area emitter (its radiance and density
        # need it); other hits only block the environment.
        first, escaped = bsdf_ray_to_emitters(scene, lights, origin, w, shade & sample.valid)
        bounce = emitter_hit(scene, lights, origin, w, first)
        found = emitted(lights, bounce, w, escaped)
        weight = bsdf_mis_weight(sample, emitter_pdf(lights, bounce, w, escaped, origin), strategies)
    else:
        # Only the environment can be found: an any-hit query says whether the ray
        # escapes, with no nearest hit and no surface record.
        going = shade & sample.valid
        escaped = going & ~scene.occluded(origin, w, Float(dr.inf), going)
        found = dr.select(escaped, lights.environment.radiance(w), 0.0)
        weight = (bsdf_mis_weight(sample, lights.environment.pdf(w), strategies)
                  if lights.environment.sampled else Float(1.0 / strategies[1]))
    return dr.select(shade & sample.valid, sample.weight * found * weight, 0.0)
