"""Mitsuba's ``principled``: Burley's Disney BSDF (2012, and its 2015 extension by a
transmission lobe) as Mitsuba 3.9.1's plugin evaluates, samples and weighs it; and its
``principledthin`` (:class:`PrincipledThin`), which shares the main lobes' roughness, Fresnel
and diffuse terms.

With ``m`` = ``metallic`` and ``t`` = ``spec_trans``, the lobes are:

* main specular reflection: GGX microfacets of alpha_u = max(0.001, ``roughness``^2 / a)
  and alpha_v = max(0.001, ``roughness``^2 a) along the shading frame's axes, with the
  aspect a = sqrt(1 - 0.9 ``anisotropic``), and Smith masking; its Fresnel term mixes the
  dielectric Fresnel reflectance of ``eta`` (weight (1 - m)(1 - ``spec_tint``)), Schlick's
  approximation from ``base_color`` (weight m: the metal) and from the luminance-normalised
  base colour times R0(eta) (weight (1 - m) ``spec_tint``). Seen from inside, only the
  dielectric Fresnel term, weighted by (1 - m) t;
* main specular transmission (weight (1 - m) t, tinted by sqrt(``base_color``)): GGX
  refraction through ``eta`` on both sides, scaled by 1 / eta^2 (radiance);
* clearcoat (weight ``clearcoat`` / 4, front side): the GTR1 distribution of alpha
  lerp(0.1, 0.001, ``clearcoat_gloss``), Schlick's Fresnel from R0 = 0.04 and separable
  Smith GGX masking of alpha 0.25. As in Mitsuba's plugin, its ``f cos`` is ``F D G
  cos_o``: without the 1 / (4 cos_i cos_o) of a microfacet BRDF;
* diffuse (weight (1 - m)(1 - t), front side): Burley's diffuse with retro-reflection,
  blended by ``flatness`` towards the Hanrahan-Krueger-like fake subsurface term; plus
  sheen (weight ``sheen`` (1 - m), tinted towards the base colour by ``sheen_tint``).

Sampling picks one lobe with the first random number, in proportion to the sampling rates
times the lobes' weights (from inside: reflection F, transmission 1 - F), and draws the
main lobes by GGX visible normals, the clearcoat by GTR1 normals and the diffuse lobe by
Mitsuba's cosine-weighted hemisphere, so that Mitsuba's plugin draws the same directions
from the same numbers. Like Mitsuba's, a sample's density is the whole BSDF's density of
the direction and its weight ``f cos / pdf``.

``eta`` (interior / exterior) or ``specular`` (eta = 2 / (1 - sqrt(0.08 specular)) - 1)
give the index of refraction; with a transmission lobe, eta = 1 becomes 1.001 and
specular = 0 becomes 0.001, as Mitsuba's constructor does. Mitsuba switches a lobe off
where its parameter is a literal 0; only the transmission lobe's switch changes a value
(the density from inside), so it is a column of its own (``has_spec_trans``).
"""

from __future__ import annotations

import numpy as np

from ..core.backend import Array3f, Bool, Float, dr, mitsuba_module
from ..core.errors import SceneError
from ..core.warp import INV_PI
from .parameter import COLOR, IOR, NUMBER, Parameter
from .texture import Texture


class _Unstored(Parameter):
    """A number that no kernel reads per lane and the table keeps no column of (kind IOR;
    principled's ``eta`` and ``specular``, which state one index of refraction that the
    table holds as ``relative_ior``; a conductor's ``eta`` column holds colours): a number
    in [low, high] (no named media, as Mitsuba's principled), or None (its default, if
    that is None) where the other one states the index."""

    def parse(self, value, where: str):
        if value is None and self.default is None:
            return None
        return Parameter(NUMBER, self.default, self.low, self.high).parse(value, where)


def _unit(default: float) -> Parameter:
    """A texturable number in [0, 1] (the plugin reads it per lookup)."""
    return Parameter(NUMBER, default, 0.0, 1.0, texture=True)


def _transmits(values: dict) -> bool:
    """Whether Mitsuba's plugin has the transmission lobe: ``spec_trans`` a texture or
    a number other than 0."""
    return isinstance(values["spec_trans"], Texture) or values["spec_trans"] != 0


def _schlick_weight(cos_theta: Float) -> Float:
    """(1 - cos)^5, clamped to [0, 1]."""
    m = dr.clip(1.0 - cos_theta, 0.0, 1.0)
    return dr.square(dr.square(m)) * m


