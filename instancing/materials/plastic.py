"""Mitsuba's ``plastic`` (a diffuse base under a smooth dielectric coating),
``roughplastic`` (under a rough, microfacet coating) and ``pplastic`` (the rough coating of
Baek et al.'s polarized plastic, as Mitsuba's unpolarized variants render it).

Light either reflects off the coating (a delta lobe, or a microfacet lobe) or enters it,
scatters diffusely in the base and leaves through it, with the Fresnel transmittance on
the way in and out and the internal reflections of the coating summed in closed form
(Mitsuba's ``fdr_int`` / its rough internal reflectance; ``nonlinear``: the base colour
takes part in them). One of the two is sampled, in proportion to how much light each
carries (Mitsuba's specular sampling weight). The rough coating's transmittance per
incident angle is tabulated per material (64 cosines, Gauss-Legendre quadrature over the
visible normals, as Mitsuba precomputes it) and interpolated linearly. ``pplastic`` has no
internal reflections: its base is seen through the smooth interface's Fresnel transmittance
on the way in and out, and it picks its lobe with a fixed probability.
"""

from __future__ import annotations

import numpy as np

from ..core.backend import Array3f, Bool, Float, Float64, UInt32, dr, mitsuba_module
from ..core.errors import SceneError
from ..core.warp import INV_PI, square_to_cosine_hemisphere
from .conductor import _MICROFACET, TEXTURED_ROUGHNESS, Microfacets, microfacets, resolve_roughness
from .dielectric import eta_changed, eta_written, traversed_eta
from .parameter import COLOR, FLAG, IOR, NUMBER, Parameter
from .texture import mean_value

#: Cosines at which a rough coating's transmittance is tabulated (Mitsuba's resolution).
TRANSMITTANCE_RESOLUTION = 64

_PLASTIC = {
    "diffuse_reflectance": Parameter(COLOR, 0.5, 0.0, 1.0, texture=True),
    "specular_reflectance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
    "int_ior": Parameter(IOR, "polypropylene"), "ext_ior": Parameter(IOR, "air"),
    "nonlinear": Parameter(FLAG, False),
}


def _fresnel(cos_theta: Float, eta: Float) -> Float:
    """The unpolarized dielectric Fresnel reflectance (Mitsuba's ``fresnel``)."""
    return mitsuba_module().fresnel(cos_theta, eta)[0]


def _check_means(where: str, values: dict) -> dict:
    """``values``, once both reflectances are known to have a mean (the coating's sampling
    weight reads them; a mesh attribute has none)."""
    for key in ("diffuse_reflectance", "specular_reflectance"):
        try:
            mean_value(values[key])
        except SceneError as err:
            raise SceneError(f"{where}: {key!r}: {err}") from None
    return values


def _specular_sampling_weight(values: dict) -> float:
    """The share of samples a coating's specular lobe gets: its reflectance's mean over both
    reflectances' means (a half where both are black: the material reflects nothing)."""
    d_mean = mean_value(values["diffuse_reflectance"])
    s_mean = mean_value(values["specular_reflectance"])
    return s_mean / (d_mean + s_mean) if d_mean + s_mean > 0 else 0.5


def _coating(values: dict) -> dict:
    """The relative index of refraction and the specular sampling weight of a coating."""
    eta = values["int_ior"] / values["ext_ior"]
    return {"coating_eta": eta, "inv_eta_2": 1.0 / (eta * eta),
            "specular_sampling_weight": _specular_sampling_weight(values),
            "nonlinear": float(values["nonlinear"])}


def _microfacet_reflection(distribution, sample_visible: bool, eta: Float, wi: Array3f, wo: Array3f):
    """A rough coating's reflection off its microfacets, ``F D G / (4 cos_i)`` (f cos), and
    the density with which its distribution samples wo (by visible normals or by D cos)."""
    mi = mitsuba_module()
    h = dr.normalize(wi + wo)
    m = mi.Vector3f(h)
    d = distribution.eval(m)
    f = _fresnel(dr.dot(wi, h), eta)
    value = f * d * distribution.G(mi.Vector3f(wi), mi.Vector3f(wo), m) / (4.0 * wi.z)
    if sample_visible:
        pdf = d * distribution.smith_g1(mi.Vector3f(wi), m) / (4.0 * wi.z)
    else:
        pdf = distribution.pdf(mi.Vector3f(wi), m) / (4.0 * dr.dot(wo, h))
    return value, pdf


