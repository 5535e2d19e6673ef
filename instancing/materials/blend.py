"""Mitsuba's ``blendbsdf``: a mix of two BSDFs, ``(1 - weight) f_0 + weight f_1``, the
weight a number in [0, 1] or a texture (its luminance).

The table (:mod:`instancing.materials.bsdf`) holds the two BSDFs as rows of their own
(each on its own sides: a ``twosided`` one shows its back row from below); lanes of a
blend row evaluate both and mix them. A sample picks one of the two by the
weight (the first random number, rescaled for the chosen BSDF), then weighs the direction
by the mixture: ``f / p`` with ``f`` and ``p`` the weighted sums of both BSDFs' values
and densities there (one-sample MIS, as Mitsuba's plugin); after a delta lobe, the chosen
BSDF's own weight, times ``share / detach(share)`` for the choice's probability ``share``
(:func:`~instancing.materials.delta_lobe.chosen`).
"""

from __future__ import annotations

from .parameter import NUMBER, Parameter


class Blend:
    """The blend row's own parameter (its two BSDFs are rows of the table); it has no
    kernel: the table routes its lanes to the BSDFs it mixes."""

    names = ("blendbsdf",)
    parameters = {"weight": Parameter(NUMBER, None, 0.0, 1.0, texture=True)}
    weight_key = "weight"
    #: The parts' names in traverse keys (Mitsuba's: ``<material>.bsdf_0.<parameter>``).
    part_keys = ("bsdf_0", "bsdf_1")
    delta_only = False
    chooses_lobe = True
    albedo = None

    @staticmethod
    def variant(values: dict) -> tuple:
        return ()
