"""Arbitrary output variables: geometric quantities of the first hit, no shading.

An ``aov`` render traces camera rays once and does no shading, lighting or
shadow rays. Misses give 0 in every channel except ``instance`` (-1).
"""

from __future__ import annotations

from ...core.backend import Array3f, Float, dr
from ...scene.scene import Scene

#: AOV name -> its channel names, in output order.
AOV_CHANNELS = {
    "depth": ["depth"],
    "position": ["position.X", "position.Y", "position.Z"],
    "normal": ["normal.X", "normal.Y", "normal.Z"],
    "shading_normal": ["shading_normal.X", "shading_normal.Y", "shading_normal.Z"],
    "instance": ["instance"],
    "albedo": ["albedo.R", "albedo.G", "albedo.B"],
}
DEFAULT_AOVS = list(AOV_CHANNELS)


def aov_channel_names(aovs: list[str]) -> list[str]:
    """Channel names of the given AOVs, in order."""
    return [c for name in aovs for c in AOV_CHANNELS[name]]


def integrate_aov(scene: Scene, o: Array3f, d: Array3f, aovs: list[str]) -> list[Float]:
    """Per-ray channel values of ``aovs`` for unit-direction rays ``o + t d``.

    ``depth`` is the distance along the ray (t, since d is unit), ``position``
    and ``normal`` are the world hit point and geometric normal, ``shading_normal``
    the normal that shades (interpolated on smooth meshes, Mitsuba's ``sh_normal``), ``instance``
    the index into the scene's instance list, ``albedo`` the material's
    reflectance.
    """
    hit = scene.intersect_surface(o, d)
    out: list[Float] = []
    for name in aovs:
        if name == "depth":
            out.append(dr.select(hit.valid, hit.t, 0.0))
        elif name == "position":
            out.extend([hit.p.x, hit.p.y, hit.p.z])
        elif name == "normal":
            out.extend([hit.n.x, hit.n.y, hit.n.z])
        elif name == "shading_normal":
            out.extend([hit.sn.x, hit.sn.y, hit.sn.z])
        elif name == "instance":
            out.append(Float(hit.instance))
        else:
            albedo = scene.albedo(hit)
            out.extend([albedo.x, albedo.y, albedo.z])
    return out
