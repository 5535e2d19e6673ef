"""Volumetric path tracing through homogeneous media (Mitsuba's ``volpath``).

Paths run as in :mod:`instancing.rendering.integrators.path`, and between surfaces through
the medium they are in (:mod:`instancing.scene.medium`; the camera's to start with). In a
homogeneous medium, each step picks one of the three channels uniformly and draws a
free-flight distance t from its extinction, ``t = -log(1 - u) / sigma_c``, before the ray's
query, which then looks no further than t (as Mitsuba's volpath: a surface beyond t is not
met, and a short query culls most of the scene):

* if t comes before the next surface, the path scatters there: weight
  ``sigma_s exp(-sigma_t t) / p(t)`` with ``p(t)`` the channels' mean density
  ``mean(sigma_t exp(-sigma_t t))`` (one-sample MIS over the channels, each step its own
  channel choice), direct light gathered with the phase function where the medium samples
  emitters, and the path continues in a direction drawn from the phase function;
* otherwise it reaches the surface, weight ``exp(-sigma_t t_s) / mean(exp(-sigma_t t_s))``,
  and the surface scatters as in ``path``, except that a sample of a pass-through lobe (a
  ``null`` surface, a polarizer, a mask's transparent part, a thin dielectric's transmission)
  passes the ray on unchanged, weighted by the sample: not a bounce, as in Mitsuba's
  ``volpath`` (the depth does not grow, even at the last one, and MIS keeps the last
  scattering point).

In a heterogeneous medium, the step is delta tracking inside the medium's box (spectral
tracking, Kutz et al. 2017, with one majorant mu for the three channels): tentative
collisions at rate mu; at each, the path scatters with probability ``mean(sigma_t) / mu``,
weighted by the albedo (``sigma_s / mean(sigma_t)``: absorption scales the path's
throughput instead of ending it, as in Mitsuba's volpath, which leaves less noise where
the medium absorbs), and passes a null collision otherwise (weight
``(mu - sigma_t) / mean(mu - sigma_t)``); no collision before the box's far side or the
surface, weight 1.

A ray leaving a surface whose interior and exterior media differ continues in the medium on
its side. Shadow rays pass through surfaces by the share of light they let straight
through (:meth:`BSDFTable.null_transmission <instancing.materials.bsdf.BSDFTable.null_transmission>`:
1 for ``null``, ``1 - opacity`` for a mask of an opaque BSDF, ...; 0 blocks them), changing
medium there, and take the media's transmittance: ``exp(-sigma_t d)`` in closed form in
homogeneous media, by ratio tracking (the product of ``1 - sigma_t / mu`` over collisions at
rate mu) in heterogeneous ones. Faint shadow rays play Russian roulette: with one uniform u
per segment, a ray lives while the largest channel of its transmittance T(s) stays above
``u FAINT_TRANSMITTANCE`` and carries ``T(s) / min(1, max T(s) / FAINT_TRANSMITTANCE)``
(unbiased: the closed form wherever T stays above the threshold), and the segment's query
reaches no further than where the ray would die; ratio tracking's collisions play it too.
Point (and spot) lights are sampled along each segment of a homogeneous medium instead of
at its scattering point: one distance per lamp drawn with density proportional to
``1 / r(t)^2`` (equiangular sampling, Kulla & Fajardo 2012), the light it scatters towards the
ray weighted ``exp(-sigma_t t) sigma_s phase I / r^2 / p(t)``, which stays bounded where the
segment passes the lamp; at a free-flight point next to a lamp the weight ``1 / r^2`` has
infinite variance (in Mitsuba's volpath too).
Emission found by a path is weighted against light sampling by the power heuristic, with
weight 1 after a delta lobe, on the camera ray, and after scattering in a medium that does
not sample emitters. Lights at infinity follow Mitsuba's volpath, which decides what a
medium that no surface bounds receives (:meth:`MediaTable.unbounded
<instancing.scene.medium.MediaTable.unbounded>`): the environment and directional lights lie
at twice the larger of the scene's bounding-sphere radius and the shadow ray origin's
distance from its centre (:attr:`~instancing.scene.scene.Scene.bounding_sphere`); at events
in such a medium a constant environment is sampled too, and the environment's density in
the MIS weights is scaled by Mitsuba's chance of picking it among its emitters (the weights
of both strategies still sum to 1; a path's later escape takes the share of the event it
left). ``max_depth`` counts surface and medium scattering events as Mitsuba
does; after ``rr_depth`` events, Russian roulette as in ``path`` (Mitsuba's volpath, one
event later than its path).

Renders with derivatives are refused: path replay does not reach media.
"""