def _sample_rough_coating(lobe, p, wi, u, variant, distribution, specular: Float):
    """A direction of a rough coating's lobes: reflected off a microfacet normal sampled from
    ``distribution`` with probability ``specular``, else from the cosine-weighted hemisphere;
    weighted by the lobe's ``f cos`` over its mixture density."""
    mi = mitsuba_module()
    m = Array3f(distribution.sample(mi.Vector3f(wi), mi.Point2f(u[1], u[2]))[0])
    reflected = 2.0 * dr.dot(wi, m) * m - wi
    wo = dr.select(u[0] < specular, reflected, square_to_cosine_hemisphere(u[1], u[2]))
    pdf = lobe.pdf(p, wi, wo, variant)
    value = lobe.eval(p, wi, wo, variant)
    valid = (wi.z > 0) & (pdf > 0)
    return wo, dr.select(valid, value / pdf, 0.0), pdf, valid, Bool(False)


def _diffuse_base(p: dict, internal: Float) -> Array3f:
    """The base colour after the coating's internal reflections."""
    base = p["diffuse_reflectance"]
    return base / (1.0 - dr.select(p["nonlinear"] != 0, base * internal, internal))


def _lerp_table(table: Float, row: UInt32, x: Float) -> Float:
    """Linear interpolation of a row of TRANSMITTANCE_RESOLUTION samples over [0, 1]."""
    x = x * (TRANSMITTANCE_RESOLUTION - 1)
    index = dr.minimum(UInt32(dr.maximum(x, 0.0)), TRANSMITTANCE_RESOLUTION - 2)
    first = row * TRANSMITTANCE_RESOLUTION + index
    v0, v1 = dr.gather(Float, table, first), dr.gather(Float, table, first + 1)
    return dr.lerp(v0, v1, x - Float(index))


class Plastic:
    """Smooth coating: the specular lobe is a delta (reflect wi, weight F(cos theta_i)),
    the diffuse one ``f cos = base / (1 - fdr_int) (1 - F_i) (1 - F_o) cos_o / (pi eta^2)``."""

    names = ("plastic",)
    parameters = _PLASTIC
    derived_keys = ("coating_eta", "inv_eta_2", "specular_sampling_weight", "nonlinear", "fdr_int")
    delta_only = False
    samples_delta = True
    chooses_lobe = True
    albedo = "diffuse_reflectance"

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        return _check_means(where, values)

    @staticmethod
    def derived(rows: list[dict]) -> list[dict]:
        coatings = [_coating(values) for values in rows]
        mi = mitsuba_module()
        fdr = np.ravel(mi.fresnel_diffuse_reflectance(
            Float(np.array([1.0 / c["coating_eta"] for c in coatings], np.float32))))
        for coating, value in zip(coatings, np.broadcast_to(fdr, (len(coatings),))):
            coating["fdr_int"] = float(value)
        return coatings

    @staticmethod
    def variant(values: dict) -> tuple:
        return ()

    @staticmethod
    def _probabilities(p, cos_theta_i):
        f_i = _fresnel(cos_theta_i, p["coating_eta"])
        specular = f_i * p["specular_sampling_weight"]
        diffuse = (1.0 - f_i) * (1.0 - p["specular_sampling_weight"])
        specular = specular / (specular + diffuse)
        return f_i, specular, 1.0 - specular

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        f_i, f_o = _fresnel(wi.z, p["coating_eta"]), _fresnel(wo.z, p["coating_eta"])
        value = (_diffuse_base(p, p["fdr_int"])
                 * (INV_PI * wo.z * p["inv_eta_2"] * (1.0 - f_i) * (1.0 - f_o)))
        return dr.select((wi.z > 0) & (wo.z > 0), value, 0.0)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        _, _, diffuse = Plastic._probabilities(p, wi.z)
        return dr.select((wi.z > 0) & (wo.z > 0), INV_PI * wo.z * diffuse, 0.0)

    @staticmethod
    def sample(p, wi, u, variant):
        f_i, specular, diffuse = Plastic._probabilities(p, wi.z)
        chose_specular = u[0] < specular
        diffuse_wo = square_to_cosine_hemisphere(u[1], u[2])
        wo = dr.select(chose_specular, Array3f(-wi.x, -wi.y, wi.z), diffuse_wo)
        pdf = dr.select(chose_specular, specular, diffuse * INV_PI * diffuse_wo.z)
        f_o = _fresnel(diffuse_wo.z, p["coating_eta"])
        diffuse_weight = (_diffuse_base(p, p["fdr_int"])
                          * (p["inv_eta_2"] * (1.0 - f_i) * (1.0 - f_o) / diffuse))
        weight = dr.select(chose_specular, p["specular_reflectance"] * (f_i / dr.detach(specular)),
                           diffuse_weight)
        valid = (wi.z > 0) & (pdf > 0)
        return wo, dr.select(valid, weight, 0.0), pdf, valid, chose_specular


