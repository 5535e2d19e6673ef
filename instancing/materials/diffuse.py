"""Mitsuba's ``diffuse``: the Lambertian BSDF, one-sided (black seen from the back)."""

from __future__ import annotations

from ..core.backend import Array3f, Bool, Float, dr
from ..core.warp import INV_PI, square_to_cosine_hemisphere
from .parameter import COLOR, Parameter


class Diffuse:
    """``f = reflectance / pi`` where both directions are above the surface (local frame,
    +z the shading normal); sampled by the cosine-weighted hemisphere."""

    names = ("diffuse",)
    parameters = {"reflectance": Parameter(COLOR, 0.5, 0.0, 1.0, texture=True)}
    delta_only = False
    albedo = "reflectance"

    @staticmethod
    def variant(values: dict) -> tuple:
        return ()

    @staticmethod
    def eval(p: dict, wi: Array3f, wo: Array3f, variant: tuple) -> Array3f:
        """f cos(theta_o)."""
        front = (wi.z > 0) & (wo.z > 0)
        return dr.select(front, p["reflectance"] * (INV_PI * wo.z), 0.0)

    @staticmethod
    def pdf(p: dict, wi: Array3f, wo: Array3f, variant: tuple) -> Float:
        return dr.select((wi.z > 0) & (wo.z > 0), INV_PI * wo.z, 0.0)

    @staticmethod
    def sample(p: dict, wi: Array3f, u: tuple[Float, Float, Float], variant: tuple
               ) -> tuple[Array3f, Array3f, Float, Bool, Bool]:
        """(wo, weight f cos / pdf, pdf, valid, whether a delta lobe was sampled)."""
        wo = square_to_cosine_hemisphere(u[1], u[2])
        pdf = INV_PI * wo.z
        valid = (wi.z > 0) & (pdf > 0)
        return wo, dr.select(valid, p["reflectance"], 0.0), pdf, valid, Bool(False)