from __future__ import annotations

import dataclasses
import math

from ...core.backend import Array3f, Bool, Float, UInt32, dr
from ...core.box import slab_span
from ...core.errors import SceneError
from ...core.ray_offset import offset_origin, shadow_distance
from ...core.warp import power_heuristic
from ...scene.lights import LightSet
from ...scene.medium import MediaTable, hg_eval, hg_sample
from ...scene.scene import Scene
from .direct import emitted, emitter_pdf, gather_light, sample_bsdf, shading, surface_terms
from .path import RR_DEPTH, _limit, roulette_survival


#: Shadow-ray transmittance (largest channel) below which a ray plays Russian roulette
#: (module docstring; sweep in docs/how-it-works.md, "Tuned constants").
FAINT_TRANSMITTANCE = 0.25


class _Media:
    """The scene's media (vacuum everywhere where it names none), and whether some surface
    lets light straight through."""

    def __init__(self, scene: Scene):
        self.table = scene.media
        self.passes_light = scene.bsdfs.passes_light

    def sigma_t(self, medium: UInt32) -> Array3f:
        return Array3f(0.0) if self.table is None else self.table.sigma_t(medium)

    def sigma_s(self, medium: UInt32, p: Array3f, active: Bool) -> Array3f:
        return Array3f(0.0) if self.table is None else self.table.sigma_s(medium, p, active)

    def g(self, medium: UInt32) -> Float:
        return Float(0.0) if self.table is None else self.table.g(medium)

    def sample_emitters(self, medium: UInt32) -> Bool:
        return Bool(False) if self.table is None else self.table.sample_emitters(medium)

    @property
    def passable(self) -> bool:
        """Whether shadow rays may meet a medium or pass a surface (else they only ask
        whether anything blocks them)."""
        return self.table is not None or self.passes_light

    @property
    def heterogeneous(self) -> bool:
        """Whether some medium is heterogeneous (its tracking is traced only then)."""
        return self.table is not None and self.table.heterogeneous

    def span(self, medium: UInt32, o: Array3f, d: Array3f, t_end: Float) -> tuple[Float, Float]:
        """The part (t_in, t_out) of the ray segment (0, t_end) inside a heterogeneous
        medium's box (empty: t_in >= t_out)."""
        t_in, t_out = slab_span(*self.table.box(medium), o, dr.rcp(d))
        return t_in, dr.minimum(t_out, t_end)

    def extinction(self, medium: UInt32, p: Array3f, active: Bool) -> tuple[Array3f, Array3f]:
        """A heterogeneous medium's sigma_t at rendering-space points ``p``, and its grid value
        there (the density that scales its scattering too)."""
        density = self.table.density(medium, p, active)
        return self.sigma_t(medium) * density, density

    def target(self, hit, d: Array3f, medium: UInt32, active: Bool) -> UInt32:
        """The medium a ray leaving ``hit`` along ``d`` travels in."""
        if self.table is None:
            return medium
        return self.table.target(UInt32(dr.maximum(hit.instance, 0)), hit.n, d, medium, active)


def check_volpath(scene: Scene) -> None:
    """Refuse what volpath cannot render.

    Raises:
        SceneError: derivatives are asked for (path replay does not reach media).
    """
    if scene.differentiable:
        raise SceneError("volpath renders without derivatives: path replay does not reach "
                         "media; detach the scene's parameters, or render with 'path'")


def camera_medium(scene: Scene, medium: str) -> int:
    """The index of the camera's medium in the scene's media table (0: none)."""
    if not medium:
        return 0
    names = [m.id for m in scene.media.media]
    return names.index(medium) + 1


