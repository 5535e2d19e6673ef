"""The materials layer (instancing/materials): BSDF kernels against Mitsuba's own plugins
on the same directions and random numbers, parameter validation, and the flat table.

Reference: Mitsuba 3's BSDF plugins (``mi.load_dict``), evaluated with ``eval``, ``pdf``
and ``sample`` on a surface interaction whose shading frame is the identity, so that our
shading-frame directions are theirs. Agreement is to float32 round-off (relative 1e-4 of
the values' scale; Mitsuba computes in float32 too).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

import instancing  # noqa: F401  (selects libLLVM before Dr.Jit starts)
from instancing.core.backend import BACKEND_NAME, Array2f, Array3f, Float, UInt32, dr, mitsuba_module
from instancing.core.errors import SceneError
from instancing.io.mitsuba_export import mitsuba_bsdf
from instancing.materials.bsdf import BSDFTable
from instancing.materials.material import parse_material
from scene_helpers import GivenNumbers

N = 4096
#: Materials covering every kernel and variant, with Mitsuba's parameter names.
MATERIALS = {
    "diffuse": {"type": "diffuse", "reflectance": [0.2, 0.5, 0.7]},
    "twosided": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": 0.3}},
    "twosided_two": {"type": "twosided", "front": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]},
                     "back": {"type": "roughconductor", "alpha": 0.3}},
    "conductor_named": {"type": "conductor", "material": "Au"},
    "conductor_eta_k": {"type": "conductor", "eta": [0.2, 0.9, 1.1], "k": [3.0, 2.5, 2.2],
                        "specular_reflectance": [0.9, 0.8, 0.7]},
    "rough_beckmann": {"type": "roughconductor", "material": "Cu", "alpha": 0.25},
    "rough_ggx": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.15,
                  "eta": [0.3, 0.4, 0.5], "k": 2.0},
    "rough_ggx_no_visible": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.4,
                             "sample_visible": False},
    "rough_uv_equal": {"type": "roughconductor", "alpha_u": 0.2, "alpha_v": 0.2},
    "rough_anisotropic": {"type": "roughconductor", "material": "Al", "alpha_u": 0.05, "alpha_v": 0.3},
    "rough_anisotropic_ggx_no_visible": {"type": "roughconductor", "distribution": "ggx",
                                         "alpha_u": 0.4, "alpha_v": 0.1, "sample_visible": False},
    "plastic": {"type": "plastic", "diffuse_reflectance": [0.6, 0.2, 0.1]},
    "plastic_water_nonlinear": {"type": "plastic", "int_ior": "water", "nonlinear": True,
                                "specular_reflectance": 0.8},
    "roughplastic": {"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": [0.1, 0.4, 0.7]},
    "roughplastic_ggx_nonlinear": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.35,
                                   "nonlinear": True, "int_ior": 1.6},
    "dielectric": {"type": "dielectric", "int_ior": 1.6, "specular_transmittance": [0.9, 0.8, 0.7]},
    "dielectric_water_in_glass": {"type": "dielectric", "int_ior": "water", "ext_ior": "bk7"},
    "thindielectric": {"type": "thindielectric", "specular_reflectance": 0.7},
    "roughdielectric": {"type": "roughdielectric", "alpha": 0.3},
    "roughdielectric_ggx": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.15,
                            "int_ior": "diamond", "specular_reflectance": [0.9, 1.0, 0.8]},
    "roughdielectric_no_visible": {"type": "roughdielectric", "alpha": 0.4, "sample_visible": False},
    "roughdielectric_anisotropic": {"type": "roughdielectric", "distribution": "ggx", "alpha_u": 0.1,
                                    "alpha_v": 0.35},
    "roughdielectric_anisotropic_no_visible": {"type": "roughdielectric", "alpha_u": 0.3, "alpha_v": 0.05,
                                               "sample_visible": False},
    "blend_diffuse_rough": {"type": "blendbsdf", "weight": 0.3,
                            "bsdf_0": {"type": "diffuse", "reflectance": [0.7, 0.3, 0.2]},
                            "bsdf_1": {"type": "roughconductor", "material": "Au", "alpha": 0.2}},
    "blend_plastic_mirror": {"type": "blendbsdf", "weight": 0.6,
                             "bsdf_0": {"type": "roughplastic", "alpha": 0.3},
                             "bsdf_1": {"type": "conductor", "material": "Ag"}},
    "twosided_blend": {"type": "twosided", "bsdf": {
        "type": "blendbsdf", "weight": 0.5, "a": {"type": "diffuse", "reflectance": 0.6},
        "b": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1}}},
    "mask_diffuse": {"type": "mask", "opacity": 0.3, "bsdf": {"type": "diffuse", "reflectance": 0.6}},
    "mask_twosided": {"type": "mask", "opacity": 0.7, "leaf": {
        "type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.3}}},
    "null": {"type": "null"},
    "polarizer": {"type": "polarizer", "theta": 30.0, "transmittance": [0.9, 0.6, 0.3]},
    "pplastic": {"type": "pplastic", "diffuse_reflectance": [0.05, 0.03, 0.1], "alpha": 0.06},
    "pplastic_ggx_anisotropic": {"type": "pplastic", "distribution": "ggx", "alpha_u": 0.3,
                                 "alpha_v": 0.08, "int_ior": "bk7",
                                 "specular_reflectance": [0.9, 0.7, 0.8]},
    "pplastic_eta_no_visible": {"type": "pplastic", "eta": 1.7, "alpha": 0.25, "sample_visible": False,
                                "diffuse_reflectance": [0.6, 0.4, 0.2]},
    "blend_twosided_part": {"type": "blendbsdf", "weight": 0.4,
                            "bsdf_0": {"type": "diffuse", "reflectance": [0.2, 0.6, 0.3]},
                            "bsdf_1": {"type": "twosided", "bsdf": {"type": "roughplastic", "alpha": 0.2}}},
    "principled_default": {"type": "principled"},
    "principled_metal": {"type": "principled", "base_color": [0.9, 0.6, 0.3], "metallic": 0.8,
                         "roughness": 0.3, "spec_tint": 0.4},
    "principled_glass": {"type": "principled", "spec_trans": 0.9, "eta": 1.45, "roughness": 0.2,
                         "base_color": [0.9, 0.95, 1.0]},
    "principled_coat_sheen": {"type": "principled", "base_color": [0.2, 0.4, 0.7], "clearcoat": 0.8,
                              "clearcoat_gloss": 0.6, "sheen": 0.7, "sheen_tint": 0.5, "roughness": 0.6},
    "principled_all": {"type": "principled", "base_color": [0.8, 0.3, 0.2], "roughness": 0.35,
                       "anisotropic": 0.0, "metallic": 0.3, "spec_trans": 0.4, "specular": 0.6,
                       "spec_tint": 0.3, "sheen": 0.4, "sheen_tint": 0.6, "flatness": 0.5,
                       "clearcoat": 0.5, "clearcoat_gloss": 0.8, "diffuse_reflectance_sampling_rate": 0.7,
                       "main_specular_sampling_rate": 1.5, "clearcoat_sampling_rate": 0.5},
    # Mitsuba's fix-ups with a transmission lobe: eta 1 becomes 1.001, specular 0 becomes 0.001.
    "principled_anisotropic": {"type": "principled", "base_color": [0.7, 0.5, 0.3], "roughness": 0.4,
                               "anisotropic": 0.8, "metallic": 0.6, "spec_trans": 0.3},
    "principled_eta_one": {"type": "principled", "spec_trans": 1.0, "eta": 1.0, "sheen": 0.8},
    "twosided_principled": {"type": "twosided", "bsdf": {"type": "principled", "metallic": 0.3,
                                                         "base_color": [0.3, 0.6, 0.2]}},
    "principled_specular_zero": {"type": "principled", "spec_trans": 0.5, "specular": 0.0,
                                 "roughness": 0.1},
    "principledthin_default": {"type": "principledthin"},
    "principledthin_glassy": {"type": "principledthin", "spec_trans": 0.9, "eta": 1.33, "roughness": 0.2,
                              "base_color": [0.9, 0.95, 1.0], "spec_tint": 0.3},
    "principledthin_leaf": {"type": "principledthin", "base_color": [0.3, 0.6, 0.1], "diff_trans": 1.2,
                            "roughness": 0.6, "flatness": 0.5, "sheen": 0.6, "sheen_tint": 0.4,
                            "spec_trans": 0.2, "eta": 1.4},
    "principledthin_anisotropic": {"type": "principledthin", "base_color": [0.7, 0.5, 0.3],
                                   "roughness": 0.4, "anisotropic": 0.8, "spec_trans": 0.5, "eta": 1.6,
                                   "diff_trans": 0.5, "specular_reflectance_sampling_rate": 0.5,
                                   "specular_transmittance_sampling_rate": 1.5,
                                   "diffuse_reflectance_sampling_rate": 0.8,
                                   "diffuse_transmittance_sampling_rate": 1.2},
    "principledthin_paper": {"type": "principledthin", "diff_trans": 2.0, "base_color": [0.8, 0.8, 0.7]},
}
#: Materials whose delta lobe passes light straight through (wo = -wi): masks, null and the
#: polarizer.
PASS_THROUGH = ("mask_diffuse", "mask_twosided", "null", "polarizer")
#: Blends with a delta part: that part alone (its weight is compared with Mitsuba's).
DELTA_PARTS = {"blend_plastic_mirror": MATERIALS["blend_plastic_mirror"]["bsdf_1"]}
#: Principled materials: with ``spec_trans`` they scatter on both sides (Mitsuba's plugin
#: has a density from inside, and transmits), their lobes sampled as Mitsuba's.
PRINCIPLED = tuple(name for name in MATERIALS if name.startswith("principled"))
#: Materials that scatter on both sides (into the surface too): their densities are compared
#: everywhere, their samples direction by direction.
TRANSMISSIVE = ("dielectric", "dielectric_water_in_glass", "thindielectric", "roughdielectric",
                "roughdielectric_ggx", "roughdielectric_no_visible", "roughdielectric_anisotropic",
                "roughdielectric_anisotropic_no_visible")


def _directions(rng, n, lower=False):
    """n random unit directions, above the surface (z > 0) or anywhere with ``lower``."""
    w = rng.normal(size=(n, 3))
    if not lower:
        w[:, 2] = np.abs(w[:, 2])
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def _rows(v) -> np.ndarray:
    """(N, 3) float64 rows of an Array3f (a width-1 value broadcast to N rows)."""
    return np.broadcast_to(np.asarray(v, np.float64).T.reshape(-1, 3), (N, 3)) if dr.width(v) <= 1 \
        else np.asarray(v, np.float64).T


#: Materials whose Mitsuba plugin fails on its CUDA variant (cuda_ad_rgb, Mitsuba 3.9.1, seen
#: on an H200): compared with Mitsuba on LLVM only.
MITSUBA_CUDA_FAULTS = {
    "blend_twosided_part": "Mitsuba's blendbsdf holding a twosided BSDF: CUDA_ERROR_ILLEGAL_ADDRESS "
                           "in its eval kernel, which aborts the process",
}


def _skip_where_mitsuba_faults(name: str) -> None:
    if BACKEND_NAME == "cuda" and name in MITSUBA_CUDA_FAULTS:
        pytest.skip(MITSUBA_CUDA_FAULTS[name])


def _mitsuba_side(spec: dict, wi: np.ndarray):
    mi = mitsuba_module()
    bsdf = mi.load_dict(mitsuba_bsdf(parse_material("m", spec)))
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*[Float(wi[:, k].astype(np.float32)) for k in range(3)])
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    return mi, bsdf, si


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_eval_and_pdf_are_mitsubas(name):
    """f cos and the sampling density for random wi, wo on both sides of the surface."""
    _skip_where_mitsuba_faults(name)
    spec = MATERIALS[name]
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    wi, wo = _directions(rng, N, lower=True), _directions(rng, N, lower=True)
    table = BSDFTable([parse_material("m", spec)])
    ours_f = _rows(table.evaluate(UInt32(0), Array3f(*wi.T.astype(np.float32)), Array3f(*wo.T.astype(np.float32))))
    ours_pdf = np.broadcast_to(np.asarray(table.pdf(UInt32(0), Array3f(*wi.T.astype(np.float32)),
                                                    Array3f(*wo.T.astype(np.float32)))), (N,))
    mi, bsdf, si = _mitsuba_side(spec, wi)
    wo_mi = mi.Vector3f(*[Float(wo[:, k].astype(np.float32)) for k in range(3)])
    theirs_f = _rows(bsdf.eval(mi.BSDFContext(), si, wo_mi))
    theirs_pdf = np.broadcast_to(np.asarray(bsdf.pdf(mi.BSDFContext(), si, wo_mi), np.float64), (N,))
    scale = max(np.abs(theirs_f).max(), 1e-6)
    np.testing.assert_allclose(ours_f, theirs_f, rtol=1e-4, atol=1e-5 * scale)
    # Densities where both directions lie on one side for the BSDFs that only reflect: on
    # opposite sides Mitsuba's roughplastic returns its lobes' formulas unmasked (its
    # eval is 0 there, so no image sees it); ours is 0. A principled BSDF without a
    # transmission lobe reflects on its front only: Mitsuba's density from inside, where its
    # eval is 0, is not compared.
    front_only = name in PRINCIPLED and not parse_material("m", spec).both_sides
    same_side = (wi[:, 2] * wo[:, 2] > 0) | (name in TRANSMISSIVE + PRINCIPLED and not front_only)
    if front_only:
        same_side &= wi[:, 2] > 0
    np.testing.assert_allclose(ours_pdf[same_side], theirs_pdf[same_side], rtol=1e-4,
                               atol=1e-5 * max(theirs_pdf.max(), 1e-6))
    assert (ours_pdf[~same_side] == 0).all()
    if not table.has_mirror:
        assert (theirs_f > 0).any(), "the directions must reach the lobe"


#: Materials whose sampling routine is Mitsuba's own (its microfacet sampling): the same
#: random numbers give the same directions. (Our cosine-weighted hemisphere lifts a polar
#: disk sample, Mitsuba's a concentric one: equal densities, other directions.)
SAME_DIRECTIONS = ("rough_beckmann", "rough_ggx", "rough_ggx_no_visible", "rough_uv_equal",
                   "rough_anisotropic", "rough_anisotropic_ggx_no_visible",
                   "conductor_named", "conductor_eta_k") + PRINCIPLED


def _sampled(spec: dict, seed: list[int]):
    """(wi, u, sample): N random wi on both sides, the random numbers u (N, 3), and the
    material's samples drawn with them (u[:, 0] where it chooses a lobe, as Mitsuba's)."""
    rng = np.random.default_rng(seed)
    wi = _directions(rng, N, lower=True)
    u = rng.random((N, 3)).astype(np.float32)
    table = BSDFTable([parse_material("m", spec)])
    numbers = [Float(u[:, k]) for k in range(3)] if table.chooses_lobe else [Float(u[:, 1]), Float(u[:, 2])]
    return wi, u, table.sample(UInt32(0), Array3f(*wi.T.astype(np.float32)), GivenNumbers(*numbers))


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_samples_agree_with_mitsuba(name):
    """Sampled directions: their weight is f cos / pdf with Mitsuba's f and pdf (the
    delta lobes': Mitsuba's sample weight), their density Mitsuba's pdf, and where the
    sampling routine is Mitsuba's, the same random numbers give its directions."""
    _skip_where_mitsuba_faults(name)
    spec = MATERIALS[name]
    wi, u, sample = _sampled(spec, [100, zlib.crc32(name.encode())])
    mi, bsdf, si = _mitsuba_side(spec, wi)
    ctx = mi.BSDFContext()
    ours_wo = _rows(sample.wo)
    valid = np.asarray(sample.valid)
    assert valid.mean() > 0.3
    wo_mi = mi.Vector3f(*[Float(ours_wo[:, k].astype(np.float32)) for k in range(3)])
    delta = np.broadcast_to(np.asarray(sample.delta), (N,))
    mitsuba_sample = lambda: bsdf.sample(ctx, si, Float(u[:, 0]),  # noqa: E731
                                         mi.Point2f(Float(u[:, 1]), Float(u[:, 2])))
    if name in PASS_THROUGH:
        # The null lobe, chosen by Mitsuba with the same number: wo = -wi, Mitsuba's weight.
        bs, weight = mitsuba_sample()
        theirs_null = np.broadcast_to((np.asarray(bs.sampled_type) & int(mi.BSDFFlags.Null)) != 0, (N,))
        np.testing.assert_array_equal(delta[valid], theirs_null[valid])
        through = valid & delta
        assert through.mean() > 0.2
        np.testing.assert_allclose(ours_wo[through], -wi[through], atol=1e-6)
        np.testing.assert_allclose(_rows(sample.weight)[through], _rows(weight)[through], rtol=1e-6)
        valid = valid & ~delta
        if not valid.any():
            return
    elif delta.all() and name in TRANSMISSIVE:
        # Reflected or refracted, chosen by the same number: Mitsuba's direction and weight.
        bs, weight = mitsuba_sample()
        np.testing.assert_allclose(ours_wo[valid], np.asarray(bs.wo, np.float64).T[valid], atol=2e-6)
        np.testing.assert_allclose(_rows(sample.weight)[valid], np.asarray(weight, np.float64).T[valid],
                                   rtol=1e-4, atol=1e-6)
        assert (ours_wo[valid, 2] * wi[valid, 2] < 0).mean() > 0.3  # transmission exercised
        return
    if delta.all():
        # A mirror: wo is wi reflected about the normal, weighted as Mitsuba weighs it.
        np.testing.assert_allclose(ours_wo[valid], (wi * [-1, -1, 1])[valid], atol=1e-6)
        bs, weight = mitsuba_sample()
        np.testing.assert_allclose(_rows(sample.weight), np.asarray(weight, np.float64).T,
                                   rtol=1e-4, atol=1e-6)
        return
    if delta.any() and name in DELTA_PARTS:
        # A blend's delta part keeps its own weight (chosen with the blend's probability,
        # it carries the part's whole delta lobe). Mitsuba 3.9.1's blendbsdf divides it by
        # the mixture density w + (1 - w) p_other after adding (1 - w) f_other, values of
        # the smooth part in a delta direction, which biases the mixture.
        _, part, part_si = _mitsuba_side(DELTA_PARTS[name], wi)
        _, weight = part.sample(ctx, part_si, Float(u[:, 0]), mi.Point2f(Float(u[:, 1]), Float(u[:, 2])))
        mirror = valid & delta
        np.testing.assert_allclose(ours_wo[mirror], (wi * [-1, -1, 1])[mirror], atol=1e-6)
        np.testing.assert_allclose(_rows(sample.weight)[mirror], np.asarray(weight, np.float64).T[mirror],
                                   rtol=1e-4, atol=1e-6)
        assert 0.4 < delta[valid].mean() < 0.8  # the weight 0.6 picks the mirror
        valid = valid & ~delta
    elif delta.any():
        # A delta lobe beside a smooth one (plastic's coating): Mitsuba picks the same
        # lobe with the same number, reflects the same way and weighs it the same.
        bs, weight = mitsuba_sample()
        theirs_delta = (np.asarray(bs.sampled_type) & int(mi.BSDFFlags.Delta)) != 0
        np.testing.assert_array_equal(delta[valid], theirs_delta[valid])
        mirror = valid & delta
        np.testing.assert_allclose(ours_wo[mirror], (wi * [-1, -1, 1])[mirror], atol=1e-6)
        np.testing.assert_allclose(_rows(sample.weight)[mirror], np.asarray(weight, np.float64).T[mirror],
                                   rtol=1e-4, atol=1e-6)
        valid = valid & ~delta
    if name in TRANSMISSIVE:
        # The same microfacet and lobe from the same numbers: Mitsuba's direction, density
        # and weight. (Where a refraction leaves on wi's side, Mitsuba's own pdf(wo) takes it
        # for a reflection and differs from its sample's density.)
        bs, weight = mitsuba_sample()
        np.testing.assert_allclose(ours_wo[valid], np.asarray(bs.wo, np.float64).T[valid], atol=2e-5)
        np.testing.assert_allclose(np.asarray(sample.pdf)[valid], np.asarray(bs.pdf)[valid], rtol=2e-4)
        np.testing.assert_allclose(_rows(sample.weight)[valid], np.asarray(weight, np.float64).T[valid],
                                   rtol=2e-4, atol=1e-6)
        assert (ours_wo[valid, 2] * wi[valid, 2] < 0).mean() > 0.3  # transmission exercised
        return
    f = np.asarray(bsdf.eval(ctx, si, wo_mi), np.float64).T
    pdf = np.asarray(bsdf.pdf(ctx, si, wo_mi), np.float64)
    ok = valid & (pdf > 1e-3)
    np.testing.assert_allclose(np.asarray(sample.pdf)[ok], pdf[ok], rtol=2e-4)
    np.testing.assert_allclose(_rows(sample.weight)[ok], f[ok] / pdf[ok, None], rtol=2e-3, atol=1e-6)
    if name in SAME_DIRECTIONS:
        bs, _ = mitsuba_sample()
        np.testing.assert_allclose(ours_wo[valid], np.asarray(bs.wo, np.float64).T[valid], atol=2e-5)
    if name in PRINCIPLED:
        # The same lobe from the same numbers: Mitsuba's sample weight on every lane (0 where
        # neither finds a valid direction).
        _, weight = mitsuba_sample()
        np.testing.assert_allclose(_rows(sample.weight), np.asarray(weight, np.float64).T,
                                   rtol=1e-4, atol=1e-6)


