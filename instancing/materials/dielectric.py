"""Mitsuba's dielectrics: ``dielectric`` (a smooth interface that reflects and refracts),
``thindielectric`` (a thin slab: reflects or lets light straight through) and
``roughdielectric`` (microfacet reflection and refraction, Walter et al. 2007).

They scatter on both sides: a direction below the surface (``wi.z < 0``) sees the interface
from inside, with the relative index of refraction inverted, as in Mitsuba. Transmission
scales radiance by ``1 / eta^2`` (solid-angle compression, Mitsuba's radiance mode). Each
picks its lobe (reflection or transmission) by the Fresnel reflectance with a third random
number; a smooth interface's lobes are delta lobes (``eval`` and ``pdf`` are 0).
"""

from __future__ import annotations

from ..core.backend import Array3f, Bool, Float, dr, mitsuba_module
from ..core.errors import SceneError
from .conductor import (_MICROFACET, TEXTURED_ROUGHNESS, Microfacets, consistent, microfacets,
                        resolve_roughness, roughness_of, written)
from .delta_lobe import DeltaLobe, chosen
from .parameter import COLOR, IOR, NUMBER, Parameter

_DIELECTRIC = {
    "int_ior": Parameter(IOR, "bk7"), "ext_ior": Parameter(IOR, "air"),
    "specular_reflectance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
    "specular_transmittance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
}


def _fresnel(cos_theta_i: Float, eta: Float):
    """Mitsuba's ``fresnel``: (reflectance, cos theta_t, eta_it, eta_ti)."""
    return mitsuba_module().fresnel(cos_theta_i, eta)


def traversed_eta(column: str) -> dict:
    """What traverse exposes of a rough or thin dielectric (or a rough plastic's coating)
    beyond its parameters, as Mitsuba's traverse does: the relative index of refraction
    ``eta`` = int_ior / ext_ior, which the kernels read from ``column``."""
    return {"eta": Parameter(NUMBER, None, 0.0, differentiable_constant=True, column=column)}


def eta_changed(must_differ: bool):
    """The ``changed`` hook of a material whose ``eta`` traverse sets: ``int_ior`` takes
    ``eta * ext_ior`` (the outer medium stays; ``must_differ``: eta 1 is refused); then
    :func:`~instancing.materials.conductor.consistent`."""
    def changed(values: dict, keys: set[str]) -> dict:
        if "eta" in keys:
            eta = values.pop("eta")
            if eta <= 0 or (must_differ and eta == 1):
                raise SceneError(f"'eta' must be positive{' and differ from 1' if must_differ else ''}, "
                                 f"got {eta}")
            values["int_ior"] = eta * values["ext_ior"]
        return consistent(values, keys)
    return changed


def eta_written(values: dict, changed: set[str]) -> dict:
    """The scene-file entries of changed values: a new ``eta`` is written as ``int_ior``."""
    if "eta" in changed:
        changed = (changed - {"eta"}) | {"int_ior"}
    return written(values, changed)


class _Interface:
    """What the dielectrics share: the relative index of refraction they derive from
    their indices, a lobe chosen per sample, both sides scattering, no albedo."""

    derived_keys = ("relative_ior",)
    chooses_lobe = True
    both_sides = True
    albedo = None
    #: Whether its transmission bends rays across the relative index ``relative_ior``
    #: (:attr:`BSDFSample.eta <instancing.materials.bsdf.BSDFSample>`).
    refracts = True

    @staticmethod
    def derived(rows: list[dict]) -> list[dict]:
        """The relative index of refraction int_ior / ext_ior per material (not ``eta``: a
        conductor's parameter of that name shares the table)."""
        return [{"relative_ior": values["int_ior"] / values["ext_ior"]} for values in rows]