def _tracking(media: _Media, medium: UInt32, o: Array3f, d: Array3f, t_end: Float, sampler,
              active: Bool, collide, carried):
    """Tentative collisions at the majorant's rate along the segment (0, t_end) of rays (o, d)
    inside a heterogeneous medium's box: at each, ``collide(t, inside, sampler, carried)``
    returns the carried values and whether the ray goes on. Returns (t, carried)."""
    t_in, t_out = media.span(medium, o, d, t_end)
    mu = media.table.majorant(medium)

    def body(t, carried, sampler, running):
        t = t - dr.log(1.0 - sampler.next_float32()) / mu
        carried, going_on = collide(t, running & (t < t_out), sampler, carried)
        return t, carried, sampler, going_on

    state = (dr.zeros(Float, dr.width(active)) + t_in, carried, sampler,
             active & (mu > 0) & (t_in < t_out))
    t, carried, _, _ = dr.while_loop(state, lambda *s: s[-1], body)
    return t, carried


def _ratio_tracking(media: _Media, medium: UInt32, o: Array3f, d: Array3f, length: Float,
                    sampler, active: Bool) -> Array3f:
    """Transmittance of the segment (0, length) through a heterogeneous medium, by ratio
    tracking: the product of ``1 - sigma_t / mu`` over collisions at the majorant's rate."""
    mu = media.table.majorant(medium)

    def collide(t, inside, sampler, tr):
        sigma_t, _ = media.extinction(medium, o + d * t, inside)
        tr = _faint_roulette(dr.select(inside, tr * dr.maximum(mu - sigma_t, 0.0) / mu, tr), sampler, inside)
        return tr, inside & dr.any(tr > 0)

    return _tracking(media, medium, o, d, length, sampler, active, collide,
                     dr.full(Array3f, 1.0, dr.width(active)))[1]


def _faint_roulette(tr: Array3f, sampler, going_on: Bool) -> Array3f:
    """Russian roulette on the transmittance ``tr`` of rays that go on (ratio tracking's
    collisions; module docstring): below FAINT_TRANSMITTANCE (largest channel) a ray
    survives with probability ``max(tr) / FAINT_TRANSMITTANCE`` and carries ``tr`` divided by
    it, else its ``tr`` is 0."""
    largest = dr.max(tr)
    survival = largest / FAINT_TRANSMITTANCE
    faint = going_on & (largest < FAINT_TRANSMITTANCE)
    survives = sampler.next_float32() < survival
    return dr.select(faint, dr.select(survives, tr / survival, 0.0), tr)


def _reach(tr: Array3f, sigma: Array3f, level: Float) -> Float:
    """How far a ray of transmittance ``tr`` goes through extinction ``sigma`` before the
    largest channel of ``tr exp(-sigma s)`` falls to ``level`` (negative: it is below
    already; inf: a channel that does not fall stays above)."""
    reach = Float(-dr.inf)
    for c in range(3):
        ahead = dr.log(tr[c] / level)
        reach = dr.maximum(reach, dr.select(sigma[c] > 0, ahead / sigma[c],
                                            dr.select(ahead >= 0, dr.inf, -dr.inf)))
    return reach