#: Beside MATERIALS, mixes whose parts let light through (for the null transmission).
PASSING_MIXES = {
    "blend_null_diffuse": {"type": "blendbsdf", "weight": 0.35, "bsdf_0": {"type": "null"},
                           "bsdf_1": {"type": "diffuse", "reflectance": 0.5}},
    "mask_thindielectric": {"type": "mask", "opacity": 0.6, "bsdf": {
        "type": "thindielectric", "int_ior": 1.7, "specular_transmittance": [0.9, 0.5, 0.2]}},
}


@pytest.mark.parametrize("name", sorted(MATERIALS) + sorted(PASSING_MIXES))
def test_null_transmission_is_mitsubas(name):
    """The share of light a material lets straight through (what volpath's shadow rays keep
    at a surface), for random wi on both sides, is Mitsuba's ``eval_null_transmission``: 1
    for null, transmittance / 2 for the polarizer, (1 - R') T for a thin dielectric, mixed
    by masks and blends, 0 for every other BSDF."""
    _skip_where_mitsuba_faults(name)
    spec = {**MATERIALS, **PASSING_MIXES}[name]
    rng = np.random.default_rng([200, zlib.crc32(name.encode())])
    wi = _directions(rng, N, lower=True)
    table = BSDFTable([parse_material("m", spec)])
    ours = _rows(table.null_transmission(UInt32(0), Array3f(*wi.T.astype(np.float32))))
    mi, bsdf, si = _mitsuba_side(spec, wi)
    theirs = _rows(bsdf.eval_null_transmission(si))
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-7)
    passes = name in PASS_THROUGH or name in PASSING_MIXES or name == "thindielectric"
    assert (ours.max() > 0.1) == passes


