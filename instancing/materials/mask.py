"""Mitsuba's ``null``, ``mask`` and ``polarizer``: surfaces that let light pass straight through.

``null`` scatters nothing: a ray that meets it goes on in its own direction (a delta lobe,
``wo = -wi``, weight 1) and its ``eval`` and ``pdf`` are 0. ``mask`` is a partly
transparent surface: with probability ``opacity`` (a number in [0, 1] or a texture's
luminance) its nested BSDF scatters, otherwise the null lobe passes the ray on. That is a
``blendbsdf`` of the null lobe and the nested BSDF weighted by the opacity, and the table
(:mod:`instancing.materials.bsdf`) routes it as one. As in Mitsuba, only rays that sample a
BSDF pass through ``path``'s surfaces: its shadow rays stop at a masked surface.

``polarizer`` is a linear polarizer as Mitsuba's unpolarized (RGB) variants render it: the
null lobe weighted by half its ``transmittance`` (unpolarized light loses half its power
whatever the polarizer's angle). Its ``theta`` (the transmission axis) and ``polarizing``
act on polarized light only; as in those variants they are read, checked and exported, and
change no pixel.

What a surface lets straight through is its ``null_transmission`` (Mitsuba's
``eval_null_transmission``): 1 for ``null``, ``transmittance / 2`` for ``polarizer``, and for
a mask ``1 - opacity (1 - t)`` with ``t`` its nested BSDF's (the table mixes the parts).
``volpath`` passes shadow rays with it, and does not count a sample of the pass-through lobe
as a bounce, as Mitsuba's does.
"""

from __future__ import annotations

from ..core.backend import Array3f, Bool, Float, dr
from .blend import Blend
from .delta_lobe import DeltaLobe
from .parameter import COLOR, FLAG, NUMBER, Parameter


class Null(DeltaLobe):
    """The pass-through lobe of ``null`` (and of a mask's transparent part), on both sides."""

    names = ("null",)
    parameters: dict = {}
    both_sides = True
    albedo = None

    @staticmethod
    def null_transmission(p: dict, wi: Array3f, variant: tuple) -> Array3f:
        """All the light passes (Mitsuba's ``eval_null_transmission``)."""
        return dr.full(Array3f, 1.0, dr.width(wi))

    @staticmethod
    def sample(p: dict, wi: Array3f, u: tuple[Float, Float, Float], variant: tuple
               ) -> tuple[Array3f, Array3f, Float, Bool, Bool]:
        """(wo = -wi, weight 1, pdf 1, valid, delta)."""
        width = dr.width(wi)
        return -wi, dr.full(Array3f, 1.0, width), dr.full(Float, 1.0, width), \
            dr.full(Bool, True, width), dr.full(Bool, True, width)


class Polarizer(Null):
    """The pass-through lobe weighted by ``transmittance / 2``, on both sides."""

    names = ("polarizer",)
    parameters = {"theta": Parameter(NUMBER, 0.0, texture=True),
                  "transmittance": Parameter(COLOR, 1.0, 0.0, 1.0, texture=True),
                  "polarizing": Parameter(FLAG, True)}

    @staticmethod
    def sample(p: dict, wi: Array3f, u: tuple[Float, Float, Float], variant: tuple
               ) -> tuple[Array3f, Array3f, Float, Bool, Bool]:
        """(wo = -wi, weight transmittance / 2, pdf 1, valid, delta)."""
        wo, _, pdf, valid, delta = Null.sample(p, wi, u, variant)
        return wo, 0.5 * p["transmittance"], pdf, valid, delta

    @staticmethod
    def null_transmission(p: dict, wi: Array3f, variant: tuple) -> Array3f:
        """Half the transmittance passes (unpolarized light)."""
        return 0.5 * p["transmittance"]


class Mask(Blend):
    """The mask row's own parameter (its null lobe and nested BSDF are rows of the table);
    the table routes its lanes as a blend's, ``opacity`` the weight of the nested BSDF."""

    names = ("mask",)
    parameters = {"opacity": Parameter(NUMBER, 0.5, 0.0, 1.0, texture=True)}
    weight_key = "opacity"
    part_keys = (None, "nested_bsdf")
    both_sides = True
