"""What every BSDF made of delta lobes only shares: no density of directions, so ``eval``
and ``pdf`` are 0 and only ``sample`` finds its directions (smooth metals and glass).

A delta lobe chosen with probability ``p`` (reflection or refraction of glass, a plastic's
coating) weighs its direction ``f / detach(p)``: the same value as ``f / p``, but its
derivative is that of ``f`` alone, the derivative of the sum over the lobes of ``f`` times
the light each brings (where ``f`` and ``p`` cancel in value, as glass's Fresnel
reflectance, the weight keeps ``p / detach(p)``)."""

from __future__ import annotations

from ..core.backend import Array3f, Float, dr


def chosen(probability: Float) -> Float:
    """1 in value, with the derivative of log ``probability``: the factor that keeps a lobe
    choice's derivative where its probability cancelled against the lobe's weight."""
    return probability / dr.detach(probability)


class DeltaLobe:
    """Base of the delta-only BSDF kernels (``variant`` none, ``eval`` and ``pdf`` 0)."""

    delta_only = True
    samples_delta = True

    @staticmethod
    def variant(values: dict) -> tuple:
        return ()

    @staticmethod
    def eval(p, wi, wo, variant) -> Array3f:
        return dr.zeros(Array3f, dr.width(wi))

    @staticmethod
    def pdf(p, wi, wo, variant) -> Float:
        return dr.zeros(Float, dr.width(wi))
