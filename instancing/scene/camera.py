"""Cameras with Mitsuba's conventions: ``perspective`` (a pinhole), ``thinlens`` (a
perspective camera with a circular aperture focused at a distance) and ``orthographic``.

Camera space looks down +z with +y up and +x to the left (Mitsuba's sensors with a
``look_at`` ``to_world``); ``fov`` is the full horizontal field of view in degrees.
Film coordinates (u, v) in [0, 1]^2 run from the top-left corner, so the same camera
gives the same picture as Mitsuba. Rays start on the near plane, ``near_clip`` in front of
the camera (Mitsuba's default 0.01; for the pinhole, at the camera when 0). An
orthographic camera sees the camera-space square [-1, 1] along x (the height by the film's
aspect), scaled by its ``to_world`` as in Mitsuba. A thin lens traces from a point of its
aperture disk (two more random numbers per ray, Mitsuba's concentric disk warp) through
the point of the focal plane that the pinhole ray through (u, v) meets.
"""

from __future__ import annotations

import dataclasses
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
#: Mitsuba's default near-clip distance.
NEAR_CLIP = 1e-2


@dataclass(frozen=True, kw_only=True)
class Camera:
    """What every camera has: world_from_camera (the scene's ``to_world``), film size,
    reconstruction filter and near-clip distance. Made from a scene file's ``"camera"`` (or
    an entry of its ``"cameras"``) by :func:`instancing.io.scene_file.parse_camera`, which
    validates it."""

    world_from_camera: Transform
    width: int
    height: int
    rfilter: str = "box"
    near_clip: float = 0.0
    #: The name that picks it among the scene's cameras ("" when the file gives none).
    id: str = ""
    #: Mitsuba's sensor plugin name.
    type = "camera"
    #: Whether all rays leave one point (the boundary terms sample edges on its film).
    pinhole = False
    #: Random numbers per ray beyond the position on the film.
    aperture_samples = 0

    def with_size(self, width: int, height: int) -> "Camera":
        """The same camera with another film resolution (checked: an integer in
        [1, MAX_FILM_SIZE] per side)."""
        for name, value in (("width", width), ("height", height)):
            if (not isinstance(value, int) or isinstance(value, bool)
                    or not 1 <= value <= MAX_FILM_SIZE):
                raise SceneError(f"{name} must be an integer in [1, {MAX_FILM_SIZE}], got {value!r}")
        return dataclasses.replace(self, width=width, height=height)

    def key(self) -> tuple:
        """The camera's values as a hashable tuple (a render's recording belongs to one pose)."""
        matrix = np.asarray(self.world_from_camera.matrix, np.float64)
        values = [getattr(self, f.name) for f in dataclasses.fields(self)
                  if f.name not in ("world_from_camera", "id")]
        return (self.type, tuple(matrix.ravel().tolist()), *values)

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

    def _aspect(self) -> Float:
        return dr.opaque(Float, self.width / self.height)

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None
             ) -> tuple[Array3f, Array3f]:
        """World rays through film positions (u, v) in [0, 1]^2 (top-left origin); unit
        directions. ``aperture``: :attr:`aperture_samples` random numbers (None: the
        aperture's centre)."""
        raise NotImplementedError

    def pixel_centre_rays(self) -> tuple[Array3f, Array3f]:
        """One ray through the centre of every pixel (and of the aperture), in row-major order."""
        index = dr.arange(UInt32, self.width * self.height)
        x = Float(index % self.width) + 0.5
        y = Float(index // self.width) + 0.5
        return self.rays(x / self.width, y / self.height)


@dataclass(frozen=True, kw_only=True)
class PerspectiveCamera(Camera):
    """A pinhole camera: field of view ``fov`` along x (Mitsuba's ``perspective``)."""

    fov: float = 45.0
    type = "perspective"
    pinhole = True

    def _film(self) -> tuple[Float, Float]:
        """(tan of half the horizontal field of view, width / height) as opaque values."""
        return dr.opaque(Float, math.tan(math.radians(self.fov) / 2)), self._aspect()

    def _directions(self, u: Float, v: Float) -> Array3f:
        """Camera-space directions (z = 1) through film positions (u, v)."""
        tan_half, aspect = self._film()
        # Film to camera space: +x left, +y up, looking down +z.
        return Array3f((1 - 2 * u) * tan_half, (1 - 2 * v) * tan_half / aspect, 1.0)

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None
             ) -> tuple[Array3f, Array3f]:
        local = self._directions(u, v)
        lanes = self._lanes(self.world_from_camera)
        d = dr.normalize(lanes.apply_vector(local))
        o = Array3f(*[lanes.matrix[i][3] for i in range(3)]) + dr.zeros(Array3f, dr.width(u))
        if self.near_clip:
            # The near plane: the ray starts where it crosses z = near_clip.
            o = dr.fma(d, dr.opaque(Float, self.near_clip) * dr.norm(local), o)
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