def _transmittance(scene: Scene, media: _Media, medium: UInt32, sampler):
    """The shadow-ray transmittance of :func:`gather_light`, starting in ``medium``: the
    media's along the ray times the surfaces' null transmission (module docstring)."""

    def transmittance(origin: Array3f, w: Array3f, t_max: Float, active: Bool) -> Array3f:
        def body(o, remaining, tr, current, sampler, active):
            # Continuous Russian roulette: the ray lives while the largest channel of its
            # transmittance stays above u FAINT_TRANSMITTANCE (closed form in a homogeneous
            # medium; heterogeneous media keep ratio tracking's own roulette), and its query
            # reaches no further than that.
            sigma = media.sigma_t(current)
            tracked = active & media.table.is_heterogeneous(current) if media.heterogeneous else Bool(False)
            sigma = dr.select(tracked, 0.0, sigma)
            reach = _reach(tr, sigma, sampler.next_float32() * FAINT_TRANSMITTANCE)
            alive = active & (reach > 0)
            hit = scene.intersect_surface(o, w, alive, dr.minimum(remaining, reach))
            length = dr.select(hit.valid, hit.t, remaining)
            closed = MediaTable.transmittance(sigma, length)
            survival = dr.minimum(dr.max(tr * closed) / FAINT_TRANSMITTANCE, 1.0)
            # (u = 0 reaches any distance; where the closed form vanishes there, the ray
            # carries nothing and dies.)
            alive &= (length <= reach) & (survival > 0)
            if media.heterogeneous:
                closed = dr.select(tracked, _ratio_tracking(media, current, o, w, length, sampler, tracked),
                                   closed)
            tr = dr.select(alive, tr * closed / survival, dr.select(active, 0.0, tr))
            met = alive & hit.valid
            info = shading(scene, hit, w)
            through = scene.bsdfs.null_transmission(info.material, info.wi, info.point)
            tr = dr.select(met, tr * through, tr)
            passes = met & dr.any(through > 0)
            current = media.target(hit, w, current, passes)
            o = dr.select(passes, offset_origin(hit.p, hit.n, hit.error, w), o)
            return o, remaining - length, tr, current, sampler, passes & dr.any(tr > 0)

        # A light at infinity (the environment, a directional light) lies, as in Mitsuba,
        # at twice the larger of the scene's bounding-sphere radius and the ray origin's
        # distance from its centre: a ray crosses no more of a medium that no surface
        # bounds (Mitsuba's volpath lights such fog; at infinity it would get nothing).
        centre, radius = scene.bounding_sphere
        t_max = dr.select(dr.isinf(t_max), 2.0 * dr.maximum(radius, dr.norm(origin - Array3f(*centre))),
                          t_max)
        width = dr.width(active)
        state = (dr.zeros(Array3f, width) + origin, dr.zeros(Float, width) + t_max,
                 dr.full(Array3f, 1.0, width), dr.zeros(UInt32, width) + medium, sampler, Bool(active))
        # (The loop advances the sampler in place, as every loop here.)
        return dr.while_loop(state, lambda *s: s[-1], body)[2]

    return transmittance


def _delta_tracking(media: _Media, medium: UInt32, o: Array3f, d: Array3f, t_end: Float,
                    sampler, active: Bool) -> tuple[Bool, Float, Array3f]:
    """The free flight of rays through a heterogeneous medium up to ``t_end`` (module
    docstring): (whether the ray scatters, where, the weight of its collisions)."""
    mu = media.table.majorant(medium)

    def collide(t, inside, sampler, carried):
        weight, scattered = carried
        p = o + d * t
        sigma_t, density = media.extinction(medium, p, inside)
        sigma_s = media.sigma_s(medium, p, inside) * density
        sigma_n = dr.maximum(mu - sigma_t, 0.0)
        # A real collision (scattering, weighted by the albedo) or a null one.
        scatter = inside & (sampler.next_float32() * mu < dr.mean(sigma_t))
        null = inside & ~scatter
        weight = dr.select(scatter, weight * sigma_s / dr.mean(sigma_t),
                           dr.select(null, weight * sigma_n / dr.mean(sigma_n), weight))
        return (weight, scattered | scatter), null

    width = dr.width(active)
    t, (weight, scattered) = _tracking(media, medium, o, d, t_end, sampler, active, collide,
                                       (dr.full(Array3f, 1.0, width), dr.zeros(Bool, width)))
    return scattered, t, weight


def _flight_distance(media: _Media, medium: UInt32, sampler) -> Float:
    """A free-flight distance through a homogeneous ``medium``, drawn in one of its channels
    picked uniformly (module docstring); inf where the scene has no media."""
    if media.table is None:
        return Float(dr.inf)
    sigma_t = media.sigma_t(medium)
    u_channel, u_distance = sampler.next_float32(), sampler.next_float32()
    sigma_c = dr.select(u_channel < 1 / 3, sigma_t.x, dr.select(u_channel < 2 / 3, sigma_t.y, sigma_t.z))
    return -dr.log(1.0 - u_distance) / sigma_c


