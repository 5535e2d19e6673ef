"""Perspective camera with Mitsuba's conventions.

Camera space looks down +z with +y up and +x to the left (Mitsuba's
``perspective`` sensor with a ``look_at`` ``to_world``); ``fov`` is the full
horizontal field of view in degrees. Film coordinates (u, v) in [0, 1]^2 run
from the top-left corner, so the same camera gives the same picture as
Mitsuba. Rays start at the camera position (no near clip).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.backend import Array3f, Bool, Float, Matrix4f, UInt32, dr
from ..core.errors import SceneError
from ..core.transform import Transform

#: Largest film side, in pixels.
MAX_FILM_SIZE = 1 << 15
#: Reconstruction filters: Mitsuba's ``box``, ``gaussian`` and ``tent`` (their default sizes).
RFILTERS = ("box", "gaussian", "tent")


@dataclass(frozen=True)
class PerspectiveCamera:
    """A pinhole camera: world_from_camera (the scene's ``to_world``), fov along x, film size.

    Made from a scene file's ``"camera"`` by :func:`instancing.io.scene_file.parse_camera`,
    which validates it."""

    world_from_camera: Transform
    fov: float
    width: int
    height: int
    rfilter: str = "box"

    def with_size(self, width: int, height: int) -> "PerspectiveCamera":
        """The same camera with another film resolution (checked: an integer in
        [1, MAX_FILM_SIZE] per side)."""
        for name, value in (("width", width), ("height", height)):
            if (not isinstance(value, int) or isinstance(value, bool)
                    or not 1 <= value <= MAX_FILM_SIZE):
                raise SceneError(f"{name} must be an integer in [1, {MAX_FILM_SIZE}], got {value!r}")
        return PerspectiveCamera(self.world_from_camera, self.fov, width, height, self.rfilter)

    def key(self) -> tuple:
        """The camera's values as a hashable tuple (a render's recording belongs to one pose)."""
        matrix = np.asarray(self.world_from_camera.matrix, np.float64)
        return (tuple(matrix.ravel().tolist()), self.fov, self.width, self.height, self.rfilter)

    def _film(self) -> tuple[Float, Float]:
        """(tan of half the horizontal field of view, width / height) as opaque values."""
        return (dr.opaque(Float, math.tan(math.radians(self.fov) / 2)),
                dr.opaque(Float, self.width / self.height))

    def _lanes(self, transform: Transform) -> Transform:
        """A scalar transform of the pose as per-lane float32 matrices of opaque values:
        the pose enters kernels as values, not literals, so that a moved camera (a
        turntable) reuses the compiled kernels instead of compiling new ones."""
        matrix, inverse = Matrix4f(transform.matrix), Matrix4f(transform.inverse_matrix)
        dr.make_opaque(matrix, inverse)
        return Transform(matrix, inverse)

    def _camera_from_world(self) -> Transform:
        """Per-lane camera_from_world (points to camera space for projection)."""
        return self._lanes(self.world_from_camera.inverse())

    def rays(self, u: Float, v: Float) -> tuple[Array3f, Array3f]:
        """World rays through film positions (u, v) in [0, 1]^2 (top-left origin); unit directions."""
        tan_half, aspect = self._film()
        # Film to camera space: +x left, +y up, looking down +z.
        local = Array3f((1 - 2 * u) * tan_half, (1 - 2 * v) * tan_half / aspect, 1.0)
        lanes = self._lanes(self.world_from_camera)
        d = dr.normalize(lanes.apply_vector(local))
        o = Array3f(*[lanes.matrix[i][3] for i in range(3)]) + dr.zeros(Array3f, dr.width(u))
        return o, d

    def project(self, p: Array3f) -> tuple[Float, Float, Bool]:
        """Film position in pixels (x right, y down, origin at the top-left corner) of world
        points; the inverse of :meth:`rays`. Differentiable in ``p``.

        Returns ``(x, y, in_front)``; ``in_front`` is False for points at or behind
        the camera plane (their x, y are meaningless).
        """
        tan_half, aspect = self._film()
        q = self._camera_from_world().apply_point(p)
        in_front = q.z > 0
        z = dr.select(in_front, q.z, 1.0)
        x = (1 - q.x / (z * tan_half)) * (0.5 * self.width)
        y = (1 - q.y * aspect / (z * tan_half)) * (0.5 * self.height)
        return x, y, in_front

    def film_velocity(self, p: Array3f, v: Array3f) -> tuple[Float, Float]:
        """Film motion (pixels per unit) of the image of point ``p`` moving with world velocity ``v``:
        the Jacobian of :meth:`project` applied to v."""
        tan_half, aspect = self._film()
        camera_from_world = self._camera_from_world()
        q, dq = camera_from_world.apply_point(p), camera_from_world.apply_vector(v)
        z2 = q.z * q.z * tan_half
        return (-(0.5 * self.width) * (dq.x * q.z - q.x * dq.z) / z2,
                -(0.5 * self.height * aspect) * (dq.y * q.z - q.y * dq.z) / z2)

    def pixel_centre_rays(self) -> tuple[Array3f, Array3f]:
        """One ray through the centre of every pixel, in row-major order."""
        index = dr.arange(UInt32, self.width * self.height)
        x = Float(index % self.width) + 0.5
        y = Float(index // self.width) + 0.5
        return self.rays(x / self.width, y / self.height)

