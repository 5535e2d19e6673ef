"""Mitsuba's ``conductor`` (a smooth metal: a mirror with the conductor Fresnel term) and
``roughconductor`` (a microfacet metal, Beckmann or GGX).

The Fresnel term, the microfacet distributions and their visible-normal sampling are
Mitsuba's own functions (``mi.fresnel_conductor``, ``mi.MicrofacetDistribution``) applied
to our arrays, per lane: the parameters of each lane's material are gathered from the
flat table, so that one kernel serves any number of materials. Named metals
(``"material": "Au"``) take the RGB ``eta`` and ``k`` that Mitsuba's RGB variant gives them.
"""

from __future__ import annotations

import functools

import numpy as np

from ..core.backend import Array3f, Bool, Float, dr, mitsuba_module
from ..core.errors import SceneError
from .delta_lobe import DeltaLobe
from .parameter import CHOICE, COLOR, FLAG, NAME, NUMBER, Parameter

_CONDUCTOR = {
    "eta": Parameter(COLOR, 0.0, differentiable_constant=True),
    "k": Parameter(COLOR, 1.0, differentiable_constant=True), "material": Parameter(NAME, "none"),
    "specular_reflectance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
}
_MICROFACET = {
    "distribution": Parameter(CHOICE, "beckmann", choices=("beckmann", "ggx")),
    "alpha": Parameter(NUMBER, 0.1, 0.0), "alpha_u": Parameter(NUMBER, 0.1, 0.0),
    "alpha_v": Parameter(NUMBER, 0.1, 0.0), "sample_visible": Parameter(FLAG, True),
}
#: The roughness of the types whose plugins look it up per lane (a texture may give it).
TEXTURED_ROUGHNESS = {key: Parameter(NUMBER, 0.1, 0.0, texture=True)
                      for key in ("alpha", "alpha_u", "alpha_v")}


def microfacet_alpha(p: dict, variant: tuple) -> Float:
    """The roughness the ``roughness`` AOV shows: alpha, or where it is anisotropic the
    geometric mean of alpha_u and alpha_v."""
    return dr.sqrt(p["alpha_u"] * p["alpha_v"]) if variant[2] else p["alpha"]


