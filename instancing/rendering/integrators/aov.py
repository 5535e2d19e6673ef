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
    "uv": ["uv.U", "uv.V"],
    "roughness": ["roughness"],
}
#: The AOVs an ``aov`` render gives unless asked for others (uv and roughness on request).
DEFAULT_AOVS = ["depth", "position", "normal", "shading_normal", "instance", "albedo"]
#: Mitsuba's AOV types that ours give alike (tests/test_mitsuba_render.py): ours, and the
#: suffixes of their channels' names in Mitsuba's.
MITSUBA_AOVS = {"depth": ("depth", ("T",)), "position": ("position", ("X", "Y", "Z")),
                "geo_normal": ("normal", ("X", "Y", "Z")),
                "sh_normal": ("shading_normal", ("X", "Y", "Z")), "uv": ("uv", ("U", "V"))}


def mitsuba_aov_channel_names(aovs, nested_labels, alpha: bool = False) -> list[str]:
    """Channel names of Mitsuba's ``aov`` integrator, as Mitsuba names them: each nested
    integrator's RGB (``label.R``; and alpha, ``label.A``, with ``alpha``), then each AOV's,
    from its (label, Mitsuba type) pair."""
    return ([f"{label}.{c}" for label in nested_labels for c in ("RGBA" if alpha else "RGB")]
            + [f"{label}.{suffix}" for label, kind in aovs for suffix in MITSUBA_AOVS[kind][1]])


def aov_channel_names(aovs: list[str]) -> list[str]:
    """Channel names of the given AOVs, in order."""
    return [c for name in aovs for c in AOV_CHANNELS[name]]


def integrate_aov(scene: Scene, o: Array3f, d: Array3f, aovs: list[str]) -> list[Float]:
    """Per-ray channel values of ``aovs`` for unit-direction rays ``o + t d``.

    ``depth`` is the distance along the ray (t, since d is unit), ``position``
    and ``normal`` are the world hit point and geometric normal, ``shading_normal``
    the normal that shades (interpolated on smooth meshes, Mitsuba's ``sh_normal``), ``instance``
    the index into the scene's instance list, ``albedo`` the material's
    reflectance, ``uv`` the surface coordinates (Mitsuba's ``uv`` AOV: each shape's own, a
    mesh's texture coordinates or barycentrics), ``roughness`` the material's microfacet
    ``alpha`` (0 for smooth and diffuse materials).
    """
    hit = scene.intersect_surface(o, d, uv=("uv" in aovs) or None)
    out: list[Float] = []
    for name in aovs:
        if name == "depth":
            out.append(dr.select(hit.valid, hit.t, 0.0))
        elif name == "position":
            # World position: the rendering-space hit point plus the scene's origin.
            origin = scene.origin
            out.extend([dr.select(hit.valid, hit.p[k] + float(origin[k]), hit.p[k])
                        if origin[k] else hit.p[k] for k in range(3)])
        elif name == "normal":
            out.extend([hit.n.x, hit.n.y, hit.n.z])
        elif name == "shading_normal":
            out.extend([hit.sn.x, hit.sn.y, hit.sn.z])
        elif name == "instance":
            out.append(Float(hit.instance))
        elif name == "uv":
            out.extend([hit.uv.x, hit.uv.y])
        elif name == "roughness":
            material = scene.material_of(hit)
            out.append(dr.select(hit.valid, scene.bsdfs.roughness(material, scene.lookup_point(hit)), 0.0))
        else:
            albedo = scene.albedo(hit)
            out.extend([albedo.x, albedo.y, albedo.z])
    return out