class Dielectric(_Interface, DeltaLobe):
    """A smooth interface: reflect wi about the normal with probability F, else refract
    (both delta lobes); weights ``specular_reflectance`` and ``specular_transmittance /
    eta^2`` (the Fresnel factor cancels against the choice)."""

    names = ("dielectric",)
    parameters = _DIELECTRIC

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        return values

    @staticmethod
    def sample(p, wi, u, variant):
        mi = mitsuba_module()
        r_i, cos_theta_t, eta_it, eta_ti = _fresnel(wi.z, p["relative_ior"])
        reflected = u[0] <= r_i
        refracted = Array3f(mi.refract(mi.Vector3f(wi), cos_theta_t, eta_ti))
        wo = dr.select(reflected, Array3f(-wi.x, -wi.y, wi.z), refracted)
        pdf = dr.select(reflected, r_i, 1.0 - r_i)
        weight = dr.select(reflected, p["specular_reflectance"],
                           p["specular_transmittance"] * dr.square(eta_ti)) * chosen(pdf)
        valid = (wi.z != 0) & (pdf > 0)
        return wo, dr.select(valid, weight, 0.0), Float(pdf), valid, Bool(True)


class ThinDielectric(Dielectric):
    """A thin slab: reflect with probability R' = 2R / (1 + R) (its inner reflections
    summed), else pass straight through (wo = -wi); weights ``specular_reflectance`` and
    ``specular_transmittance``."""

    names = ("thindielectric",)
    refracts = False
    traversed = traversed_eta("relative_ior")
    changed = staticmethod(eta_changed(False))
    written = staticmethod(eta_written)

    @staticmethod
    def sample(p, wi, u, variant):
        r = _fresnel(dr.abs(wi.z), p["relative_ior"])[0]
        r = r * 2.0 / (1.0 + r)
        reflected = u[0] <= r
        wo = dr.select(reflected, Array3f(-wi.x, -wi.y, wi.z), -wi)
        pdf = dr.select(reflected, r, 1.0 - r)
        weight = dr.select(reflected, p["specular_reflectance"], p["specular_transmittance"]) * chosen(pdf)
        valid = (wi.z != 0) & (pdf > 0)
        return wo, dr.select(valid, weight, 0.0), Float(pdf), valid, Bool(True)

    @staticmethod
    def null_transmission(p, wi, variant):
        """What passes straight through: ``(1 - R') specular_transmittance`` (Mitsuba's
        ``eval_null_transmission``; the pass-through is its null lobe)."""
        r = _fresnel(dr.abs(wi.z), p["relative_ior"])[0]
        return (1.0 - r * 2.0 / (1.0 + r)) * p["specular_transmittance"]