def _schlick(r0, cos_theta: Float, eta: Float):
    """Schlick's Fresnel reflectance from ``r0`` at a microfacet of cosine ``cos_theta``
    with wi (negative: from inside), taken at the transmitted angle where light leaves the
    denser side (the plugin's ``calc_schlick``)."""
    outside = cos_theta >= 0.0
    rcp_eta = dr.rcp(eta)
    eta_it = dr.select(outside, eta, rcp_eta)
    eta_ti = dr.select(outside, rcp_eta, eta)
    cos_theta_t = dr.safe_sqrt(dr.fma(-dr.fma(-cos_theta, cos_theta, 1.0), dr.square(eta_ti), 1.0))
    return dr.select(eta_it > 1.0, dr.lerp(_schlick_weight(dr.abs(cos_theta)), 1.0, r0),
                     dr.lerp(_schlick_weight(cos_theta_t), 1.0, r0))


def _gtr1(alpha: Float, cos_theta: Float) -> Float:
    """The GTR1 (Berry) normal distribution of the clearcoat."""
    alpha2 = dr.square(alpha)
    d = (alpha2 - 1.0) / (dr.pi * dr.log(alpha2) * (1.0 + (alpha2 - 1.0) * dr.square(cos_theta)))
    return dr.select(d * cos_theta > 1e-20, d, 0.0)


def _smith_ggx1(v: Array3f, m: Array3f, alpha: float) -> Float:
    """Smith's GGX masking of direction v by microfacets m (the clearcoat's, alpha fixed)."""
    cos2 = dr.square(dr.abs(v.z))
    tan2 = (1.0 - cos2) / cos2
    g = 2.0 * dr.rcp(1.0 + dr.sqrt(1.0 + alpha * alpha * tan2))
    g = dr.select(v.z == 1.0, 1.0, g)
    return dr.select(dr.dot(v, m) * v.z <= 0.0, 0.0, g)


def _compatible(m: Array3f, wi: Array3f, wo: Array3f, reflection: bool) -> Bool:
    """Whether wi faces the microfacet m (turned to wi's side) and wo leaves it on wi's
    side (reflection) or on the other (transmission)."""
    facing = dr.mulsign(m, wi.z)
    wo_m = dr.dot(wo, facing)
    return (dr.dot(wi, facing) > 0.0) & ((wo_m > 0.0) if reflection else (wo_m < 0.0))