def _free_flight(media: _Media, medium: UInt32, o: Array3f, d: Array3f, t: Float, t_surface: Float,
                 sampler, active: Bool) -> tuple[Bool, Float, Array3f]:
    """Rays (o, d) in ``medium`` with the distance ``t`` drawn by :func:`_flight_distance` and
    their next surface at ``t_surface`` (inf where none lies before t): whether each scatters
    in the medium first, where (t), and the weight of its flight (module docstring)."""
    width = dr.width(o)
    if media.table is None:
        return dr.zeros(Bool, width), dr.zeros(Float, width), dr.full(Array3f, 1.0, width)
    # Homogeneous media: weighted by the channels' mean density.
    sigma_t = media.sigma_t(medium)
    in_medium = active & (medium != 0)
    scatters = in_medium & (t < t_surface)
    tr = MediaTable.transmittance(sigma_t, dr.select(scatters, t, t_surface))
    density = dr.mean(dr.select(scatters, sigma_t * tr, tr))
    weight = dr.select(scatters, media.sigma_s(medium, o + d * t, scatters), 1.0) * tr / density
    weight = dr.select(density > 0, weight, 0.0)
    if media.heterogeneous:
        # Heterogeneous media: delta tracking up to the surface instead.
        tracked = in_medium & media.table.is_heterogeneous(medium)
        scatters_h, t_h, weight_h = _delta_tracking(media, medium, o, d, t_surface, sampler, tracked)
        scatters = dr.select(tracked, scatters_h, scatters)
        t = dr.select(tracked, t_h, t)
        weight = dr.select(tracked, weight_h, weight)
    return scatters, t, weight


def _lamps_along(scene: Scene, lights: LightSet, media: _Media, medium: UInt32, o: Array3f,
                 d: Array3f, t_end: Float, g: Float, active: Bool, sampler) -> Array3f:
    """Light that the point lights scatter towards the unit-direction rays (o, d) along their
    segment (0, t_end) through the homogeneous ``medium``, per unit throughput: for each
    lamp one distance drawn equiangularly (module docstring), its shadow ray through the
    scene's surfaces and media."""
    result = Array3f(0.0)
    sigma_t = media.sigma_t(medium)
    transmittance = _transmittance(scene, media, medium, sampler)
    for light in lights.delta:
        if light.kind != "point":
            continue
        # The lamp's foot on the ray's line (delta along the ray, h off it) and the angles
        # under which the segment's ends are seen from the lamp.
        c = light.vector
        delta = dr.dot(c - o, d)
        h = dr.norm(c - dr.fma(d, delta, o))
        theta_a = dr.atan2(-delta, h)
        theta_b = dr.select(dr.isinf(t_end), 0.5 * math.pi, dr.atan2(t_end - delta, h))
        t = dr.fma(h, dr.tan(dr.lerp(theta_a, theta_b, sampler.next_float32())), delta)
        pdf = h / ((theta_b - theta_a) * dr.fma(h, h, dr.square(t - delta)))
        p = dr.fma(d, t, o)
        w, t_max = shadow_distance(p, c)
        intensity = light.irradiance_at(p)
        scattered = (MediaTable.transmittance(sigma_t, t) * media.sigma_s(medium, p, active)
                     * hg_eval(g, -dr.dot(d, w)))
        ok = active & (h > 0) & (theta_b > theta_a) & (t >= 0) & (t < t_end) & (pdf > 0)
        value = scattered * intensity / pdf
        result += dr.select(ok, value * transmittance(p, w, t_max, ok), 0.0)
    return result


