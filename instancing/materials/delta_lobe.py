"""What every BSDF made of delta lobes only shares: no density of directions, so ``eval``
and ``pdf`` are 0 and only ``sample`` finds its directions (smooth metals and glass)."""

from __future__ import annotations

from ..core.backend import Array3f, Float, dr


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