class _RoughCoating:
    """What the rough coatings share: a diffuse base, a lobe chosen per sample, and the
    coating's relative index of refraction exposed as ``eta`` (setting it sets ``int_ior``)."""

    traversed = traversed_eta("coating_eta")
    delta_only = False
    chooses_lobe = True
    albedo = "diffuse_reflectance"
    changed = staticmethod(eta_changed(True))
    written = staticmethod(eta_written)


class RoughPlastic(_RoughCoating):
    """Rough coating (Mitsuba's ``roughplastic``): ``f cos = F D G / (4 cos_i) s +
    base / (1 - r_int) t(cos_i) t(cos_o) cos_o / (pi eta^2)``, t the coating's tabulated
    transmittance, r_int its internal reflectance; isotropic microfacets only.

    Its roughness ``alpha`` and relative index of refraction ``eta`` are differentiable (as
    Mitsuba's traverse marks them): where they carry derivatives, the tables t and r_int
    add their own derivatives, tabulated on demand by the same quadrature in forward mode
    (:meth:`~instancing.materials.bsdf.BSDFTable.tabulate_derivatives`), times the
    parameter's offset from its detached value."""

    names = ("roughplastic",)
    parameters = {**_PLASTIC, **_MICROFACET,
                  "alpha": Parameter(NUMBER, 0.1, 0.0, differentiable_constant=True)}
    #: The parameters its tables are computed from, and the derived values (the tables) whose
    #: derivatives ``derivatives`` tabulates (as ``<table>_d_<parameter>``).
    tabulated_from = ("alpha", "eta")
    tabulated = ("coating_transmittance", "internal_reflectance")
    derived_keys = ("coating_eta", "specular_sampling_weight", "nonlinear", *tabulated,
                    "coating_transmittance_d_alpha", "coating_transmittance_d_eta",
                    "internal_reflectance_d_alpha", "internal_reflectance_d_eta")

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        if values["int_ior"] == values["ext_ior"]:
            raise SceneError(f"{where}: 'int_ior' and 'ext_ior' must differ")
        return resolve_roughness(where, _check_means(where, values), given, anisotropic=False)

    @staticmethod
    def derived(rows: list[dict]) -> list[dict]:
        coatings = [_coating(values) for values in rows]
        for distribution in {values["distribution"] for values in rows}:
            mine = [k for k, values in enumerate(rows) if values["distribution"] == distribution]
            tables, internal = rough_coatings(
                distribution, np.array([rows[k]["alpha"] for k in mine]),
                np.array([coatings[k]["coating_eta"] for k in mine]))
            for j, k in enumerate(mine):
                coatings[k].update(coating_transmittance=tables[j], internal_reflectance=float(internal[j]))
        return coatings

    @staticmethod
    def derivatives(rows: list[dict], key: str) -> list[dict]:
        """Per material (values): the derivatives of its tables with respect to ``key``
        ("alpha" or "eta"), keyed ``<table>_d_<key>``."""
        result = [{} for _ in rows]
        for distribution in {values["distribution"] for values in rows}:
            mine = [k for k, values in enumerate(rows) if values["distribution"] == distribution]
            tables, internal = rough_coatings(
                distribution, np.array([rows[k]["alpha"] for k in mine]),
                np.array([rows[k]["int_ior"] / rows[k]["ext_ior"] for k in mine]), key)
            for j, k in enumerate(mine):
                result[k] = {f"coating_transmittance_d_{key}": tables[j],
                             f"internal_reflectance_d_{key}": float(internal[j])}
        return result

    @staticmethod
    def _tabulated(p, key: str, at: Float | None = None) -> Float:
        """Table ``key`` of the lanes' rows (interpolated at cosine ``at``; a number where
        None), plus, where alpha or eta carry derivatives, the table's derivatives times
        their offsets from their detached values."""
        def read(name):
            return p[name] if at is None else _lerp_table(p[name], p["row"], at)

        value = read(key)
        for name, parameter in (("alpha", p["alpha"]), ("eta", p["coating_eta"])):
            if f"{key}_d_{name}" in p and dr.grad_enabled(parameter):
                value = value + (parameter - dr.detach(parameter)) * read(f"{key}_d_{name}")
        return value

    @staticmethod
    def variant(values: dict) -> tuple:
        return (values["distribution"], values["sample_visible"])

    @staticmethod
    def _specular(p, wi, wo, variant):
        """The coating's microfacet reflection f cos and its sampling density."""
        distribution = microfacets(variant[0], p["alpha"], sample_visible=variant[1])
        return _microfacet_reflection(distribution, variant[1], p["coating_eta"], wi, wo)

    @staticmethod
    def _probabilities(p, row, cos_theta_i):
        t_i = _lerp_table(p["coating_transmittance"], row, cos_theta_i)
        specular = (1.0 - t_i) * p["specular_sampling_weight"]
        diffuse = t_i * (1.0 - p["specular_sampling_weight"])
        specular = specular / (specular + diffuse)
        return t_i, specular, 1.0 - specular

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        specular, _ = RoughPlastic._specular(p, wi, wo, variant)
        t_i = RoughPlastic._tabulated(p, "coating_transmittance", wi.z)
        t_o = RoughPlastic._tabulated(p, "coating_transmittance", wo.z)
        diffuse = (_diffuse_base(p, RoughPlastic._tabulated(p, "internal_reflectance"))
                   * (INV_PI * dr.rcp(dr.square(p["coating_eta"])) * wo.z * t_i * t_o))
        value = p["specular_reflectance"] * specular + diffuse
        return dr.select((wi.z > 0) & (wo.z > 0), value, 0.0)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        _, pdf_specular = RoughPlastic._specular(p, wi, wo, variant)
        _, specular, diffuse = RoughPlastic._probabilities(p, p["row"], wi.z)
        ok = (wi.z > 0) & (wo.z > 0)
        return dr.select(ok, specular * pdf_specular + diffuse * INV_PI * wo.z, 0.0)

    @staticmethod
    def sample(p, wi, u, variant):
        distribution = microfacets(variant[0], p["alpha"], sample_visible=variant[1])
        _, specular, _ = RoughPlastic._probabilities(p, p["row"], wi.z)
        return _sample_rough_coating(RoughPlastic, p, wi, u, variant, distribution, specular)


