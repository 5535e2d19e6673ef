"""The space a scene is rendered in: world space moved so that the camera sits at the origin.

Kernels work in float32. In world coordinates a unit sphere 1e6 from the origin is a few
dozen float32 steps across, and hit points, shadow-ray offsets and normals near it lose
their precision (acne, a faceted sphere). As pbrt-v4's camera-world space, a scene is
therefore stored relative to a float64 ``origin``: every position (instance translations,
cameras, point and spot lights) has the origin subtracted in float64 *before* it is
rounded to float32, so precision follows the distance from the camera, not from the world
origin. Directions, rotations and scales are the same in both spaces.

The origin is the first camera's position (a scene's several cameras share it: they look
at one set of objects, so their distances to it are alike); without a camera, the centre
of the instances' translations, so that a far-away scene traced with float64 NumPy rays
(:meth:`~instancing.scene.scene.Scene.intersect`) keeps its precision too. A scene whose
chosen point lies within four extents (the spread of its cameras and instances) of the
world origin keeps the world origin: world
coordinates there are already as small as the scene's own, and its float32 data are those
of world space.

The origin is chosen when the scene is loaded and kept: cameras set and instances moved
later are stored relative to it.

Everything a scene hands back (``Scene.to_world``, ``bounds``, hit points, ``position``
AOVs, parameters) is in world space: the origin is added back, in float64 where the result
is float64.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.transform import translate
from .camera import Camera
from .description import PointLight

#: A scene whose camera (or centre) lies within this many extents of the world origin is
#: rendered in world space.
NEAR_EXTENTS = 4.0


class RenderingSpace:
    """World space translated by ``-origin`` (float64 (3,))."""

    def __init__(self, origin: np.ndarray):
        self.origin = np.asarray(origin, np.float64).reshape(3)
        #: False when the origin is the world origin: nothing is moved.
        self.moved = bool(self.origin.any())

    @classmethod
    def for_scene(cls, cameras: tuple[Camera, ...], to_world: np.ndarray) -> "RenderingSpace":
        """The space of a scene with these cameras and (N, 4, 4) float64 instance matrices."""
        eyes = np.array([c.world_from_camera.to_numpy()[0][:3, 3] for c in cameras]).reshape(-1, 3)
        t = to_world[:, :3, 3]
        if len(eyes):
            point = eyes[0]
        elif len(t):
            point = 0.5 * (t.min(axis=0) + t.max(axis=0))
        else:
            return cls(np.zeros(3))
        # The extent: the spread of the cameras and translations, and twice the largest
        # axis length.
        places = np.concatenate([eyes, t])
        extent = float(np.max(places.max(axis=0) - places.min(axis=0)))
        if len(t):
            extent += 2 * float(np.linalg.norm(to_world[:, :3, :3], axis=1).max())
        if np.abs(point).max() <= NEAR_EXTENTS * extent:
            return cls(np.zeros(3))
        return cls(point)

    # -- world to rendering (before rounding to float32) --------------------------------------

    def matrices(self, to_world: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 world_from_object matrices as rendering_from_object."""
        return _translated(to_world, -self.origin)

    def inverses(self, from_world: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 object_from_world matrices as object_from_rendering
        (``from_world @ translate(origin)``)."""
        return _inverse_translated(from_world, -self.origin)

    def points(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) in rendering space, float64."""
        return np.asarray(p, np.float64) - self.origin

    def camera(self, camera: Camera) -> Camera:
        """A world camera as the same camera in rendering space."""
        if not self.moved:
            return camera
        return dataclasses.replace(camera, world_from_camera=translate(
            (-self.origin).tolist()) @ camera.world_from_camera)

    def light(self, light):
        """A world light record in rendering space (only point and spot lights have a
        position; directions and environments are unchanged)."""
        if not self.moved or not isinstance(light, PointLight):
            return light
        return dataclasses.replace(light, position=tuple(self.points(light.position).tolist()))

    # -- rendering to world (results handed back) ---------------------------------------------

    def world_matrices(self, to_rendering: np.ndarray) -> np.ndarray:
        """(N, 4, 4) rendering_from_object matrices as world_from_object, float64."""
        return _translated(to_rendering, self.origin)

    def world_inverses(self, from_rendering: np.ndarray) -> np.ndarray:
        """(N, 4, 4) object_from_rendering matrices as object_from_world, float64."""
        return _inverse_translated(from_rendering, self.origin)

    def world_points(self, p: np.ndarray) -> np.ndarray:
        """Rendering-space points (..., 3) in world space, float64."""
        return np.asarray(p, np.float64) + self.origin


def _translated(matrices: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``translate(offset) @ matrices`` (float64; the input itself, unchanged, for offset 0)."""
    if not offset.any():
        return np.asarray(matrices, np.float64)
    out = np.array(matrices, np.float64)
    out[..., :3, 3] += offset
    return out


def _inverse_translated(inverses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The inverses of ``translate(offset) @ M`` from those of M: ``inverses @
    translate(-offset)`` (float64; the input itself, unchanged, for offset 0)."""
    if not offset.any():
        return np.asarray(inverses, np.float64)
    out = np.array(inverses, np.float64)
    out[..., :3, 3] -= np.einsum("...ij,j->...i", out[..., :3, :3], offset)
    return out