@functools.lru_cache(maxsize=64)
def named_conductor(name: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(eta, k) in RGB of Mitsuba's named conductor ``name``, as its RGB variant makes them."""
    mi = mitsuba_module()
    try:
        params = mi.traverse(mi.load_dict({"type": "conductor", "material": name}))
    except Exception as err:  # Mitsuba raises RuntimeError naming the problem
        raise SceneError(f"'material' {name!r} is none of Mitsuba's named conductors "
                         f"({str(err).splitlines()[-1]})") from None
    return tuple(tuple(float(c) for c in np.ravel(params[key]) * np.ones(3))
                 for key in ("eta.value", "k.value"))


def resolve_conductor(where: str, values: dict, given: set[str]) -> dict:
    """The complex index of refraction of a conductor: ``eta`` and ``k``, or a named
    ``material`` (not both, as Mitsuba)."""
    if values["material"] != "none":
        if given & {"eta", "k"}:
            raise SceneError(f"{where}: give either 'eta' and 'k' or 'material', not both")
        try:
            values["eta"], values["k"] = named_conductor(values["material"])
        except SceneError as err:
            raise SceneError(f"{where}: {err}") from None
    return values


def consistent(values: dict, changed: set[str]) -> dict:
    """A microfacet or conductor material's values after ``changed`` keys were set: a new
    ``alpha`` is also ``alpha_u`` and ``alpha_v``; a new ``eta`` or ``k`` makes a conductor
    no longer the named ``material``."""
    if "alpha" in changed and "alpha_u" in values:
        values["alpha_u"] = values["alpha_v"] = values["alpha"]
    if changed & {"eta", "k"} and "material" in values:
        values["material"] = "none"
    return values


def written(values: dict, changed: set[str]) -> dict:
    """The scene-file entries that state a microfacet or conductor material's new
    ``changed`` values (None: drop the entry): ``eta`` and ``k`` go together and replace a
    named ``material``; ``alpha`` replaces ``alpha_u`` and ``alpha_v``."""
    entries = {key: values[key] for key in changed}
    if changed & {"eta", "k"} and "material" in values:
        entries.update(eta=values["eta"], k=values["k"], material=None)
    if "alpha" in changed and "alpha_u" in values:
        entries.update(alpha_u=None, alpha_v=None)
    return entries


def resolve_roughness(where: str, values: dict, given: set[str], anisotropic: bool = True) -> dict:
    """``alpha``, or ``alpha_u`` and ``alpha_v`` (both). Where those differ or a texture gives
    either, the roughness is anisotropic (``anisotropic``: whether the type allows it, as
    Mitsuba's roughconductor and roughdielectric do and its roughplastic does not) and the
    values hold no ``alpha``: the kernel reads the two (:func:`is_anisotropic`)."""
    axes = given & {"alpha_u", "alpha_v"}
    if not axes:  # (isotropic, as Mitsuba: both axes take alpha)
        values["alpha_u"] = values["alpha_v"] = values["alpha"]
        return values
    if axes != {"alpha_u", "alpha_v"}:
        raise SceneError(f"{where}: give both 'alpha_u' and 'alpha_v'")
    if "alpha" in given:
        raise SceneError(f"{where}: give either 'alpha' or 'alpha_u' and 'alpha_v'")
    u, v = values["alpha_u"], values["alpha_v"]
    if isinstance(u, float) and isinstance(v, float) and u == v:
        values["alpha"] = u
        return values
    if not anisotropic:
        raise SceneError(f"{where}: anisotropic roughness (alpha_u {u} != alpha_v {v}) is not "
                         "supported by this type, as by Mitsuba's")
    del values["alpha"]
    return values


def is_anisotropic(values: dict) -> bool:
    """Whether a microfacet material's roughness differs along the shading frame's axes."""
    return "alpha" not in values


def exposed(values: dict, key: str) -> bool:
    """Whether :func:`instancing.traverse` exposes ``key`` of a microfacet material: ``alpha``
    where it is isotropic, ``alpha_u`` and ``alpha_v`` where it is anisotropic."""
    if key == "alpha":
        return not is_anisotropic(values)
    if key in ("alpha_u", "alpha_v"):
        return is_anisotropic(values)
    return True


def microfacets(distribution: str, alpha_u: Float, alpha_v: Float | None = None,
                sample_visible: bool = True):
    """Mitsuba's microfacet distribution (``"beckmann"`` or ``"ggx"``) with a roughness per
    lane along the shading frame's first and second axes (isotropic where ``alpha_v`` is
    None)."""
    mi = mitsuba_module()
    kind = mi.MicrofacetType.GGX if distribution == "ggx" else mi.MicrofacetType.Beckmann
    return mi.MicrofacetDistribution(kind, alpha_u, alpha_u if alpha_v is None else alpha_v,
                                     sample_visible)


def roughness_of(p: dict, variant: tuple):
    """The kernel's (alpha_u, alpha_v) of the lanes' rows (variant[2]: anisotropic), for
    :func:`microfacets`."""
    return (p["alpha_u"], p["alpha_v"]) if variant[2] else (p["alpha"], None)


def microfacet_variant(values: dict) -> tuple:
    """The kernel variant of a microfacet material: (distribution, sample_visible,
    anisotropic)."""
    return (values["distribution"], values["sample_visible"], is_anisotropic(values))


def lanes_distribution(p: dict, variant: tuple):
    """The microfacet distribution of the lanes' rows, for a :func:`microfacet_variant`."""
    return microfacets(variant[0], *roughness_of(p, variant), sample_visible=variant[1])


class Microfacets:
    """What the microfacet types share: their kernel variant, the lanes' distribution, which
    roughness keys traverse exposes, whether the roughness is anisotropic and the roughness
    the ``roughness`` AOV shows."""

    variant = staticmethod(microfacet_variant)
    _distribution = staticmethod(lanes_distribution)
    exposed = staticmethod(exposed)
    anisotropic = staticmethod(is_anisotropic)
    microfacet_alpha = staticmethod(microfacet_alpha)


def _fresnel(cos_theta: Float, eta: Array3f, k: Array3f) -> Array3f:
    """The conductor Fresnel reflectance per colour channel (Mitsuba's fresnel_conductor)."""
    mi = mitsuba_module()
    return Array3f(*[mi.fresnel_conductor(cos_theta, mi.Complex2f(eta[c], k[c])) for c in range(3)])


class Conductor(DeltaLobe):
    """A perfectly smooth metal: reflects wi about the normal with weight
    ``specular_reflectance * F(cos theta_i)`` (a delta lobe: eval and pdf are 0)."""

    names = ("conductor",)
    parameters = _CONDUCTOR
    albedo = "specular_reflectance"

    changed = staticmethod(consistent)
    written = staticmethod(written)

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        return resolve_conductor(where, values, given)

    @staticmethod
    def sample(p, wi, u, variant) -> tuple[Array3f, Array3f, Float, Bool, Bool]:
        valid = wi.z > 0
        wo = Array3f(-wi.x, -wi.y, wi.z)
        weight = p["specular_reflectance"] * _fresnel(wi.z, p["eta"], p["k"])
        return wo, dr.select(valid, weight, 0.0), Float(1.0), valid, Bool(True)


class RoughConductor(Microfacets):
    """Microfacet reflection (Walter et al. 2007): ``f cos = F(wi . h) D(h) G(wi, wo) /
    (4 cos theta_i)`` with Mitsuba's Beckmann or GGX distribution and Smith masking;
    sampled by visible normals (or by D cos, with ``sample_visible`` false)."""

    names = ("roughconductor",)
    parameters = {**_CONDUCTOR, **_MICROFACET, **TEXTURED_ROUGHNESS}
    delta_only = False
    albedo = "specular_reflectance"

    changed = staticmethod(consistent)
    written = staticmethod(written)

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        return resolve_roughness(where, resolve_conductor(where, values, given), given)

    @staticmethod
    def _distribution(p, variant):
        return mitsuba_module(), lanes_distribution(p, variant)

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        mi, distribution = RoughConductor._distribution(p, variant)
        h = dr.normalize(wi + wo)
        m = mi.Vector3f(h)
        d = distribution.eval(m)
        g = distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), m)
        value = d * g / (4.0 * wi.z)
        f = _fresnel(dr.dot(wi, h), p["eta"], p["k"]) * p["specular_reflectance"]
        ok = (wi.z > 0) & (wo.z > 0) & (d != 0)
        return dr.select(ok, f * value, 0.0)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        mi, distribution = RoughConductor._distribution(p, variant)
        h = dr.normalize(wi + wo)
        m = mi.Vector3f(h)
        ok = (wi.z > 0) & (wo.z > 0) & (dr.dot(wi, h) > 0) & (dr.dot(wo, h) > 0)
        if variant[1]:
            value = distribution.eval(m) * distribution.smith_g1(mi.Vector3f(wi), m) / (4.0 * wi.z)
        else:
            value = distribution.pdf(mi.Vector3f(wi), m) / (4.0 * dr.dot(wo, h))
        return dr.select(ok, value, 0.0)

    @staticmethod
    def sample(p, wi, u, variant) -> tuple[Array3f, Array3f, Float, Bool, Bool]:
        mi, distribution = RoughConductor._distribution(p, variant)
        m, pdf = distribution.sample(mi.Vector3f(wi), mi.Point2f(u[1], u[2]))
        m = Array3f(m)
        wo = 2.0 * dr.dot(wi, m) * m - wi
        valid = (wi.z > 0) & (pdf != 0) & (wo.z > 0)
        if variant[1]:
            weight = distribution.smith_g1(mi.Vector3f(wo), mi.Vector3f(m))
        else:
            weight = (distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), mi.Vector3f(m))
                      * dr.dot(wi, m) / (wi.z * m.z))
        pdf = pdf / (4.0 * dr.dot(wo, m))
        f = _fresnel(dr.dot(wi, m), p["eta"], p["k"]) * p["specular_reflectance"]
        return wo, dr.select(valid, f * weight, 0.0), Float(pdf), valid, Bool(False)