@pytest.mark.parametrize("name", sorted(MATERIALS) + sorted(PASSING_MIXES))
def test_a_sample_passes_through_where_mitsubas_takes_its_null_lobe(name):
    """From the same random numbers, a sample is flagged as passing straight through exactly
    where Mitsuba's sample takes a ``Null`` lobe (which its volpath does not count as a
    bounce)."""
    _skip_where_mitsuba_faults(name)
    spec = {**MATERIALS, **PASSING_MIXES}[name]
    wi, u, sample = _sampled(spec, [300, zlib.crc32(name.encode())])
    mi, bsdf, si = _mitsuba_side(spec, wi)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, Float(u[:, 0]), mi.Point2f(Float(u[:, 1]), Float(u[:, 2])))
    valid = np.broadcast_to(np.asarray(sample.valid), (N,)) & (np.asarray(bs.pdf) > 0)
    ours = np.broadcast_to(np.asarray(sample.null), (N,))
    theirs = np.broadcast_to((np.asarray(bs.sampled_type) & int(mi.BSDFFlags.Null)) != 0, (N,))
    np.testing.assert_array_equal(ours[valid], theirs[valid])
    assert not ours[~np.broadcast_to(np.asarray(sample.valid), (N,))].any()
    passes = name in PASS_THROUGH or name in PASSING_MIXES or name == "thindielectric"
    assert (ours[valid].mean() > 0.2) == passes


