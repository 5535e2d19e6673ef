"""``instancing.render``: camera samples -> integrator -> film -> (H, W, C) image.

Pixel sampling: each pixel gets ``spp`` camera rays through film positions
offset from the pixel centre by the reconstruction filter's distribution
(filter importance sampling: uniform over the pixel for ``box``, Mitsuba's
truncated Gaussian for ``gaussian``), so every sample has weight 1 and the
pixel value is the sample mean. Random numbers come from one PCG32 stream per
sample, seeded by ``seed``: the same scene, spp and seed give a bit-identical
image.
"""

from __future__ import annotations

import math

from .backend import Float, TensorXf, UInt32, dr, jit
from .camera import PerspectiveCamera
from .errors import SceneError
from .integrators.aov import AOV_CHANNELS, DEFAULT_AOVS, aov_channel_names, integrate_aov
from .integrators.direct import integrate_direct
from .lights import LightSet
from .scene import Scene

INTEGRATORS = ("aov", "direct")
#: Mitsuba's ``gaussian`` reconstruction filter: standard deviation 0.5 px, truncated at 4 sigma.
GAUSSIAN_STDDEV = 0.5
GAUSSIAN_RADIUS = 4 * GAUSSIAN_STDDEV


def channel_names(integrator: str, aovs: list[str] | None = None) -> list[str]:
    """Names of the channels that :func:`render` returns for these settings."""
    if integrator == "aov":
        return aov_channel_names(_check_aovs(aovs))
    return ["R", "G", "B"]


def _check_aovs(aovs: list[str] | None) -> list[str]:
    aovs = DEFAULT_AOVS if aovs is None else list(aovs)
    unknown = [a for a in aovs if a not in AOV_CHANNELS]
    if unknown or not aovs:
        raise SceneError(f"unknown AOVs {unknown}; available: {list(AOV_CHANNELS)}")
    return aovs


def _filter_offset(rfilter: str, u: Float) -> Float:
    """Offset from the pixel centre (in pixels) distributed as the filter, from u in [0, 1)."""
    if rfilter == "box":
        return u - 0.5
    # Inverse CDF of the Gaussian truncated to [-R, R].
    scale = GAUSSIAN_STDDEV * math.sqrt(2.0)
    edge = math.erf(GAUSSIAN_RADIUS / scale)
    return scale * dr.erfinv((2.0 * u - 1.0) * edge)


def render(scene: Scene, integrator: str = "direct", spp: int = 64, seed: int = 0, *,
           aovs: list[str] | None = None, max_depth: int | None = None,
           width: int | None = None, height: int | None = None) -> TensorXf:
    """Render the scene through its camera.

    Args:
        scene: a loaded scene with a ``"camera"``.
        integrator: 'aov' or 'direct' ('path' follows).
        spp: samples per pixel (>= 1).
        seed: random seed; equal inputs give bit-identical images.
        aovs: for 'aov': any of depth, position, normal, instance, albedo (default all).
        max_depth: path length limit for 'path' (reserved).
        width, height: override the camera's film size.

    Returns:
        TensorXf of shape (H, W, C); :func:`channel_names` gives the channel names.
    """
    if integrator not in INTEGRATORS:
        raise SceneError(f"unknown integrator {integrator!r}; available: {list(INTEGRATORS)}")
    if not isinstance(spp, int) or spp < 1:
        raise SceneError(f"spp must be a positive integer, got {spp!r}")
    if scene.camera is None:
        raise SceneError("the scene has no 'camera'; add one to render it")
    camera = PerspectiveCamera.from_dict(scene.camera)
    if width is not None or height is not None:
        camera = camera.with_size(width or camera.width, height or camera.height)
    w, h = camera.width, camera.height
    # One sample per lane, samples of a pixel consecutive.
    index = dr.arange(UInt32, w * h * spp)
    pixel = index // spp
    sampler = jit.PCG32(size=w * h * spp, initstate=UInt32(seed & 0xFFFFFFFF), initseq=index)
    dx = _filter_offset(camera.rfilter, sampler.next_float32())
    dy = _filter_offset(camera.rfilter, sampler.next_float32())
    px = Float(pixel % w) + 0.5 + dx
    py = Float(pixel // w) + 0.5 + dy
    o, d = camera.rays(px / w, py / h)
    if integrator == "aov":
        channels = integrate_aov(scene, o, d, _check_aovs(aovs))
    else:
        rgb = integrate_direct(scene, LightSet(scene), o, d, sampler)
        channels = [rgb.x, rgb.y, rgb.z]
    # Film: the pixel value is the mean of its samples (all weights are 1).
    count = len(channels)
    flat = dr.zeros(Float, w * h * count)
    slot = dr.arange(UInt32, w * h) * count
    for c, values in enumerate(channels):
        dr.scatter(flat, dr.block_sum(values, spp) / spp, slot + c)
    return TensorXf(flat, shape=(h, w, count))