class PolarizedPlastic(_RoughCoating, Microfacets):
    """Mitsuba's ``pplastic`` in its unpolarized variants: ``f cos = s F(wi . h) D G /
    (4 cos_i) + base (1 - F(cos_i)) (1 - F(cos_o)) cos_o / pi``, F the dielectric Fresnel
    reflectance of ``eta = int_ior / ext_ior`` (or ``eta`` itself); Beckmann or GGX, isotropic
    or anisotropic, the roughness a texture where given. The specular lobe is sampled with
    probability ``mean(s) / (mean(s) + mean(base))`` whatever the angle, the other by the
    cosine-weighted hemisphere."""

    names = ("pplastic",)
    parameters = {"diffuse_reflectance": Parameter(COLOR, 0.5, 0.0, 1.0, texture=True),
                  "specular_reflectance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
                  "int_ior": Parameter(IOR, "polypropylene"), "ext_ior": Parameter(IOR, "air"),
                  "eta": Parameter(IOR, 1.0), **_MICROFACET, **TEXTURED_ROUGHNESS}
    derived_keys = ("coating_eta", "specular_sampling_weight")

    @staticmethod
    def resolve(where: str, values: dict, given: set[str]) -> dict:
        """The interface's ``eta`` as ``int_ior`` over ``ext_ior`` (either is given, not
        both, as Mitsuba), the roughness resolved, the reflectances' means checked."""
        eta = values.pop("eta")
        if "eta" in given:
            if given & {"int_ior", "ext_ior"}:
                raise SceneError(f"{where}: give either 'eta' or 'int_ior' and 'ext_ior', not both")
            values["int_ior"], values["ext_ior"] = eta, 1.0
        if values["int_ior"] == values["ext_ior"]:
            raise SceneError(f"{where}: the interior and exterior indices of refraction must differ, "
                             f"got {values['int_ior']} both")
        return resolve_roughness(where, _check_means(where, values), given)

    @staticmethod
    def derived(rows: list[dict]) -> list[dict]:
        return [{"coating_eta": values["int_ior"] / values["ext_ior"],
                 "specular_sampling_weight": _specular_sampling_weight(values)} for values in rows]

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        specular, _ = _microfacet_reflection(PolarizedPlastic._distribution(p, variant), variant[1],
                                             p["coating_eta"], wi, wo)
        through = (1.0 - _fresnel(wi.z, p["coating_eta"])) * (1.0 - _fresnel(wo.z, p["coating_eta"]))
        value = p["specular_reflectance"] * specular + p["diffuse_reflectance"] * (through * INV_PI * wo.z)
        return dr.select((wi.z > 0) & (wo.z > 0), value, 0.0)

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        _, pdf_specular = _microfacet_reflection(PolarizedPlastic._distribution(p, variant), variant[1],
                                                 p["coating_eta"], wi, wo)
        specular = p["specular_sampling_weight"]
        value = specular * pdf_specular + (1.0 - specular) * INV_PI * wo.z
        return dr.select((wi.z > 0) & (wo.z > 0), value, 0.0)

    @staticmethod
    def sample(p, wi, u, variant):
        return _sample_rough_coating(PolarizedPlastic, p, wi, u, variant,
                                     PolarizedPlastic._distribution(p, variant),
                                     p["specular_sampling_weight"])