class Principled:
    """Mitsuba's ``principled`` (see the module docstring)."""

    names = ("principled",)
    parameters = {
        "base_color": Parameter(COLOR, 0.5, 0.0, 1.0, texture=True),
        "roughness": _unit(0.5),
        "anisotropic": Parameter(NUMBER, 0.0, 0.0, 1.0, texture=True),
        "metallic": _unit(0.0), "spec_trans": _unit(0.0),
        "eta": _Unstored(IOR, None, 0.0), "specular": _Unstored(IOR, 0.5, 0.0, 1.0),
        "spec_tint": _unit(0.0), "sheen": _unit(0.0), "sheen_tint": _unit(0.0),
        "flatness": _unit(0.0), "clearcoat": _unit(0.0), "clearcoat_gloss": _unit(0.0),
        "diffuse_reflectance_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
        "main_specular_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
        "clearcoat_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
    }
    #: Its index of refraction as traverse exposes it (however the file states it).
    traversed = {"eta": Parameter(NUMBER, None, 0.0, differentiable_constant=True,
                                  column="relative_ior")}
    derived_keys = ("relative_ior", "has_spec_trans")
    delta_only = False
    refracts = True
    chooses_lobe = True
    #: Both sides only with a transmission lobe (without one it reflects on its front only,
    #: and a twosided may hold it, as Mitsuba's).
    both_sides = staticmethod(_transmits)
    albedo = "base_color"

    @staticmethod
    def changed(values: dict, keys: set[str]) -> dict:
        """A new ``eta`` (from traverse) states the index of refraction: ``specular`` goes."""
        if "eta" in keys:
            if not values["eta"] > 0:
                raise SceneError(f"'eta' must be positive, got {values['eta']}")
            values["specular"] = None
        return values

    @staticmethod
    def written(values: dict, changed: set[str]) -> dict:
        """The scene-file entries of changed values (a new ``eta`` drops ``specular``)."""
        entries = {key: values[key] for key in changed}
        if "eta" in changed:
            entries["specular"] = None
        return entries

    @staticmethod
    def anisotropic(values: dict) -> bool:
        """Whether its main lobes' roughness differs along the shading frame's axes (an
        ``anisotropic`` weight other than 0, or a texture)."""
        return isinstance(values["anisotropic"], Texture) or values["anisotropic"] != 0

    @staticmethod
    def exposed(values: dict, key: str) -> bool:
        """:func:`instancing.traverse` exposes ``anisotropic`` where the material is
        anisotropic (its hits then carry the tangent that orients it)."""
        return key != "anisotropic" or Principled.anisotropic(values)

    @staticmethod
    def microfacet_alpha(p, variant=None) -> Float:
        """The main lobes' GGX roughness: the geometric mean of their alpha_u and alpha_v,
        which is max(0.001, roughness^2) without anisotropy."""
        alpha_u, alpha_v = _main_roughness(p)
        return dr.sqrt(alpha_u * alpha_v)

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        """Refuse both ``eta`` and ``specular``; keep the one given (else ``specular``), the
        other None."""
        if {"eta", "specular"} <= given:
            raise SceneError(f"{where}: give either 'eta' or 'specular', not both (they state "
                             "one index of refraction, as in Mitsuba)")
        if "eta" in given:
            if not values["eta"]:
                raise SceneError(f"{where}: 'eta' must be a positive number, got {values['eta']!r}")
            values["specular"] = None
        return values

    @staticmethod
    def derived(rows: list[dict]) -> list[dict]:
        """Per material the relative index of refraction (in float32, as Mitsuba's
        constructor computes it) and whether it has the transmission lobe (1 or 0)."""
        result = []
        for values in rows:
            transmits = _transmits(values)
            if values["eta"] is not None:
                eta = np.float32(values["eta"])
                eta = np.float32(1.001) if transmits and eta == 1 else eta
            else:
                specular = np.float32(values["specular"])
                specular = np.float32(1e-3) if transmits and specular == 0 else specular
                one = np.float32(1)
                eta = np.float32(2) * (one / (one - np.sqrt(np.float32(0.08) * specular))) - one
            result.append({"relative_ior": float(eta), "has_spec_trans": float(transmits)})
        return result

    @staticmethod
    def variant(values: dict) -> tuple:
        return ()

    @staticmethod
    def _half_vector(p, wi, wo):
        """(front, reflect, refract, eta seen from wi's side, h turned to +z, the dielectric
        Fresnel reflectance at h, GGX of the main lobes)."""
        mi = mitsuba_module()
        front = wi.z > 0.0
        reflect = wi.z * wo.z > 0.0
        refract = wi.z * wo.z < 0.0
        eta = p["relative_ior"]
        eta_path = dr.select(front, eta, dr.rcp(eta))
        h = dr.normalize(wi + wo * dr.select(reflect, 1.0, eta_path))
        h = dr.mulsign(h, h.z)
        f = mi.fresnel(dr.dot(wi, h), eta)[0]
        return front, reflect, refract, eta_path, h, f, _main_lobes(p)

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        """f cos(theta_o): the lobes' sum (module docstring)."""
        mi = mitsuba_module()
        front, reflect, refract, eta_path, h, f, distribution = Principled._half_vector(p, wi, wo)
        eta, base, metallic = p["relative_ior"], p["base_color"], p["metallic"]
        brdf = (1.0 - metallic) * (1.0 - p["spec_trans"])
        bsdf = (1.0 - metallic) * p["spec_trans"]
        wi_h, wo_h = dr.dot(wi, h), dr.dot(wo, h)
        compatible_reflection = _compatible(h, wi, wo, True)
        m = mi.Vector3f(h)
        d = distribution.eval(m)
        g = distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), m)
        luminance = mi.luminance(mi.Color3f(base))
        tint = dr.select(luminance > 0.0, base / luminance, 1.0)
        value = Array3f(0.0)

        # Main specular reflection: the principled Fresnel term (module docstring).
        eta_it = dr.select(wi_h >= 0.0, eta, dr.rcp(eta))
        r0_tint = tint * dr.square((eta_it - 1.0) / (eta_it + 1.0))
        schlick = (metallic * _schlick(base, wi_h, eta)
                   + (1.0 - metallic) * p["spec_tint"] * _schlick(r0_tint, wi_h, eta))
        fresnel = dr.select(front, (1.0 - metallic) * (1.0 - p["spec_tint"]) * f + schlick, bsdf * f)
        on = reflect & compatible_reflection & (f > 0.0)
        value = dr.select(on, value + fresnel * d * g / (4.0 * dr.abs(wi.z)), value)

        # Main specular transmission, with the radiance's solid-angle compression.
        on = (bsdf > 0.0) & refract & _compatible(h, wi, wo, False) & (f < 1.0)
        scale = dr.square(dr.rcp(eta_path))
        transmitted = dr.sqrt(base) * bsdf * dr.abs(
            (scale * (1.0 - f) * d * g * eta_path * eta_path * wi_h * wo_h)
            / (wi.z * dr.square(wi_h + eta_path * wo_h)))
        value = dr.select(on, value + transmitted, value)

        # Clearcoat.
        clearcoat = p["clearcoat"]
        on = (clearcoat > 0.0) & reflect & compatible_reflection & front
        coat = ((clearcoat * 0.25) * _schlick(0.04, wi_h, eta)
                * _gtr1(dr.lerp(0.1, 0.001, p["clearcoat_gloss"]), h.z)
                * _smith_ggx1(wi, h, 0.25) * _smith_ggx1(wo, h, 0.25) * dr.abs(wo.z))
        value = dr.select(on, value + coat, value)

        # Diffuse with retro-reflection, blended towards the fake subsurface term.
        cos_i, cos_o = dr.abs(wi.z), dr.abs(wo.z)
        f_i, f_o = _schlick_weight(cos_i), _schlick_weight(cos_o)
        f_diffuse = (1.0 - 0.5 * f_i) * (1.0 - 0.5 * f_o)
        cos_d = dr.dot(h, wo)
        rr = 2.0 * p["roughness"] * dr.square(cos_d)
        f_retro = rr * (f_o + f_i + f_o * f_i * (rr - 1.0))
        f_ss90 = rr / 2.0
        f_ss = dr.lerp(1.0, f_ss90, f_o) * dr.lerp(1.0, f_ss90, f_i)
        subsurface = 1.25 * (f_ss * (1.0 / (cos_o + cos_i) - 0.5) + 0.5)
        on = (brdf > 0.0) & reflect & front
        diffuse = (brdf * cos_o * base * INV_PI
                   * dr.lerp(f_diffuse + f_retro, subsurface, p["flatness"]))
        value = dr.select(on, value + diffuse, value)

        # Sheen.
        sheen = p["sheen"]
        on = (sheen > 0.0) & reflect & (1.0 - metallic > 0.0) & front
        colour = dr.lerp(1.0, tint, p["sheen_tint"])
        value = dr.select(on, value + sheen * (1.0 - metallic) * _schlick_weight(dr.abs(cos_d))
                          * colour * cos_o, value)
        return dr.select(wi.z != 0.0, value, 0.0)

    @staticmethod
    def _probabilities(p, front: Bool, f: Float):
        """The chances of sampling transmission, clearcoat and diffuse (the main reflection
        takes the rest): front side by the sampling rates and weights, inside reflection
        F and transmission 1 - F."""
        bsdf = (1.0 - p["metallic"]) * p["spec_trans"]
        brdf = (1.0 - p["metallic"]) * (1.0 - p["spec_trans"])
        rate = p["main_specular_sampling_rate"]
        reflection = dr.select(front, rate * (1.0 - bsdf * (1.0 - f)), f)
        transmission = dr.select(p["has_spec_trans"] != 0,
                                 dr.select(front, rate * bsdf * (1.0 - f), 1.0 - f), 0.0)
        clearcoat = dr.select(front, 0.25 * p["clearcoat"] * p["clearcoat_sampling_rate"], 0.0)
        diffuse = dr.select(front, brdf * p["diffuse_reflectance_sampling_rate"], 0.0)
        return _normalised(reflection, transmission, clearcoat, diffuse)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        """The density with which :meth:`sample` draws wo: the lobes' densities weighted
        by their chances."""
        mi = mitsuba_module()
        front, reflect, refract, eta_path, h, f, distribution = Principled._half_vector(p, wi, wo)
        reflection, transmission, clearcoat, diffuse = Principled._probabilities(p, front, f)
        wi_h, wo_h = dr.dot(wi, h), dr.dot(wo, h)
        # dh / dwo of the reflected or refracted direction.
        jacobian = dr.abs(dr.select(reflect, dr.rcp(4.0 * wo_h),
                                    dr.square(eta_path) * wo_h / dr.square(wi_h + eta_path * wo_h)))
        visible = distribution.pdf(mi.Vector3f(dr.mulsign(wi, wi.z)), mi.Vector3f(h))
        reflected = _compatible(h, wi, wo, True) & reflect
        pdf = dr.select(reflected, reflection * visible * jacobian, 0.0)
        pdf = dr.select(reflect, pdf + diffuse * (INV_PI * wo.z), pdf)
        refracted = (p["has_spec_trans"] != 0) & _compatible(h, wi, wo, False) & refract
        pdf = dr.select(refracted, pdf + transmission * visible * jacobian, pdf)
        coat = dr.select(h.z < 0.0, 0.0, h.z * _gtr1(dr.lerp(0.1, 0.001, p["clearcoat_gloss"]), h.z))
        return dr.select(reflected, pdf + clearcoat * coat * jacobian, pdf)

    @staticmethod
    def sample(p, wi, u, variant):
        """A lobe chosen by u[0], a direction from (u[1], u[2]) as Mitsuba's plugin draws
        them; weight f cos / pdf of the whole BSDF."""
        mi = mitsuba_module()
        front = wi.z > 0.0
        eta = p["relative_ior"]
        square = mi.Point2f(u[1], u[2])
        m_spec = Array3f(_main_lobes(p).sample(mi.Vector3f(dr.mulsign(wi, wi.z)), square)[0])
        f, cos_theta_t, _, eta_ti = mi.fresnel(dr.dot(wi, m_spec), eta)
        _, transmission, clearcoat, diffuse = Principled._probabilities(p, front, f)
        bsdf = (1.0 - p["metallic"]) * p["spec_trans"]
        active = (wi.z != 0.0) & (front | (bsdf > 0.0))

        # The lobe: diffuse, clearcoat, transmission, main reflection in turn along u[0].
        picks_diffuse = u[0] < diffuse
        below = diffuse
        picks_clearcoat = (u[0] >= below) & (u[0] < below + clearcoat)
        below = below + clearcoat
        picks_transmission = (u[0] >= below) & (u[0] < below + transmission)
        below = below + transmission
        picks_reflection = u[0] >= below

        # Each lobe's direction, valid where it leaves on the side the lobe scatters to.
        reflected = Array3f(mi.reflect(mi.Vector3f(wi), mi.Normal3f(m_spec)))
        refracted = Array3f(mi.refract(mi.Vector3f(wi), mi.Normal3f(m_spec), cos_theta_t, eta_ti))
        m_coat = _gtr1_sample(dr.lerp(0.1, 0.001, p["clearcoat_gloss"]), u[1], u[2])
        coated = Array3f(mi.reflect(mi.Vector3f(wi), mi.Normal3f(m_coat)))
        scattered = Array3f(mi.warp.square_to_cosine_hemisphere(square))
        wo = dr.select(picks_reflection, reflected,
                       dr.select(picks_transmission, refracted,
                                 dr.select(picks_clearcoat, coated, scattered)))
        ok = dr.select(picks_reflection, _compatible(m_spec, wi, reflected, True)
                       & (wi.z * reflected.z > 0.0),
                       dr.select(picks_transmission, _compatible(m_spec, wi, refracted, False)
                                 & (wi.z * refracted.z < 0.0),
                                 dr.select(picks_clearcoat, _compatible(m_coat, wi, coated, True)
                                           & (wi.z * coated.z > 0.0),
                                           picks_diffuse & (wi.z * scattered.z > 0.0))))
        pdf = Principled.pdf(p, wi, wo, variant)
        valid = active & ok & (pdf > 0.0)
        weight = Principled.eval(p, wi, wo, variant) / pdf
        return wo, dr.select(valid, weight, 0.0), pdf, valid, Bool(False)