@pytest.mark.parametrize("name", sorted(MATERIALS) + sorted(PASSING_MIXES))
def test_a_samples_relative_index_of_refraction_is_mitsubas(name):
    """From the same random numbers, the relative index a sample crossed (Russian roulette
    counts the throughput times its square) is Mitsuba's ``BSDFSample3f.eta``: the
    interface's entering, its inverse leaving, 1 for reflections, a thin pane's pass and
    every other BSDF. (Ours follows the side the direction leaves on; Mitsuba's the lobe it
    chose, which for a few rough samples lands on the other side: those are left out.)"""
    _skip_where_mitsuba_faults(name)
    spec = {**MATERIALS, **PASSING_MIXES}[name]
    wi, u, sample = _sampled(spec, [400, zlib.crc32(name.encode())])
    mi, bsdf, si = _mitsuba_side(spec, wi)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, Float(u[:, 0]), mi.Point2f(Float(u[:, 1]), Float(u[:, 2])))
    if name in DELTA_PARTS:
        return  # (Mitsuba's blend of a delta part weighs, not picks, differently: no eta there)
    valid = np.broadcast_to(np.asarray(sample.valid), (N,)) & (np.asarray(bs.pdf) > 0)
    ours = np.broadcast_to(np.asarray(sample.eta, np.float64), (N,))
    theirs = np.broadcast_to(np.asarray(bs.eta, np.float64), (N,))
    crossed = np.asarray(bs.wo, np.float64)[2] * wi[:, 2] < 0
    flags = np.broadcast_to(np.asarray(bs.sampled_type), (N,))
    through = (flags & int(mi.BSDFFlags.Transmission | mi.BSDFFlags.Null)) != 0
    consistent = crossed == through
    # (Without visible-normal sampling a fifth of Mitsuba's rough samples land so: 81 %
    # consistent for roughdielectric_no_visible.)
    assert consistent[valid].mean() > 0.75
    valid &= consistent
    np.testing.assert_allclose(ours[valid], theirs[valid], rtol=1e-6)
    if name in TRANSMISSIVE and name != "thindielectric":
        assert (np.abs(ours[valid] - 1.0) > 1e-3).mean() > 0.2  # refractions exercised