#: Lanes of one quadrature kernel at most (the materials are integrated in batches).
QUADRATURE_LANES = 1 << 22


#: Steps of the central differences that tabulate the coating's derivatives. (Forward mode
#: through the quadrature misses 8 % of the internal reflectance's: the integrand's
#: derivative has an integrable singularity at the critical angle.) The quadrature's values
#: wobble by ~0.3 % of their slope at steps of 0.005 in eta, so eta steps by 0.02.
DERIVATIVE_STEPS = {"alpha": 5e-3, "eta": 2e-2}


def rough_coatings(distribution: str, alphas: np.ndarray, etas: np.ndarray,
                   derivative: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rough dielectric coatings' transmittance at TRANSMITTANCE_RESOLUTION cosines in [0, 1]
    (from outside; (M, 64)) and internal reflectance (from inside, cosine-weighted; (M,)), as
    Mitsuba's roughplastic precomputes them per material: Gauss-Legendre quadrature (32 x 32
    nodes for a relative IOR above 1, 128 x 128 below) over the visible normals, with
    Fresnel and Smith masking. Many materials are integrated in one kernel. With
    ``derivative`` ("alpha" or "eta"): the derivatives of both with respect to it instead,
    by central differences of DERIVATIVE_STEPS (halved near 0 for a small alpha)."""
    if derivative is not None:
        given = {"alpha": np.asarray(alphas, np.float64), "eta": np.asarray(etas, np.float64)}
        step = np.minimum(DERIVATIVE_STEPS[derivative], 0.5 * given[derivative])
        if derivative == "eta":  # (stay on one side of 1)
            step = np.minimum(step, 0.5 * np.abs(given["eta"] - 1.0))
        ends = [rough_coatings(distribution, *[given[k] + sign * step if k == derivative else given[k]
                                               for k in ("alpha", "eta")])
                for sign in (1.0, -1.0)]
        return tuple((up - down) / (2.0 * (step[:, None] if up.ndim == 2 else step))
                     for up, down in zip(*ends))
    mu = np.maximum(1e-6, np.linspace(0.0, 1.0, TRANSMITTANCE_RESOLUTION))
    table = _coating_quadrature(distribution, alphas, etas, mu, transmit=True)
    internal = 2.0 * (_coating_quadrature(distribution, alphas, 1.0 / etas, mu, transmit=False)
                      * mu).mean(axis=1)
    return table, internal


def _coating_quadrature(distribution: str, alphas: np.ndarray, etas: np.ndarray, mu: np.ndarray,
                        transmit: bool) -> np.ndarray:
    """(M, len(mu)): the light a rough interface of relative IOR ``etas`` transmits
    (``transmit``) or reflects, for incident cosines ``mu``, unshadowed by Smith masking.

    One lane per (material, cosine, node), the materials in batches of at most
    QUADRATURE_LANES lanes: each lane finds its cosine, node and material by index, and the
    weighted nodes of each (material, cosine) are summed in float64 on the device."""
    mi = mitsuba_module()
    out = np.zeros((len(alphas), len(mu)))
    cosines = Float(np.asarray(mu, np.float32))
    for res in (32, 128):
        rows = np.flatnonzero((etas > 1) == (res == 32))
        if not len(rows):
            continue
        nodes, weights = np.polynomial.legendre.leggauss(res)
        node_x, node_y = (Float((a.ravel() * 0.5 + 0.5).astype(np.float32))
                          for a in np.meshgrid(nodes, nodes))
        node_weight = Float64(np.outer(weights, weights).T.ravel() * 0.25)
        square = res * res
        per_material = len(mu) * square
        step = max(1, QUADRATURE_LANES // per_material)
        for first in range(0, len(rows), step):
            chunk = rows[first:first + step]
            lane = dr.arange(UInt32, len(chunk) * per_material)
            node, pair = lane % square, lane // square
            cos = dr.gather(Float, cosines, pair % len(mu))
            wi = mi.Vector3f(dr.sqrt(1.0 - cos * cos), 0.0, cos)
            material = pair // len(mu)
            alpha = dr.gather(Float, Float(alphas[chunk].astype(np.float32)), material)
            eta = dr.gather(Float, Float(etas[chunk].astype(np.float32)), material)
            dist = microfacets(distribution, alpha)
            m = dist.sample(wi, mi.Point2f(dr.gather(Float, node_x, node), dr.gather(Float, node_y, node)))[0]
            f, cos_t, _, eta_ti = mi.fresnel(dr.dot(wi, m), eta)
            if transmit:
                wo = mi.refract(wi, m, cos_t, eta_ti)
                value = dr.select(wo.z * wi.z >= 0, 0.0, dist.smith_g1(wo, m) * (1.0 - f))
            else:
                wo = mi.reflect(wi, m)
                value = dr.select((wo.z <= 0) | (wi.z <= 0), 0.0, dist.smith_g1(wo, m) * f)
            sums = dr.block_sum(Float64(value) * dr.gather(Float64, node_weight, node), square)
            out[chunk] = np.asarray(sums, np.float64).reshape(len(chunk), len(mu))
    return out
