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

from .backend import Array3f, Bool, Float, Matrix4f, UInt32, dr
from .errors import SceneError
from .io.scene_file import parse_transform
from .transform import Transform

_CAMERA_KEYS = {"type", "fov", "to_world", "width", "height", "rfilter"}


@dataclass(frozen=True)
class PerspectiveCamera:
    """A pinhole camera: world_from_camera (the scene's ``to_world``), fov along x, film size."""

    world_from_camera: Transform
    fov: float
    width: int
    height: int
    rfilter: str = "box"

    @staticmethod
    def from_dict(spec: dict) -> "PerspectiveCamera":
        """Validate a scene's ``"camera"`` entry (see the README's scene format)."""
        if not isinstance(spec, dict) or spec.get("type") != "perspective":
            kind = spec.get("type") if isinstance(spec, dict) else spec
            raise SceneError(f"camera: unknown camera type {kind!r}; supported: 'perspective'")
        extra = sorted(set(spec) - _CAMERA_KEYS)
        if extra:
            raise SceneError(f"camera: unknown keys {extra}; expected some of {sorted(_CAMERA_KEYS)}")
        fov = spec.get("fov", 45.0)
        if not isinstance(fov, (int, float)) or isinstance(fov, bool) or not 0 < fov < 180:
            raise SceneError(f"camera: fov must be a number of degrees in (0, 180), got {fov!r}")
        size = []
        for key, default in (("width", 256), ("height", 256)):
            value = spec.get(key, default)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 1 << 15:
                raise SceneError(f"camera: {key} must be an integer in [1, 32768], got {value!r}")
            size.append(value)
        rfilter = spec.get("rfilter", "box")
        if rfilter not in ("box", "gaussian"):
            raise SceneError(f"camera: rfilter must be 'box' or 'gaussian', got {rfilter!r}")
        to_world = parse_transform(spec.get("to_world", []), "camera: to_world")
        linear = np.array(to_world.matrix)[:3, :3]
        if not np.allclose(linear.T @ linear, np.eye(3), atol=1e-6):
            # As Mitsuba's sensor: a scaled or sheared camera frame would distort the view.
            raise SceneError("camera: to_world must be rigid (rotations, reflections and "
                             "translations only; no scale or shear)")
        return PerspectiveCamera(to_world, float(fov), size[0], size[1], rfilter)

    def with_size(self, width: int, height: int) -> "PerspectiveCamera":
        """The same camera with another film resolution."""
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

