"""Participating media: Mitsuba's ``homogeneous`` and ``heterogeneous`` media with their phase
functions, and the table of which medium fills which side of an instance's surface.

A homogeneous medium has one extinction ``sigma_t`` (per RGB channel, times ``scale``)
everywhere: light travelling a distance t keeps ``exp(-sigma_t t)`` of itself. A
heterogeneous medium's extinction is a ``volume`` texture (a gridvolume's or constvolume's
values times ``scale``) inside the volume's world-space bounding box, and 0 outside; paths cross it by
delta tracking against its majorant (``scale`` times the grid's largest value), shadow rays
by ratio tracking (:mod:`instancing.rendering.integrators.volpath`). Both have a
single-scattering ``albedo`` (a constant or a volume texture), and a phase function that
spreads scattered light over directions: Mitsuba's ``isotropic`` (1 / 4 pi) or ``hg``
(Henyey-Greenstein with mean cosine g; g > 0 scatters forwards), both written for the
direction ``wi`` pointing back along the incoming ray, as Mitsuba's are:
``p(wi, wo) = (1 - g^2) / (4 pi (1 + g^2 + 2 g dot(wi, wo))^1.5)``.

Media are attached as Mitsuba attaches them: an instance's ``interior`` and ``exterior``
media (none: vacuum) fill the side its geometric normal points away from and the side it
points to; a ray that crosses a surface whose two media differ continues in the medium on
the side it leaves towards (``target``). The camera sits in its own ``medium``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.backend import Array2f, Array3f, Bool, Float, UInt32, device_array, device_vectors, dr
from ..core.box import outward32
from ..core.warp import frame
from ..materials.texture import LookupPoint, Texture, TextureSet

#: The phase functions a medium may have.
PHASE_FUNCTIONS = ("isotropic", "hg")
#: The medium types.
MEDIUM_TYPES = ("homogeneous", "heterogeneous")
#: A medium's albedo texture index where it has none.
_NO_TEXTURE = 0xFFFFFFFF


@dataclass(frozen=True)
class Medium:
    """Mitsuba's ``homogeneous`` or ``heterogeneous`` medium (``type``): extinction ``sigma_t``
    (a constant per channel; for a heterogeneous medium a ``volume`` texture) and ``albedo``
    per channel (a constant or a ``volume`` texture, looked up where light scatters), ``scale``
    multiplying the extinction, its phase function (``phase``, and the mean cosine
    ``g`` of ``hg``), whether paths sample the lights at its scattering points
    (``sample_emitters``), and whether its extinction may differ between channels
    (``has_spectral_extinction``: Mitsuba's estimator assumes equal channels where it is
    false, so such a medium must have them). ``id`` names it in errors and exports."""

    sigma_t: tuple[float, float, float] | Texture
    albedo: tuple[float, float, float] | Texture
    scale: float = 1.0
    phase: str = "isotropic"
    g: float = 0.0
    sample_emitters: bool = True
    has_spectral_extinction: bool = True
    id: str = ""
    type: str = "homogeneous"

    @property
    def extinction(self) -> np.ndarray:
        """A homogeneous medium's extinction: ``sigma_t * scale`` (per channel)."""
        return np.asarray(self.sigma_t, np.float64) * self.scale

    @property
    def majorant(self) -> float:
        """A heterogeneous medium's majorant: ``scale`` times the grid's largest value."""
        return float(self.sigma_t.texels.max()) * self.scale

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """A heterogeneous medium's world box: the bounding box of its grid's unit cube."""
        to_world = np.linalg.inv(self.sigma_t.to_local)
        corners = np.array([[x, y, z, 1.0] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
        world = (corners @ to_world.T)[:, :3]
        return world.min(axis=0), world.max(axis=0)


def hg_eval(g: Float, cos_wi_wo: Float) -> Float:
    """Henyey-Greenstein density of scattering from ``wi`` (pointing back along the incoming
    ray) into ``wo``, given ``dot(wi, wo)`` (isotropic where g is 0)."""
    temp = 1.0 + g * g + 2.0 * g * cos_wi_wo
    return (1.0 - g * g) / (4.0 * math.pi * temp * dr.sqrt(temp))


def hg_sample(g: Float, wi: Array3f, u1: Float, u2: Float) -> Array3f:
    """A direction drawn from the Henyey-Greenstein density around the incoming direction
    ``-wi`` (by inverting its cosine's distribution; uniform where |g| is tiny)."""
    square = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1)
    cos_theta = dr.select(dr.abs(g) < 1e-7, 1.0 - 2.0 * u1,
                          (1.0 + g * g - square * square) / (2.0 * dr.select(g == 0, 1.0, g)))
    sin_theta = dr.safe_sqrt(1.0 - cos_theta * cos_theta)
    sin_phi, cos_phi = dr.sincos(2.0 * math.pi * u2)
    s, t = frame(-wi)
    return s * (sin_theta * cos_phi) + t * (sin_theta * sin_phi) + (-wi) * cos_theta


class MediaTable:
    """The media that a scene's instances and camera name, as kernels read them.

    Media are numbered from 1 in ``media``'s order; 0 stands for no medium (vacuum), so
    per-lane medium indices index the arrays directly.

    Args:
        media: the media in use.
        interior, exterior: per instance, the index of the medium inside and outside it (0:
            none).
        origin: the world point at the origin of rendering space (volume textures are looked
            up at rendering-space points).
        cameras: the indices of the media the cameras are in.
    """

    def __init__(self, media: list[Medium], interior: np.ndarray, exterior: np.ndarray,
                 origin: np.ndarray | None = None, cameras: Sequence[int] = ()):
        self.media = list(media)
        # A medium around the cameras or outside some instance, and inside none, has no
        # surface that bounds it (fog around the scene).
        unbounded = np.zeros(len(media) + 1, np.uint32)
        unbounded[np.asarray([*cameras, *np.asarray(exterior).ravel()], np.int64)] = 1
        unbounded[np.asarray(interior, np.int64).ravel()] = 0
        unbounded[0] = 0
        #: Whether some medium is unbounded (:meth:`unbounded`).
        self.any_unbounded = bool(unbounded.any())
        self._unbounded = device_array(UInt32, unbounded)
        sigma = np.zeros((len(media) + 1, 3), np.float32)
        sigma_s = np.zeros((len(media) + 1, 3), np.float32)
        g = np.zeros(len(media) + 1, np.float32)
        emitters = np.zeros(len(media) + 1, np.uint32)
        textures: list[Texture] = []
        texture_of = np.full(len(media) + 1, _NO_TEXTURE, np.uint32)
        tracked = np.zeros(len(media) + 1, np.uint32)
        density_of = np.zeros(len(media) + 1, np.uint32)
        majorant = np.zeros(len(media) + 1, np.float32)
        lo, hi = np.zeros((len(media) + 1, 3)), np.zeros((len(media) + 1, 3))
        origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        for k, medium in enumerate(media, 1):
            if medium.type == "heterogeneous":
                # Extinction = the scale times the grid's value where it is looked up.
                tracked[k], density_of[k] = 1, len(textures)
                textures.append(medium.sigma_t)
                majorant[k] = medium.majorant
                lo[k], hi[k] = (b - origin for b in medium.bounds)
                sigma[k] = medium.scale
            else:
                sigma[k] = medium.extinction
            if isinstance(medium.albedo, Texture):
                # Scattering = extinction times the texture's value where light scatters.
                texture_of[k] = len(textures)
                textures.append(medium.albedo)
                sigma_s[k] = sigma[k]
            else:
                sigma_s[k] = sigma[k] * np.asarray(medium.albedo)
            g[k] = medium.g if medium.phase == "hg" else 0.0
            emitters[k] = medium.sample_emitters
        self._textures = TextureSet(textures, origin=origin) if textures else None
        self._texture_of = device_array(UInt32, texture_of) if textures else None
        #: Whether some medium is heterogeneous (kernels trace its tracking only then).
        self.heterogeneous = bool(tracked.any())
        if self.heterogeneous:
            self._tracked = device_array(UInt32, tracked)
            self._density_of = device_array(UInt32, density_of)
            self._majorant = device_array(Float, majorant)
            lo32, hi32 = outward32(lo, hi)
            self._lo, self._hi = device_vectors(lo32), device_vectors(hi32)
        self._sigma_t = device_vectors(sigma)
        self._sigma_s = device_vectors(sigma_s)
        self._g = device_array(Float, g)
        self._sample_emitters = device_array(UInt32, emitters)
        # (A scene without instances keeps one entry, never met, for the masked gathers.)
        self.interior, self.exterior = (device_array(UInt32, np.asarray(side, np.uint32) if len(side)
                                                     else np.zeros(1, np.uint32))
                                        for side in (interior, exterior))

    def unbounded(self, medium: UInt32) -> Bool:
        """Whether the medium has no surface that bounds it: the cameras' or an instance's
        exterior medium that is no instance's interior."""
        return dr.gather(UInt32, self._unbounded, medium) != 0

    def sigma_t(self, medium: UInt32) -> Array3f:
        """Extinction per channel (0 in vacuum)."""
        return dr.gather(Array3f, self._sigma_t, medium)

    def sigma_s(self, medium: UInt32, p: Array3f, active: Bool) -> Array3f:
        """Scattering coefficient per channel at rendering-space points ``p``: extinction
        times albedo (a homogeneous medium's extinction; a heterogeneous medium's scale, to
        be multiplied by its grid's value, :meth:`density`)."""
        sigma_s = dr.gather(Array3f, self._sigma_s, medium, active)
        if self._textures is None:
            return sigma_s
        texture = dr.gather(UInt32, self._texture_of, medium, active)
        textured = active & (texture != _NO_TEXTURE)
        return dr.select(textured, sigma_s * self._lookup(texture, p, textured), sigma_s)

    def _lookup(self, texture: UInt32, p: Array3f, active: Bool) -> Array3f:
        width = dr.width(p)
        point = LookupPoint(dr.zeros(Array2f, width), dr.zeros(UInt32, width), dr.zeros(Array2f, width), p)
        return self._textures.eval(texture, point, active)

    def is_heterogeneous(self, medium: UInt32) -> Bool:
        """Whether the medium is heterogeneous (tracked against its majorant)."""
        return dr.gather(UInt32, self._tracked, medium) != 0 if self.heterogeneous else Bool(False)

    def majorant(self, medium: UInt32) -> Float:
        """A heterogeneous medium's majorant (0 for the others)."""
        return dr.gather(Float, self._majorant, medium)

    def box(self, medium: UInt32) -> tuple[Array3f, Array3f]:
        """A heterogeneous medium's box in rendering space (outside it the medium is empty)."""
        return dr.gather(Array3f, self._lo, medium), dr.gather(Array3f, self._hi, medium)

    def density(self, medium: UInt32, p: Array3f, active: Bool) -> Array3f:
        """A heterogeneous medium's grid value at rendering-space points ``p`` (its extinction
        there is this times ``sigma_t``, the scale)."""
        return self._lookup(dr.gather(UInt32, self._density_of, medium, active), p, active)

    def g(self, medium: UInt32) -> Float:
        """The phase function's mean cosine (0: isotropic)."""
        return dr.gather(Float, self._g, medium)

    def sample_emitters(self, medium: UInt32) -> Bool:
        """Whether scattering points in the medium sample the lights."""
        return dr.gather(UInt32, self._sample_emitters, medium) != 0

    def target(self, instance: UInt32, n: Array3f, d: Array3f, current: UInt32,
               active: Bool) -> UInt32:
        """The medium a ray with direction ``d`` enters on leaving a hit on ``instance``
        (geometric normal ``n``): its exterior medium on the side n points to, its
        interior on the other, where the two differ; else ``current``."""
        inside = dr.gather(UInt32, self.interior, instance, active)
        outside = dr.gather(UInt32, self.exterior, instance, active)
        return dr.select(active & (inside != outside),
                         dr.select(dr.dot(d, n) > 0, outside, inside), current)

    @staticmethod
    def transmittance(sigma_t: Array3f, t: Float) -> Array3f:
        """``exp(-sigma_t t)`` per channel, 1 where sigma_t is 0 (also for t = inf)."""
        return dr.select(sigma_t > 0, dr.exp(-sigma_t * t), 1.0)