def _normalised(*weights: Float) -> tuple[Float, ...]:
    """The lobes' sampling weights divided by their sum: the chances of picking each."""
    scale = dr.rcp(sum(weights[1:], weights[0]))
    return tuple(weight * scale for weight in weights)


def _main_roughness(p) -> tuple[Float, Float]:
    """The main lobes' GGX (alpha_u, alpha_v) (Mitsuba's, from the Disney course notes):
    roughness^2 stretched by the aspect sqrt(1 - 0.9 anisotropic), at least 0.001."""
    aspect = dr.sqrt(1.0 - 0.9 * p["anisotropic"])
    squared = dr.square(p["roughness"])
    return dr.maximum(0.001, squared / aspect), dr.maximum(0.001, squared * aspect)


def _main_lobes(p):
    """The GGX distribution of the main reflection and transmission (visible normals)."""
    mi = mitsuba_module()
    return mi.MicrofacetDistribution(mi.MicrofacetType.GGX, *_main_roughness(p))


def _gtr1_sample(alpha: Float, u1: Float, u2: Float) -> Array3f:
    """A clearcoat microfacet normal drawn from D cos of the GTR1 distribution."""
    sin_phi, cos_phi = dr.sincos(dr.two_pi * u1)
    alpha2 = dr.square(alpha)
    cos2 = (1.0 - dr.power(alpha2, 1.0 - u2)) / (1.0 - alpha2)
    sin_theta = dr.sqrt(dr.maximum(0.0, 1.0 - cos2))
    return Array3f(cos_phi * sin_theta, sin_phi * sin_theta, dr.sqrt(dr.maximum(0.0, cos2)))