def test_a_mirror_is_the_side_that_reflects_by_delta_lobes_only():
    """``mirror`` answers for the side wi sees: a twosided material with a smooth conductor
    in front and a diffuse back is a mirror from above only; a one-sided conductor seen from
    below scatters nothing, so is no mirror; glass and null are mirrors from both sides."""
    table = BSDFTable([parse_material("m", spec) for spec in (
        {"type": "twosided", "front": {"type": "conductor"}, "back": {"type": "diffuse"}},
        {"type": "conductor"}, {"type": "dielectric"}, {"type": "null"}, {"type": "diffuse"})])
    material = UInt32([0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    z = np.tile([0.6, -0.6], 5).astype(np.float32)
    wi = Array3f(Float(np.full(10, 0.8, np.float32)), Float(np.zeros(10, np.float32)), Float(z))
    np.testing.assert_array_equal(np.asarray(table.mirror(material, wi)),
                                  [True, False, True, False, True, True, True, True, False, False])


@pytest.mark.parametrize("differentiated", [False, True],
                         ids=["a branch per kernel", "every kernel on every lane"])
def test_one_table_serves_many_materials_per_lane(differentiated):
    """Lanes of different materials (and types) in one call give each material's own value,
    density, sample, albedo and roughness: each material alone in a table of its own is the
    reference (with a checkerboard-textured one, looked up at per-lane coordinates). Without
    derivatives each kernel runs in a branch of its own; with them (wi carries derivatives
    here), every lane runs every kernel and keeps its own."""
    specs = {**MATERIALS, "checkered": {"type": "roughconductor", "alpha": {
        "type": "checkerboard", "color0": 0.1, "color1": 0.6}}}
    names = sorted(specs)
    materials = [parse_material(n, specs[n]) for n in names]
    table = BSDFTable(materials)
    rng = np.random.default_rng(7)
    wi, wo = _directions(rng, N), _directions(rng, N)
    u = rng.random((3, N)).astype(np.float32)
    uv = rng.random((2, N)).astype(np.float32)
    which = rng.integers(0, len(names), N)

    def queries(table, material, lanes):
        wi_j = Array3f(*wi[lanes].T.astype(np.float32))
        if differentiated:
            dr.enable_grad(wi_j)
        wo_j = Array3f(*wo[lanes].T.astype(np.float32))
        at = Array2f(*uv[:, lanes])
        sample = table.sample_from(material, wi_j, tuple(Float(x) for x in u[:, lanes]), at)
        values = {"eval": table.evaluate(material, wi_j, wo_j, at), "pdf": table.pdf(material, wi_j, wo_j, at),
                  "albedo": table.albedo(material, at), "roughness": table.roughness(material, at),
                  "sampled wo": sample.wo, "sample weight": sample.weight, "sample pdf": sample.pdf,
                  "sample valid": sample.valid, "sample delta": sample.delta}
        return {key: np.broadcast_to(np.asarray(dr.detach(v), np.float64).T, (int(lanes.sum()),)
                                     + np.asarray(v).T.shape[1:]) for key, v in values.items()}

    mixed = queries(table, UInt32(which.astype(np.uint32)), np.ones(N, bool))
    assert len(set(name for name, _ in table.kernels)) > 10
    for k, material in enumerate(materials):
        lanes = which == k
        alone = queries(BSDFTable([material]), UInt32(0), lanes)
        # (Some: the same material for every lane, given once, as in a scene of one material.)
        uniform = queries(table, UInt32(k), lanes) if k % 16 == 0 or names[k] == "checkered" else {}
        for key, value in alone.items():
            np.testing.assert_allclose(mixed[key][lanes], value, rtol=1e-6, atol=1e-7,
                                       err_msg=f"{names[k]}: {key}")
            if uniform:
                np.testing.assert_allclose(uniform[key], value, rtol=1e-6, atol=1e-7,
                                           err_msg=f"{names[k]} for every lane: {key}")


def test_a_parameter_held_in_a_column_of_its_own_is_set_through_traverse():
    """principledthin's ``eta`` (column ``thin_eta``, beside a conductor's colour ``eta`` in
    one scene): ``instancing.traverse`` reads it and sets it, and the material then scatters
    as one loaded with the new value; the conductor keeps its own."""
    scene = instancing.load_scene({
        "materials": {"thin": MATERIALS["principledthin_glassy"],
                      "metal": {"type": "conductor", "material": "Au"}},
        "instances": [{"model": "sphere", "material": "thin"}, {"model": "cube", "material": "metal"}]})
    params = instancing.traverse(scene)
    assert float(params["thin.eta"][0]) == pytest.approx(1.33)
    params["thin.eta"] = 1.7
    params.update()
    rng = np.random.default_rng(13)
    wi, wo = (Array3f(*_directions(rng, N, lower=True).T.astype(np.float32)) for _ in range(2))
    fresh = BSDFTable([parse_material("t", {**MATERIALS["principledthin_glassy"], "eta": 1.7}),
                       parse_material("m", {"type": "conductor", "material": "Au"})])
    for row in (0, 1):
        np.testing.assert_allclose(_rows(scene.bsdfs.evaluate(UInt32(row), wi, wo)),
                                   _rows(fresh.evaluate(UInt32(row), wi, wo)), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.ravel(params["metal.eta"]), parse_material("m", {
        "type": "conductor", "material": "Au"})["eta"], rtol=1e-6)


def test_columns_of_the_table_mean_one_thing():
    """The table keeps one column per name over all types, of a type's colours, numbers and
    derived values: a derived value is no colour or number of another type, and colours
    and numbers of one column (a parameter's name, or the ``column`` it names: principledthin's
    number ``eta`` beside the conductors' colour) are of one kind in every type."""
    from instancing.materials.material import LOBES
    from instancing.materials.parameter import COLOR, NUMBER
    lobes = set(LOBES.values())

    def columns(lobe) -> dict:
        return {parameter.column or key: parameter for key, parameter in lobe.parameters.items()
                if parameter.kind in (COLOR, NUMBER)}

    for lobe in lobes:
        others = {column for other in lobes - {lobe} for column in columns(other)}
        assert not others & set(getattr(lobe, "derived_keys", ())), lobe.__name__
    kinds: dict[str, set] = {}
    for lobe in lobes:
        for column, parameter in columns(lobe).items():
            kinds.setdefault(column, set()).add(parameter.kind)
    assert {column: k for column, k in kinds.items() if len(k) > 1} == {}
    assert columns(LOBES["principledthin"])["thin_eta"].kind != columns(LOBES["conductor"])["eta"].kind


def test_named_conductors_take_mitsubas_rgb_ior():
    mi = mitsuba_module()
    ours = parse_material("m", {"type": "conductor", "material": "Au"})
    theirs = mi.traverse(mi.load_dict({"type": "conductor", "material": "Au"}))
    np.testing.assert_allclose(ours["eta"], np.ravel(theirs["eta.value"]), rtol=1e-6)
    np.testing.assert_allclose(ours["k"], np.ravel(theirs["k.value"]), rtol=1e-6)


@pytest.mark.parametrize("spec, words", [
    ({"type": "velvet"}, ["unknown material type", "'velvet'", "roughconductor"]),
    ({"type": "diffuse", "reflectence": 0.5}, ["'reflectence'", "did you mean 'reflectance'"]),
    ({"type": "diffuse", "reflectance": 1.5}, ["'reflectance'", "[0.0, 1.0]"]),
    ({"type": "roughconductor", "alpha": -0.1}, ["'alpha'"]),
    ({"type": "roughconductor", "distribution": "phong"}, ["'distribution'", "ggx"]),
    ({"type": "roughconductor", "sample_visible": 1}, ["'sample_visible'", "true or false"]),
    ({"type": "conductor", "material": "Au", "eta": 0.5}, ["either", "'material'"]),
    ({"type": "conductor", "material": "Unobtainium"}, ["Unobtainium"]),
    ({"type": "roughconductor", "alpha_u": 0.1}, ["both 'alpha_u' and 'alpha_v'"]),
    ({"type": "roughplastic", "alpha_u": 0.1, "alpha_v": 0.3}, ["anisotropic", "not supported"]),
    ({"type": "roughconductor", "alpha_u": 0.1}, ["both 'alpha_u' and 'alpha_v'"]),
    ({"type": "roughdielectric", "alpha": 0.1, "alpha_u": 0.1, "alpha_v": 0.2}, ["either 'alpha'"]),
    ({"type": "twosided"}, ["one or two BSDFs"]),
    ({"type": "twosided", "a": {"type": "twosided", "b": {"type": "diffuse"}}}, ["cannot hold another"]),
    ({"type": "twosided", "a": {"type": "diffuse", "colour": 1}}, ["m.a", "'colour'"]),
    ({"type": "twosided", "a": {"type": "dielectric"}}, ["m.a", "both sides"]),
    ({"type": "roughdielectric", "int_ior": 1.5, "ext_ior": 1.5}, ["must differ"]),
    ({"type": "pplastic", "eta": 1.5, "int_ior": 1.6}, ["either 'eta' or 'int_ior' and 'ext_ior'"]),
    ({"type": "pplastic", "int_ior": "water", "ext_ior": "water"}, ["must differ"]),
    ({"type": "pplastic", "eta": {"type": "checkerboard"}}, ["'eta'", "constant"]),
    ({"type": "pplastic", "alpha_u": 0.1}, ["both 'alpha_u' and 'alpha_v'"]),
    ({"type": "pplastic", "diffuse_reflectance": 1.5}, ["'diffuse_reflectance'", "[0.0, 1.0]"]),
    ({"type": "polarizer", "transmittance": -0.5}, ["'transmittance'", "[0.0, 1.0]"]),
    ({"type": "polarizer", "theta": float("nan")}, ["'theta'", "finite"]),
    ({"type": "polarizer", "polarizing": 1}, ["'polarizing'", "true or false"]),
    ({"type": "polarizer", "angle": 30}, ["'angle'"]),
    ({"type": "mask", "a": {"type": "diffuse"}, "b": {"type": "diffuse"}}, ["'mask'", "1 BSDF", "['a', 'b']"]),
    ({"type": "mask", "opacity": 1.2, "a": {"type": "diffuse"}}, ["'opacity'", "[0.0, 1.0]"]),
    ({"type": "mask", "opacty": 0.5, "a": {"type": "diffuse"}}, ["'mask'", "'opacty'", "did you mean 'opacity'"]),
    ({"type": "mask", "a": {"type": "blendbsdf", "weight": 0.5, "b": {"type": "diffuse"},
                            "c": {"type": "diffuse"}}}, ["m.a", "not 'blendbsdf'"]),
    ({"type": "twosided", "a": {"type": "mask", "b": {"type": "diffuse"}}}, ["m.a", "both sides"]),
    ({"type": "null", "opacity": 0.5}, ["'opacity'"]),
    ({"type": "dielectric", "int_ior": "glas"}, ["'int_ior'", "glas"]),
    ({"type": "twosided", "a": {"type": "principled", "spec_trans": 0.2}}, ["m.a", "both sides"]),
    ({"type": "principled", "anisotropic": 1.5}, ["'anisotropic'", "[0.0, 1.0]"]),
    ({"type": "principled", "base_colour": 0.5}, ["'base_colour'", "did you mean 'base_color'"]),
    ({"type": "principled", "eta": 1.5, "specular": 0.5}, ["either 'eta' or 'specular'"]),
    ({"type": "principled", "eta": "water"}, ["'eta'", "water"]),
    ({"type": "principled", "eta": 0}, ["'eta'", "positive"]),
    ({"type": "principled", "roughness": 1.5}, ["'roughness'", "[0.0, 1.0]"]),
    ({"type": "principled", "specular": -0.1}, ["'specular'", "[0.0, 1.0]"]),
    ({"type": "principled", "base_color": [0.5, 1.2, 0.5]}, ["'base_color'", "[0.0, 1.0]"]),
    ({"type": "principled", "clearcoat_sampling_rate": -1}, ["'clearcoat_sampling_rate'"]),
    ({"type": "principledthin", "eta": 0}, ["'eta'", "positive"]),
    ({"type": "principledthin", "diff_trans": 2.5}, ["'diff_trans'", "[0.0, 2.0]"]),
    ({"type": "principledthin", "metallic": 0.5}, ["'metallic'", "principledthin"]),
    ({"type": "twosided", "a": {"type": "principledthin"}}, ["m.a", "both sides"]),
    ({"type": "principled", "main_specular_sampling_rate": {"type": "checkerboard"}},
     ["'main_specular_sampling_rate'", "constant"]),
])
def test_bad_materials_name_the_key(spec, words):
    with pytest.raises(SceneError) as err:
        parse_material("m", spec)
    for word in words:
        assert word in str(err.value), str(err.value)


@pytest.mark.parametrize("weight", [0.3, 0.6])
def test_a_blend_with_a_delta_part_reflects_the_mixture_of_its_parts(weight):
    """The reflected light of a blend is the weighted mixture of its parts': the mean
    sample weight (the albedo for light from wi) equals (1 - w) times that of the rough
    part plus w times that of the mirror, both from Mitsuba's own plugins sampled alone
    (2^20 samples each; the difference's Monte Carlo error is at most 0.13 %, 1 sigma,
    against the 0.5 % allowed). Mitsuba 3.9.1's blendbsdf
    itself returns about half of that here (its sample divides the mirror's weight by a
    mixture density), so its renders of such blends are darker than the mixture."""
    parts = ({"type": "roughplastic", "distribution": "ggx", "alpha": 0.3, "diffuse_reflectance": 0.2},
             {"type": "conductor", "material": "Au"})
    spec = {"type": "blendbsdf", "weight": weight, "bsdf_0": parts[0], "bsdf_1": parts[1]}
    n = 1 << 20
    rng = np.random.default_rng(7)
    for theta in (10.0, 50.0, 80.0):
        wi = np.tile([np.sin(np.radians(theta)), 0.0, np.cos(np.radians(theta))], (n, 1))
        u = [Float(rng.random(n).astype(np.float32)) for _ in range(3)]
        table = BSDFTable([parse_material("m", spec)])
        ours = np.asarray(table.sample(UInt32(0), Array3f(*wi.T.astype(np.float32)),
                                       GivenNumbers(*u)).weight, np.float64).mean(axis=1)
        albedos = []
        for part in parts:
            mi, bsdf, si = _mitsuba_side(part, wi)
            v = [Float(rng.random(n).astype(np.float32)) for _ in range(3)]
            _, value = bsdf.sample(mi.BSDFContext(), si, v[0], mi.Point2f(v[1], v[2]))
            albedos.append(np.asarray(value, np.float64).mean(axis=1))
        expected = (1.0 - weight) * albedos[0] + weight * albedos[1]
        np.testing.assert_allclose(ours, expected, rtol=5e-3, err_msg=f"theta {theta}")