class RoughDielectric(_Interface, Microfacets):
    """Microfacet reflection and refraction: with h the half vector of wi and wo (for
    refraction wi + eta wo), ``f cos = F D G / (4 |cos_i|)`` reflected and
    ``(1 - F) D G eta^2 |wi.h wo.h| / (|cos_i| (wi.h + eta wo.h)^2) / eta^2`` refracted;
    sampled by visible normals (or by D cos with Walter's widened roughness), the lobe
    chosen by F."""

    names = ("roughdielectric",)
    parameters = {**_DIELECTRIC, **_MICROFACET, **TEXTURED_ROUGHNESS}
    traversed = traversed_eta("relative_ior")
    delta_only = False
    changed = staticmethod(eta_changed(True))
    written = staticmethod(eta_written)

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        if values["int_ior"] == values["ext_ior"]:
            raise SceneError(f"{where}: 'int_ior' and 'ext_ior' must differ (a rough interface "
                             "between equal media is undefined, as in Mitsuba)")
        return resolve_roughness(where, values, given)

    @staticmethod
    def _sampling(p, variant, cos_theta_i):
        """The distribution that samples: Walter et al.'s widened roughness without
        visible-normal sampling."""
        alpha_u, alpha_v = roughness_of(p, variant)
        if not variant[1]:
            widening = 1.2 - 0.2 * dr.sqrt(dr.abs(cos_theta_i))
            alpha_u = alpha_u * widening
            alpha_v = None if alpha_v is None else alpha_v * widening
        return microfacets(variant[0], alpha_u, alpha_v, variant[1])

    @staticmethod
    def _half_vector(p, wi, wo):
        """(reflect, eta seen from wi's side, h with h.z >= 0)."""
        reflect = wi.z * wo.z > 0
        eta = dr.select(wi.z > 0, p["relative_ior"], 1.0 / p["relative_ior"])
        h = dr.normalize(wi + wo * dr.select(reflect, 1.0, eta))
        return reflect, eta, dr.mulsign(h, h.z)

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        mi = mitsuba_module()
        reflect, eta, h = RoughDielectric._half_vector(p, wi, wo)
        distribution = RoughDielectric._distribution(p, variant)
        m = mi.Vector3f(h)
        d = distribution.eval(m)
        g = distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), m)
        f = _fresnel(dr.dot(wi, h), p["relative_ior"])[0]
        wi_h, wo_h = dr.dot(wi, h), dr.dot(wo, h)
        reflected = p["specular_reflectance"] * (f * d * g / (4.0 * dr.abs(wi.z)))
        refracted = p["specular_transmittance"] * dr.abs(
            (1.0 - f) * d * g * wi_h * wo_h / (wi.z * dr.square(wi_h + eta * wo_h)))
        value = dr.select(reflect, reflected, refracted)
        return dr.select((wi.z != 0) & (wo.z != 0), value, 0.0)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        mi = mitsuba_module()
        reflect, eta, h = RoughDielectric._half_vector(p, wi, wo)
        wi_h, wo_h = dr.dot(wi, h), dr.dot(wo, h)
        # Only where the microfacet and the macro-surface agree on each side (as smith_g1).
        ok = (wi.z != 0) & (wo.z != 0) & (wi_h * wi.z > 0) & (wo_h * wo.z > 0)
        jacobian = dr.select(reflect, 1.0 / (4.0 * wo_h), eta * eta * wo_h / dr.square(wi_h + eta * wo_h))
        sampling = RoughDielectric._sampling(p, variant, wi.z)
        density = sampling.pdf(mi.Vector3f(dr.mulsign(wi, wi.z)), mi.Vector3f(h))
        f = _fresnel(wi_h, p["relative_ior"])[0]
        value = density * dr.select(reflect, f, 1.0 - f) * dr.abs(jacobian)
        return dr.select(ok, value, 0.0)

    @staticmethod
    def sample(p, wi, u, variant):
        mi = mitsuba_module()
        sampling = RoughDielectric._sampling(p, variant, wi.z)
        m, pdf = sampling.sample(mi.Vector3f(dr.mulsign(wi, wi.z)), mi.Point2f(u[1], u[2]))
        m = Array3f(m)
        f, cos_theta_t, eta_it, eta_ti = _fresnel(dr.dot(wi, m), p["relative_ior"])
        reflected = u[0] <= f
        wo = dr.select(reflected, 2.0 * dr.dot(wi, m) * m - wi,
                       Array3f(mi.refract(mi.Vector3f(wi), mi.Normal3f(m), cos_theta_t, eta_ti)))
        eta = dr.select(reflected, 1.0, eta_it)
        wo_m = dr.dot(wo, m)
        jacobian = dr.select(reflected, 1.0 / (4.0 * wo_m),
                             dr.square(eta) * wo_m / dr.square(dr.dot(wi, m) + eta * wo_m))
        distribution = RoughDielectric._distribution(p, variant)
        if variant[1]:
            shadowing = distribution.smith_g1(mi.Vector3f(wo), mi.Vector3f(m))
        else:
            shadowing = (distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), mi.Vector3f(m))
                         * dr.dot(wi, m) / (wi.z * m.z))
        weight = dr.select(reflected, p["specular_reflectance"],
                           p["specular_transmittance"] * dr.square(eta_ti)) * shadowing
        pdf = Float(pdf) * dr.select(reflected, f, 1.0 - f) * dr.abs(jacobian)
        valid = (wi.z != 0) & (pdf > 0) & (dr.all(dr.isfinite(wo)))
        return wo, dr.select(valid, weight, 0.0), pdf, valid, Bool(False)