def integrate_volpath(scene: Scene, lights: LightSet, o: Array3f, d: Array3f, sampler,
                      max_depth: "int | UInt32" = -1, medium: int = 0,
                      rr_depth: int = RR_DEPTH, hide_emitters: bool = False,
                      alpha: bool = False) -> "Array3f | tuple[Array3f, Float]":
    """RGB radiance along unit-direction rays that start in the medium ``medium`` (see
    :func:`camera_medium`; the module docstring describes the estimator). With
    ``hide_emitters`` (Mitsuba's), the emitters that the rays see before any scattering
    event give no light, and area emitters met then are passed through. With ``alpha``,
    also each path's alpha (1 or 0), as Mitsuba's ``volpath`` sets it: 1 where the
    environment is seen, or the path scatters in a medium or at a surface other than by a
    pass-through lobe."""
    check_volpath(scene)
    media = _Media(scene)
    limit = _limit(max_depth)
    # In media that no surface bounds, the environment's share of the MIS weights: Mitsuba's
    # chance of picking it among its emitters (each point, spot, directional light and
    # emitting shape one; module docstring); elsewhere a map's full density, a constant
    # environment not drawn.
    unbounded = media.table is not None and media.table.any_unbounded and lights.environment is not None
    elsewhere = 1.0 if lights.environment is not None and lights.environment.sampled else 0.0
    pick = 1.0 / (len(lights.delta) + len(lights.area_instances) + 1)
    width = dr.width(o)
    state = (dr.zeros(Array3f, width) + o, dr.zeros(Array3f, width) + d,
             dr.full(Array3f, 1.0, width), dr.zeros(Array3f, width),  # throughput, radiance
             dr.zeros(UInt32, width), dr.full(UInt32, medium, width),  # depth, medium
             dr.zeros(Float, width), dr.full(Bool, True, width),       # scattering pdf, specular
             dr.zeros(Float, width), dr.opaque(Float, 1.0, width),       # distance, eta
             dr.full(Float, elsewhere, width),                          # environment's share
             sampler, dr.full(Bool, True, width))
    if alpha:
        # Rays that see the environment are covered from the start.
        state += (dr.full(Bool, not hide_emitters and lights.environment is not None, width),)

    def body(o, d, beta, radiance, depth, current, pdf_prev, specular, travelled, eta, share_prev,
             sampler, active, *covered):
        # Russian roulette (once more than rr_depth events lie behind, as Mitsuba's volpath),
        # then the depth limit.
        survive = roulette_survival(beta, eta)
        roulette = depth > rr_depth
        active &= dr.any(beta != 0) & (~roulette | (sampler.next_float32() < survive))
        beta = dr.select(roulette, beta / survive, beta)
        active &= depth < limit

        # Point lights scattered towards the ray along its segment through a homogeneous
        # medium (equiangular; at its free-flight point below, only the other lights).
        g = media.g(current)
        along = Bool(False)
        lamps = media.table is not None and any(light.kind == "point" for light in lights.delta)
        if lamps:
            along = (active & (current != 0) & ~media.table.is_heterogeneous(current)
                     & media.sample_emitters(current) & (depth + 1 < limit))
        # The free-flight distance through a homogeneous medium, drawn first: the ray's query
        # stops there (as Mitsuba's volpath's), unless its whole segment is wanted (a lamp's
        # light gathered along it, delta tracking through a heterogeneous medium).
        t_flight = _flight_distance(media, current, sampler)
        whole = along | (current == 0)
        if media.heterogeneous:
            whole |= media.table.is_heterogeneous(current)
        hit = scene.intersect_surface(o, d, active, dr.select(whole, dr.inf, t_flight))
        if lamps:
            radiance += dr.select(along, beta * _lamps_along(scene, lights, media, current, o, d, hit.t, g,
                                                             along, sampler), 0.0)

        # Free flight through the current medium: a scattering point before the surface, or none.
        scatters, t, weight = _free_flight(media, current, o, d, t_flight, hit.t, sampler, active)
        beta = dr.select(active & (current != 0), beta * weight, beta)
        p = o + d * t

        # Scattering in the medium: a new direction drawn from the phase function (the light
        # arriving there is sampled below, with the surfaces').
        wi = -d
        depth_medium = depth + 1
        scatter = scatters & (depth_medium < limit)
        sample_emitters = media.sample_emitters(current)

        def phase(w: Array3f) -> Float:
            return hg_eval(g, dr.dot(wi, w))

        d_phase = d
        gathered = Bool(False)
        if media.table is not None:
            gathered = scatter & sample_emitters
            u1, u2 = sampler.next_float32(), sampler.next_float32()
            d_phase = hg_sample(g, wi, u1, u2)

        # Reaching a surface: emission found there (or the environment), MIS weighted
        # against light sampling from the last scattering point; none seen before the first
        # event with hide_emitters, which passes through the area emitters met then.
        reach = active & ~scatters
        from_last = dataclasses.replace(hit, t=travelled + hit.t)
        mis = dr.select(specular, 1.0, power_heuristic(pdf_prev, emitter_pdf(
            lights, from_last, d, environment_pick=share_prev if unbounded else None)))
        seen = reach & (depth > 0) if hide_emitters else reach
        radiance += dr.select(seen, beta * emitted(lights, hit, d) * mis, 0.0)
        skipped = Bool(False)
        if hide_emitters and lights.area_instances:
            skipped = reach & hit.valid & (depth == 0) & lights.is_area_emitter(hit.instance)[0]
        info = shading(scene, hit, d)
        here = reach & info.lit & ~skipped
        shade = here & (depth + 1 < limit)

        # Light sampled where the path scatters, by one set of shadow rays for both kinds of
        # event: at a medium's scattering point with the phase function, at a surface with
        # its BSDF (its shadow rays start in the medium on the side they leave).
        spawn, bsdf, bsdf_pdf = surface_terms(scene, hit, info)

        def transmittance(origin, w, t_max, ok):
            start = dr.select(gathered, current, media.target(hit, w, current, ok & ~gathered))
            return _transmittance(scene, media, start, sampler)(origin, w, t_max, ok)

        lit = gathered | shade
        share = dr.select(media.table.unbounded(current), pick, elsewhere) if unbounded else None
        radiance += dr.select(lit, beta * gather_light(
            scene, lights, dr.select(gathered, p, hit.p),
            lambda towards: dr.select(gathered, p, spawn(towards)),
            lambda w: dr.select(gathered, Array3f(phase(w)), bsdf(w)),
            lambda w: dr.select(gathered, phase(w), bsdf_pdf(w)),
            lit, sampler, False, transmittance if media.passable else None, point_lights=~(gathered & along),
            environment_pick=share),
            0.0)
        o_bsdf, d_bsdf, sample = sample_bsdf(scene, hit, info, sampler)
        # A pass-through sample (or a skipped emitter) goes on in the ray's own direction and
        # is no bounce.
        passes = here & sample.null
        shade &= ~sample.null
        weight = dr.select(skipped, 1.0, sample.weight)
        passes |= skipped
        if alpha:
            covered = (covered[0] | scatter | (reach & hit.valid & ~skipped & ~sample.null),)

        # The next step: after a medium scattering, a surface's BSDF sample, or a pass.
        o_pass = offset_origin(hit.p, hit.n, hit.error, d)
        o = dr.select(scatter, p, dr.select(passes, o_pass, o_bsdf))
        d_next = dr.select(scatter, d_phase, dr.select(passes, d, d_bsdf))
        beta = dr.select(shade | passes, beta * weight, beta)
        eta = dr.select(shade, eta * sample.eta, eta)
        current = dr.select(passes | shade, media.target(hit, d_next, current, passes | shade), current)
        pdf_prev = dr.select(scatter, phase(d_phase), dr.select(shade, sample.pdf, pdf_prev))
        specular = dr.select(scatter, ~sample_emitters, dr.select(shade, sample.delta, specular))
        travelled = dr.select(passes, travelled + hit.t, 0.0)
        if unbounded:
            share_prev = dr.select(scatter | shade, share, share_prev)
        depth = dr.select(scatter, depth_medium, dr.select(shade, depth + 1, depth))
        active = scatter | passes | (shade & sample.valid)
        return (o, d_next, beta, radiance, depth, current, pdf_prev, specular, travelled, eta, share_prev,
                sampler, active) + covered

    with dr.suspend_grad():
        result = dr.while_loop(state, lambda *s: s[12], body, labels=(
            "o", "d", "beta", "radiance", "depth", "medium", "pdf_prev", "specular", "travelled",
            "eta", "share_prev", "sampler", "active") + (("covered",) if alpha else ()))
    return (result[3], dr.select(result[13], 1.0, 0.0)) if alpha else result[3]