class PrincipledThin:
    """Mitsuba's ``principledthin``: Burley's thin-surface BSDF (2015), symmetric in the
    surface's two sides (wi is turned to the front, wo with it), as Mitsuba 3.9.1's plugin
    evaluates, samples and weighs it. With ``t`` = ``spec_trans`` and ``d`` =
    ``diff_trans`` / 2 (a weight in [0, 2] made one in [0, 1]), and h the half vector of wi
    and wo mirrored to wi's side:

    * specular reflection (weight t): GGX of the main lobes' roughness (as ``principled``'s)
      at h, Fresnel the dielectric reflectance of ``eta`` blended by ``spec_tint`` towards
      Schlick's approximation from the luminance-normalised base colour times R0(eta);
    * specular transmission (weight t, tinted by ``base_color``, times 1 - the dielectric
      Fresnel): the mirror image below the surface of a GGX reflection whose roughness is
      scaled by 0.65 eta - 0.35 (the slab does not bend light: eta 1 on the way through);
    * diffuse reflection (weight (1 - t)(1 - d)): Burley's diffuse with retro-reflection,
      blended by ``flatness`` towards the fake subsurface term, plus sheen as
      ``principled``'s;
    * diffuse transmission (weight (1 - t) d): Lambertian, tinted by ``base_color``.

    Sampling picks one of the four with the first random number in proportion to t / 2,
    t / 2, (1 - t)(1 - d) and (1 - t) d times their sampling rates, and draws the
    specular ones by GGX visible normals and the diffuse ones by Mitsuba's cosine-weighted
    hemisphere (below the surface for transmission), so that Mitsuba's plugin draws the same
    directions from the same numbers.
    """

    names = ("principledthin",)
    parameters = {
        "base_color": Parameter(COLOR, 0.5, 0.0, 1.0, texture=True),
        "roughness": _unit(0.5),
        "anisotropic": Parameter(NUMBER, 0.0, 0.0, 1.0, texture=True),
        "spec_trans": _unit(0.0),
        "eta": Parameter(NUMBER, 1.5, 0.0, texture=True, column="thin_eta"),
        "spec_tint": _unit(0.0), "sheen": _unit(0.0), "sheen_tint": _unit(0.0),
        "flatness": _unit(0.0),
        "diff_trans": Parameter(NUMBER, 0.0, 0.0, 2.0, texture=True),
        "diffuse_reflectance_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
        "specular_reflectance_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
        "specular_transmittance_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
        "diffuse_transmittance_sampling_rate": Parameter(NUMBER, 1.0, 0.0),
    }
    delta_only = False
    chooses_lobe = True
    both_sides = True
    albedo = "base_color"
    anisotropic = staticmethod(Principled.anisotropic)
    exposed = staticmethod(Principled.exposed)
    microfacet_alpha = staticmethod(Principled.microfacet_alpha)
    variant = staticmethod(Principled.variant)

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        """Refuse an ``eta`` of 0 (the slab's index of refraction is positive)."""
        if not isinstance(values["eta"], Texture) and not values["eta"] > 0:
            raise SceneError(f"{where}: 'eta' must be a positive number, got {values['eta']!r}")
        return values

    @staticmethod
    def _frame(p, wi, wo):
        """(wi and wo turned so that wi lies on the front, reflect, refract, the half vector
        h of wi and wo mirrored to the front, the dielectric Fresnel reflectance at h)."""
        mi = mitsuba_module()
        wi_front, wo_front = dr.mulsign(wi, wi.z), dr.mulsign(wo, wi.z)
        reflect, refract = wo_front.z > 0.0, wo_front.z < 0.0
        h = dr.normalize(wi_front + Array3f(wo_front.x, wo_front.y, dr.abs(wo_front.z)))
        f = mi.fresnel(dr.dot(wi_front, h), p["eta"])[0]
        return wi_front, wo_front, reflect, refract, h, f

    @staticmethod
    def _lobes(p):
        """The GGX distributions of the specular reflection and of the transmission (its
        roughness scaled by 0.65 eta - 0.35)."""
        mi = mitsuba_module()
        scaled = dict(p, roughness=(0.65 * p["eta"] - 0.35) * p["roughness"])
        return _main_lobes(p), mi.MicrofacetDistribution(mi.MicrofacetType.GGX, *_main_roughness(scaled))

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        """f cos(theta_o): the lobes' sum (class docstring)."""
        mi = mitsuba_module()
        wi, wo, reflect, refract, h, f = PrincipledThin._frame(p, wi, wo)
        base, t, d = p["base_color"], p["spec_trans"], 0.5 * p["diff_trans"]
        cos_i, cos_o = dr.abs(wi.z), wo.z
        reflection, transmission = PrincipledThin._lobes(p)
        m, wi_m, wo_m = mi.Vector3f(h), mi.Vector3f(wi), mi.Vector3f(wo)
        luminance = mi.luminance(mi.Color3f(base))
        tint = dr.select(luminance > 0.0, base / luminance, 1.0)
        value = Array3f(0.0)

        # Specular reflection, its Fresnel term tinted by spec_tint.
        r0_tint = tint * dr.square((p["eta"] - 1.0) / (p["eta"] + 1.0))
        fresnel = dr.lerp(f, _schlick(r0_tint, dr.dot(wi, h), p["eta"]), p["spec_tint"])
        on = (t > 0.0) & reflect & _compatible(h, wi, wo, True)
        value = dr.select(on, value + t * fresnel * reflection.eval(m) * reflection.G(wi_m, wo_m, m)
                          / (4.0 * cos_i), value)

        # Specular transmission through the slab.
        on = (t > 0.0) & refract & _compatible(h, wi, wo, False)
        value = dr.select(on, value + t * base * (1.0 - f) * transmission.eval(m)
                          * transmission.G(wi_m, wo_m, m) / (4.0 * cos_i), value)

        # Diffuse reflection with retro-reflection, blended towards the fake subsurface term,
        # and sheen.
        f_i, f_o = _schlick_weight(cos_i), _schlick_weight(dr.abs(cos_o))
        cos_d = dr.dot(h, wo)
        rr = 2.0 * p["roughness"] * dr.square(cos_d)
        f_retro = rr * (f_o + f_i + f_o * f_i * (rr - 1.0))
        f_ss = dr.lerp(1.0, rr / 2.0, f_o) * dr.lerp(1.0, rr / 2.0, f_i)
        subsurface = 1.25 * (f_ss * (1.0 / (dr.abs(cos_o) + cos_i) - 0.5) + 0.5)
        f_diffuse = (1.0 - 0.5 * f_i) * (1.0 - 0.5 * f_o)
        weight = (1.0 - t) * (1.0 - d)
        on = reflect & (t < 1.0) & (d < 1.0)
        diffuse = weight * cos_o * base * INV_PI * dr.lerp(f_diffuse + f_retro, subsurface, p["flatness"])
        sheen = (p["sheen"] * weight * _schlick_weight(dr.abs(cos_d)) * dr.lerp(1.0, tint, p["sheen_tint"])
                 * dr.abs(cos_o))
        value = dr.select(on, value + diffuse + dr.select(p["sheen"] > 0.0, sheen, 0.0), value)

        # Lambertian transmission.
        on = refract & (t < 1.0) & (d > 0.0)
        value = dr.select(on, value + (1.0 - t) * d * base * INV_PI * dr.abs(cos_o), value)
        return dr.select(wi.z != 0.0, value, 0.0)

    @staticmethod
    def _probabilities(p):
        """The chances of sampling specular reflection, specular transmission and diffuse
        reflection (diffuse transmission takes the rest)."""
        t, d = p["spec_trans"], 0.5 * p["diff_trans"]
        reflection = t * p["specular_reflectance_sampling_rate"] / 2.0
        transmission = t * p["specular_transmittance_sampling_rate"] / 2.0
        diffuse = p["diffuse_reflectance_sampling_rate"] * (1.0 - t) * (1.0 - d)
        through = p["diffuse_transmittance_sampling_rate"] * (1.0 - t) * d
        return _normalised(reflection, transmission, diffuse, through)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        """The density with which :meth:`sample` draws wo: the lobes' densities weighted
        by their chances."""
        mi = mitsuba_module()
        wi, wo, reflect, refract, h, _ = PrincipledThin._frame(p, wi, wo)
        reflection, transmission = PrincipledThin._lobes(p)
        chance_reflection, chance_transmission, chance_diffuse, chance_through = \
            PrincipledThin._probabilities(p)
        # dh / dwo of the mirrored direction.
        jacobian = dr.abs(dr.rcp(4.0 * dr.dot(Array3f(wo.x, wo.y, dr.abs(wo.z)), h)))
        wi_m, m = mi.Vector3f(wi), mi.Vector3f(h)
        pdf = dr.select(reflect & _compatible(h, wi, wo, True),
                        chance_reflection * reflection.pdf(wi_m, m) * jacobian, 0.0)
        pdf = dr.select(refract & _compatible(h, wi, wo, False),
                        pdf + chance_transmission * transmission.pdf(wi_m, m) * jacobian, pdf)
        pdf = dr.select(reflect, pdf + chance_diffuse * INV_PI * wo.z, pdf)
        pdf = dr.select(refract, pdf + chance_through * INV_PI * -wo.z, pdf)
        return dr.select(wi.z != 0.0, pdf, 0.0)

    @staticmethod
    def sample(p, wi, u, variant):
        """A lobe chosen by u[0], a direction from (u[1], u[2]) as Mitsuba's plugin draws
        them; weight f cos / pdf of the whole BSDF."""
        mi = mitsuba_module()
        front = dr.mulsign(wi, wi.z)
        square = mi.Point2f(u[1], u[2])
        chance_reflection, chance_transmission, chance_diffuse, _ = PrincipledThin._probabilities(p)
        picks_reflection = u[0] < chance_reflection
        below = chance_reflection
        picks_transmission = (u[0] >= below) & (u[0] < below + chance_transmission)
        below = below + chance_transmission
        picks_diffuse = (u[0] >= below) & (u[0] < below + chance_diffuse)
        picks_through = (u[0] >= below + chance_diffuse) & (p["diff_trans"] > 0.0)

        # Each lobe's direction on wi's front, valid where it leaves on the lobe's side.
        reflection, transmission = PrincipledThin._lobes(p)
        wi_m = mi.Vector3f(front)
        m_reflection = Array3f(reflection.sample(wi_m, square)[0])
        reflected = Array3f(mi.reflect(wi_m, mi.Normal3f(m_reflection)))
        m_transmission = Array3f(transmission.sample(wi_m, square)[0])
        mirrored = Array3f(mi.reflect(wi_m, mi.Normal3f(m_transmission)))
        transmitted = Array3f(mirrored.x, mirrored.y, -mirrored.z)
        scattered = Array3f(mi.warp.square_to_cosine_hemisphere(square))
        wo = dr.select(picks_reflection, reflected,
                       dr.select(picks_transmission, transmitted,
                                 dr.select(picks_diffuse, scattered, -scattered)))
        reflects = _compatible(m_reflection, front, reflected, True) & (reflected.z > 0.0)
        transmits = _compatible(m_transmission, front, transmitted, False) & (transmitted.z < 0.0)
        ok = dr.select(picks_reflection, reflects,
                       dr.select(picks_transmission, transmits, picks_diffuse | picks_through))
        wo = dr.mulsign(wo, wi.z)
        pdf = PrincipledThin.pdf(p, wi, wo, variant)
        valid = (wi.z != 0.0) & ok & (pdf > 0.0)
        weight = PrincipledThin.eval(p, wi, wo, variant) / pdf
        return wo, dr.select(valid, weight, 0.0), pdf, valid, Bool(False)