@dataclass(frozen=True, kw_only=True)
class ThinLensCamera(PerspectiveCamera):
    """A perspective camera with a lens: rays leave points of the aperture disk of radius
    ``aperture_radius`` and meet at the focal plane ``focus_distance`` ahead (Mitsuba's
    ``thinlens``)."""

    aperture_radius: float = 0.0
    focus_distance: float = 1e4
    type = "thinlens"
    pinhole = False
    aperture_samples = 2

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None
             ) -> tuple[Array3f, Array3f]:
        local = self._directions(u, v)
        focus = local * dr.opaque(Float, self.focus_distance)
        lens = Array3f(0.0)
        if aperture is not None:
            x, y = square_to_uniform_disk_concentric(*aperture)
            radius = dr.opaque(Float, self.aperture_radius)
            lens = Array3f(radius * x, radius * y, 0.0)
        d_local = dr.normalize(focus - lens)
        lanes = self._lanes(self.world_from_camera)
        d = dr.normalize(lanes.apply_vector(d_local))
        o = lanes.apply_point(lens)
        # The near plane: the ray starts where it crosses z = near_clip.
        o = dr.fma(d, dr.opaque(Float, self.near_clip) / d_local.z, o)
        return o, d


@dataclass(frozen=True, kw_only=True)
class OrthographicCamera(Camera):
    """Parallel rays along the camera's +z from the near plane's points: camera-space x
    in [-1, 1] across the film (+1 on the left), y by the aspect (Mitsuba's
    ``orthographic``; its ``to_world`` may scale the view)."""

    type = "orthographic"

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None
             ) -> tuple[Array3f, Array3f]:
        near = Array3f(1 - 2 * u, (1 - 2 * v) / self._aspect(),
                       dr.opaque(Float, self.near_clip) + dr.zeros(Float, dr.width(u)))
        lanes = self._lanes(self.world_from_camera)
        d = dr.normalize(lanes.apply_vector(Array3f(0.0, 0.0, 1.0)))
        return lanes.apply_point(near), d + dr.zeros(Array3f, dr.width(u))


def square_to_uniform_disk_concentric(u1: Float, u2: Float) -> tuple[Float, Float]:
    """Shirley and Chiu's concentric map of [0, 1)^2 onto the unit disk (Mitsuba's
    ``square_to_uniform_disk_concentric``)."""
    x, y = 2 * u1 - 1, 2 * u2 - 1
    first = dr.abs(x) > dr.abs(y)
    r = dr.select(first, x, y)
    safe_x = dr.select(x == 0, 1.0, x)
    safe_y = dr.select(y == 0, 1.0, y)
    phi = dr.select(first, (math.pi / 4) * y / safe_x, math.pi / 2 - (math.pi / 4) * x / safe_y)
    phi = dr.select((x == 0) & (y == 0), 0.0, phi)
    s, c = dr.sincos(phi)
    return r * c, r * s


#: Camera types by Mitsuba's sensor plugin name.
CAMERAS = {camera.type: camera for camera in (PerspectiveCamera, ThinLensCamera, OrthographicCamera)}
