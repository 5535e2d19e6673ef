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

A camera may render a window of its film (Mitsuba's film crop): :attr:`Camera.window`
holds it in fractions of the film, and the image's (u, v) and pixels run over the window
alone. A perspective camera's ``principal_point`` moves the film's centre off the optical
axis by fractions of the film (Mitsuba's ``principal_point_offset_x`` and ``_y``).

A camera's ``sampler`` names how the random numbers of a pixel's samples are drawn, by the
names of Mitsuba's samplers: ``independent`` (the default, as Mitsuba's) or one that
stratifies them over the pixel's samples (``stratified``, ``multijitter``, ``orthogonal``,
``ldsampler``: all drawn by :class:`~instancing.core.rng.PixelSampler`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..core.arguments import integer, is_real
from ..core.backend import Array3f, Bool, Float, Matrix4f, UInt32, dr
from ..core.errors import SceneError, TransformError
from ..core.transform import Transform, require_rigid

#: Largest film side, in pixels.
MAX_FILM_SIZE = 1 << 15
#: Reconstruction filters: Mitsuba's ``box``, ``gaussian``, ``tent``, ``mitchell``,
#: ``catmullrom`` and ``lanczos``, each with the name of its size parameter in Mitsuba and its
#: default (pixels): the Gaussian's standard deviation (it reaches 4 of them), the tent's
#: radius, the Lanczos window's lobes (an integer, its radius); the box and the cubic filters
#: (radius 2) have none.
RFILTER_SIZES = {"box": None, "gaussian": ("stddev", 0.5), "tent": ("radius", 1.0), "mitchell": None,
                 "catmullrom": None, "lanczos": ("lobes", 3.0)}
RFILTERS = tuple(RFILTER_SIZES)
#: The cubic filters' (B, C) (Mitchell and Netravali, "Reconstruction Filters in Computer
#: Graphics", 1988): Mitsuba's defaults for ``mitchell`` (its parameters ``B`` and ``C``),
#: and ``catmullrom``'s.
CUBIC_FILTERS = {"mitchell": (1.0 / 3.0, 1.0 / 3.0), "catmullrom": (0.0, 0.5)}
#: A Gaussian filter reaches this many standard deviations (Mitsuba's truncation).
GAUSSIAN_REACH = 4.0
#: The widest reach of a filter, in pixels: a boundary sample is splatted into every pixel
#: its filter reaches.
MAX_RFILTER_REACH = 32
#: The window of a camera that renders its whole film.
WHOLE_FILM = (0.0, 0.0, 1.0, 1.0)
#: Mitsuba's default near-clip distance.
NEAR_CLIP = 1e-2
#: Mitsuba's sampler names that a camera takes; every one but ``independent`` stratifies.
SAMPLERS = ("independent", "stratified", "multijitter", "orthogonal", "ldsampler")
#: The samplers that take Mitsuba's ``jitter`` (their samples at the strata's centres when false).
JITTERED_SAMPLERS = ("stratified", "multijitter", "orthogonal")
#: A film's channels, by Mitsuba's ``pixel_format`` names: RGB, or RGB and alpha.
PIXEL_FORMATS = ("rgb", "rgba")


def _check_rfilter(name: str, size: float | None, bc: tuple[float, float] | None) -> None:
    """A reconstruction filter's name, size (:data:`RFILTER_SIZES`; None: its default) and a
    Mitchell filter's (B, C) (None: Mitsuba's), within :data:`MAX_RFILTER_REACH`."""
    if name not in RFILTERS:
        raise SceneError(f"rfilter: must be one of {list(RFILTERS)} (or a dict with 'type' and its "
                         f"size), got {name!r}")
    if bc is not None:
        if name != "mitchell":
            raise SceneError(f"rfilter: B and C are the mitchell filter's, not {name!r}'s")
        if not (isinstance(bc, tuple) and len(bc) == 2 and all(is_real(v) and math.isfinite(v) for v in bc)):
            raise SceneError(f"rfilter: the mitchell filter's B and C must be finite numbers, got {bc!r}")
    if size is None:
        return
    key = RFILTER_SIZES[name]
    if key is None:
        raise SceneError(f"rfilter: the {name} filter has no size, got {size!r}")
    if not is_real(size) or not 0 < size < math.inf:
        raise SceneError(f"rfilter: {key[0]} must be a positive number of pixels, got {size!r}")
    if name == "lanczos" and size != int(size):
        raise SceneError(f"rfilter: lobes must be a whole number (Mitsuba's is an integer), got {size!r}")
    reach = size * (GAUSSIAN_REACH if name == "gaussian" else 1.0)
    if reach > MAX_RFILTER_REACH:
        raise SceneError(f"rfilter: {key[0]} {size!r} reaches {reach:g} pixels; at most "
                         f"{MAX_RFILTER_REACH} are supported (a boundary sample is splatted into "
                         "every pixel the filter reaches)")


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
    #: The filter's size (:data:`RFILTER_SIZES`; None: Mitsuba's default, and the box's).
    rfilter_size: float | None = None
    #: The mitchell filter's (B, C) (:data:`CUBIC_FILTERS`; None: Mitsuba's default).
    rfilter_bc: tuple[float, float] | None = None
    near_clip: float = 0.0
    #: The name that picks it among the scene's cameras ("" when the file gives none).
    id: str = ""
    #: The part of the film that the image shows, (x0, y0, x1, y1) in fractions of the film's
    #: width and height from its top-left corner (Mitsuba's crop window): the image's
    #: ``width`` x ``height`` pixels cover it, so the whole film is width / (x1 - x0) by
    #: height / (y1 - y0) pixels.
    window: tuple[float, float, float, float] = WHOLE_FILM
    #: Whether film samples may fall past the image's edge, so that an edge pixel averages
    #: its whole filter (Mitsuba's ``sample_border``); by default only the part on the image.
    sample_border: bool = False
    #: The name of the medium the camera sits in ("": none; see :mod:`instancing.scene.medium`).
    medium: str = ""
    #: Samples per pixel of renders that name none (Mitsuba's sampler's ``sample_count``;
    #: None: :data:`instancing.rendering.film.DEFAULT_SPP`).
    spp: int | None = None
    #: How a pixel's samples draw their random numbers (:data:`SAMPLERS`).
    sampler: str = "independent"
    #: Added to every render's seed (modulo 2^32), as Mitsuba adds its sampler's ``seed``
    #: to the one a render is given: in [0, 2^32).
    seed: int = 0
    #: Whether a stratified sampler's draws lie at random within their strata (Mitsuba's
    #: ``jitter``; false: at their centres, e.g. one sample at each pixel's centre), for
    #: :data:`JITTERED_SAMPLERS` only.
    jitter: bool = True
    #: The film's channels (:data:`PIXEL_FORMATS`): ``rgba`` adds an alpha channel to the
    #: images of ``direct``, ``path`` and ``volpath``, as Mitsuba's film of that format.
    pixel_format: str = "rgb"
    #: Mitsuba's sensor plugin name.
    type = "camera"
    #: Random numbers per ray beyond the position on the film.
    aperture_samples = 0

    def __post_init__(self) -> None:
        """Check every value, whoever made the camera (a scene file's parser, which names
        where it came from, ``dataclasses.replace`` or a direct call)."""
        if not isinstance(self.world_from_camera, Transform) or not self.world_from_camera.is_scalar:
            raise SceneError(f"to_world must be an instancing.Transform of one pose, got "
                             f"{type(self.world_from_camera).__name__}")
        for key in ("width", "height"):
            integer(key, getattr(self, key), 1, MAX_FILM_SIZE)
        _check_rfilter(self.rfilter, self.rfilter_size, self.rfilter_bc)
        if not is_real(self.near_clip) or not 0 <= self.near_clip < math.inf:
            raise SceneError(f"near_clip must be a non-negative number, got {self.near_clip!r}")
        window = self.window
        if not (isinstance(window, tuple) and len(window) == 4 and all(is_real(c) for c in window)
                and 0 <= window[0] < window[2] <= 1 and 0 <= window[1] < window[3] <= 1):
            raise SceneError(f"window must be (x0, y0, x1, y1), fractions of the film with x0 < x1 "
                             f"and y0 < y1, got {window!r}")
        if not isinstance(self.sample_border, bool):
            raise SceneError(f"sample_border must be true or false, got {self.sample_border!r}")
        for key in ("id", "medium"):
            if not isinstance(getattr(self, key), str):
                raise SceneError(f"{key} must be a string, got {getattr(self, key)!r}")
        if self.spp is not None:
            integer("spp", self.spp, 1)
        if self.sampler not in SAMPLERS:
            raise SceneError(f"sampler must be one of {list(SAMPLERS)}, got {self.sampler!r}")
        integer("seed", self.seed, 0, 2 ** 32 - 1)
        if not isinstance(self.jitter, bool):
            raise SceneError(f"jitter must be true or false, got {self.jitter!r}")
        if not self.jitter and self.sampler not in JITTERED_SAMPLERS:
            raise SceneError(f"jitter: false applies to the samplers {list(JITTERED_SAMPLERS)}, not "
                             f"{self.sampler!r} (as in Mitsuba)")
        if self.pixel_format not in PIXEL_FORMATS:
            raise SceneError(f"pixel_format must be one of {list(PIXEL_FORMATS)}, got {self.pixel_format!r}")
        # Numbers of any kind (NumPy's too) are stored as Python's.
        self._store(width=int(self.width), height=int(self.height), near_clip=float(self.near_clip),
                    window=tuple(map(float, window)),
                    rfilter_size=None if self.rfilter_size is None else float(self.rfilter_size),
                    rfilter_bc=None if self.rfilter_bc is None else tuple(map(float, self.rfilter_bc)),
                    spp=None if self.spp is None else int(self.spp), seed=int(self.seed))

    def _store(self, **values) -> None:
        """Set fields of the (frozen) camera while it is made."""
        for key, value in values.items():
            object.__setattr__(self, key, value)

    def with_size(self, width: int, height: int) -> "Camera":
        """The same camera with another film resolution (checked: an integer in
        [1, MAX_FILM_SIZE] per side)."""
        return dataclasses.replace(self, width=integer("width", width, 1, MAX_FILM_SIZE),
                                   height=integer("height", height, 1, MAX_FILM_SIZE))

    def batches_with(self, other: "Camera") -> bool:
        """Whether ``other`` can be traced in one wavefront with this camera
        (:class:`CameraBatch`): the same type, film size and window, filter, sampling, seed and
        pixel format."""
        return type(other) is type(self) and self._film_key() == other._film_key()

    def _film_key(self) -> tuple:
        return (self.width, self.height, self.rfilter, self.rfilter_size, self.rfilter_bc, self.window,
                self.sample_border,
                self.stratified, self.jitter, self.seed, self.pixel_format)

    @property
    def alpha(self) -> bool:
        """Whether the film has an alpha channel."""
        return self.pixel_format == "rgba"

    @property
    def stratified(self) -> bool:
        """Whether a pixel's samples are stratified (any sampler but ``independent``)."""
        return self.sampler != "independent"

    def key(self) -> tuple:
        """The camera's values as a hashable tuple (a render's recording belongs to one pose)."""
        matrix = np.asarray(self.world_from_camera.matrix, np.float64)
        values = [getattr(self, f.name) for f in dataclasses.fields(self)
                  if f.name not in ("world_from_camera", "id", "spp")]
        return (self.type, tuple(matrix.ravel().tolist()), *values)

    def _lanes(self, transform: Transform) -> Transform:
        """A scalar transform of the pose as per-lane float32 matrices of opaque values:
        the pose enters kernels as values, not literals, so that a moved camera (a
        turntable) reuses the compiled kernels instead of compiling new ones."""
        matrix, inverse = Matrix4f(transform.matrix), Matrix4f(transform.inverse_matrix)
        dr.make_opaque(matrix, inverse)
        return Transform(matrix, inverse)

    def _aspect(self) -> Float:
        """The whole film's width over its height."""
        x0, y0, x1, y1 = self.window
        return dr.opaque(Float, (self.width / (x1 - x0)) / (self.height / (y1 - y0)))

    def _film_position(self, u: Float, v: Float) -> tuple[Float, Float]:
        """Film fractions (of the whole film) of image positions (u, v) in [0, 1]^2."""
        if self.window == WHOLE_FILM:
            return u, v
        x0, y0, x1, y1 = self.window
        return x0 + u * (x1 - x0), y0 + v * (y1 - y0)

    def _film_scale(self) -> tuple[float, float]:
        """Image pixels per unit of film fraction, along x and y."""
        x0, y0, x1, y1 = self.window
        return self.width / (x1 - x0), self.height / (y1 - y0)

    def values(self) -> dict[str, float]:
        """The numbers besides the pose and the film that its rays depend on (one entry per
        view in a :class:`CameraBatch`)."""
        return {"near_clip": self.near_clip}

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None,
             lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Array3f, Array3f]:
        """World rays through film positions (u, v) in [0, 1]^2 (top-left origin); unit
        directions. ``aperture``: :attr:`aperture_samples` random numbers (None: the
        aperture's centre). ``lanes``: each lane's pose and :meth:`values` (default: this
        camera's on every lane; :meth:`CameraBatch.lanes`: each lane's view's)."""
        raise NotImplementedError

    def pixel_centre_rays(self) -> tuple[Array3f, Array3f]:
        """One ray through the centre of every pixel (and of the aperture), in row-major order."""
        index = dr.arange(UInt32, self.width * self.height)
        x = Float(index % self.width) + 0.5
        y = Float(index // self.width) + 0.5
        return self.rays(x / self.width, y / self.height)

    def viewpoint(self) -> np.ndarray | None:
        """Where every ray comes from, homogeneous (4,) float64: a world point (w = 1), or a
        direction to a viewer at infinity (w = 0); None where rays leave no single point (a
        lens). The boundary terms sample the curves seen from it on the film."""
        return None

    def lane_viewpoint(self, lanes: "CameraLanes | BatchLanes") -> tuple[Array3f, float]:
        """:meth:`viewpoint` of each lane's view, as (xyz, w) (the same w for every view)."""
        raise NotImplementedError

    def project(self, p: Array3f, lanes: "CameraLanes | BatchLanes | None" = None
                ) -> tuple[Float, Float, Bool]:
        """Film position in pixels (x right, y down, origin at the top-left corner) of world
        points; the inverse of :meth:`rays` (a camera with a :meth:`viewpoint`).
        Differentiable in ``p``. ``lanes`` as for :meth:`rays`.

        Returns ``(x, y, in_front)``; ``in_front`` is False for points the rays do not reach
        (at or behind the camera plane; their x, y are meaningless).
        """
        raise NotImplementedError

    def film_velocity(self, p: Array3f, v: Array3f,
                      lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Float, Float]:
        """Film motion (pixels per unit) of the image of point ``p`` moving with world velocity ``v``:
        the Jacobian of :meth:`project` applied to v."""
        raise NotImplementedError


@dataclass(frozen=True, kw_only=True)
class PerspectiveCamera(Camera):
    """A pinhole camera: field of view ``fov`` along x (Mitsuba's ``perspective``)."""

    fov: float = 45.0
    #: The film's centre off the optical axis, in fractions of the film's width and height
    #: (Mitsuba's ``principal_point_offset_x`` and ``_y``; the perspective camera's alone).
    principal_point: tuple[float, float] = (0.0, 0.0)
    type = "perspective"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not is_real(self.fov) or not 0 < self.fov < 180:
            raise SceneError(f"fov must be a number of degrees in (0, 180), got {self.fov!r}")
        point = self.principal_point
        if not (isinstance(point, tuple) and len(point) == 2 and all(is_real(c) and math.isfinite(c)
                                                                     for c in point)):
            raise SceneError(f"principal_point must be two finite numbers (fractions of the film's "
                             f"width and height), got {point!r}")
        # As Mitsuba's sensor: a scaled or sheared camera frame would distort the view (an
        # orthographic camera's scale sets the extent it sees).
        try:
            require_rigid(self.world_from_camera, "to_world")
        except TransformError as err:
            raise SceneError(str(err)) from None
        self._store(fov=float(self.fov), principal_point=tuple(map(float, point)))

    def values(self) -> dict[str, float]:
        return {"tan_half": math.tan(math.radians(self.fov) / 2), "near_clip": self.near_clip}

    def _film_key(self) -> tuple:
        return super()._film_key() + (self.principal_point,)

    def _optical_position(self, u: Float, v: Float) -> tuple[Float, Float]:
        """Film fractions of image positions (u, v), measured from the film's corner as
        placed about the optical axis (the principal point moves the film)."""
        x, y = self._film_position(u, v)
        if self.principal_point == (0.0, 0.0):
            return x, y
        return x + self.principal_point[0], y + self.principal_point[1]

    def _directions(self, u: Float, v: Float, lanes: "CameraLanes | BatchLanes") -> Array3f:
        """Camera-space directions (z = 1) through image positions (u, v)."""
        tan_half, aspect = lanes.value("tan_half"), self._aspect()
        x, y = self._optical_position(u, v)
        # Film to camera space: +x left, +y up, looking down +z.
        return Array3f((1 - 2 * x) * tan_half, (1 - 2 * y) * tan_half / aspect, 1.0)

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None,
             lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Array3f, Array3f]:
        lanes = CameraLanes(self) if lanes is None else lanes
        local = self._directions(u, v, lanes)
        pose = lanes.pose()
        d = dr.normalize(pose.apply_vector(local))
        o = Array3f(*[pose.matrix[i][3] for i in range(3)]) + dr.zeros(Array3f, dr.width(u))
        if lanes.near_clip:
            # The near plane: the ray starts where it crosses z = near_clip.
            o = dr.fma(d, lanes.value("near_clip") * dr.norm(local), o)
        return o, d

    def viewpoint(self) -> np.ndarray | None:
        return np.append(np.asarray(self.world_from_camera.matrix, np.float64)[:3, 3], 1.0)

    def lane_viewpoint(self, lanes: "CameraLanes | BatchLanes") -> tuple[Array3f, float]:
        pose = lanes.pose().matrix
        return Array3f(pose[0][3], pose[1][3], pose[2][3]), 1.0

    def project(self, p: Array3f, lanes: "CameraLanes | BatchLanes | None" = None
                ) -> tuple[Float, Float, Bool]:
        lanes = CameraLanes(self) if lanes is None else lanes
        tan_half, aspect = lanes.value("tan_half"), self._aspect()
        q = lanes.pose().inverse().apply_point(p)
        in_front = q.z > 0
        z = dr.select(in_front, q.z, 1.0)
        if self.window == WHOLE_FILM and self.principal_point == (0.0, 0.0):
            x = (1 - q.x / (z * tan_half)) * (0.5 * self.width)
            y = (1 - q.y * aspect / (z * tan_half)) * (0.5 * self.height)
            return x, y, in_front
        # Film fractions about the optical axis, less the principal point and the window's corner.
        (sx, sy), (x0, y0) = self._film_scale(), self.window[:2]
        x = (0.5 * (1 - q.x / (z * tan_half)) - (self.principal_point[0] + x0)) * sx
        y = (0.5 * (1 - q.y * aspect / (z * tan_half)) - (self.principal_point[1] + y0)) * sy
        return x, y, in_front

    def film_velocity(self, p: Array3f, v: Array3f,
                      lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Float, Float]:
        lanes = CameraLanes(self) if lanes is None else lanes
        tan_half, aspect = lanes.value("tan_half"), self._aspect()
        camera_from_world = lanes.pose().inverse()
        q, dq = camera_from_world.apply_point(p), camera_from_world.apply_vector(v)
        z2 = q.z * q.z * tan_half
        sx, sy = self._film_scale()
        return (-(0.5 * sx) * (dq.x * q.z - q.x * dq.z) / z2,
                -(0.5 * sy * aspect) * (dq.y * q.z - q.y * dq.z) / z2)


@dataclass(frozen=True, kw_only=True)
class ThinLensCamera(PerspectiveCamera):
    """A perspective camera with a lens: rays leave points of the aperture disk of radius
    ``aperture_radius`` and meet at the focal plane ``focus_distance`` ahead (Mitsuba's
    ``thinlens``)."""

    aperture_radius: float = 0.0
    focus_distance: float = 1e4
    type = "thinlens"
    aperture_samples = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        for key in ("aperture_radius", "focus_distance"):
            value = getattr(self, key)
            if not is_real(value) or not 0 < value < math.inf:
                raise SceneError(f"{key} must be a positive number, got {value!r}")
            self._store(**{key: float(value)})

    def viewpoint(self) -> np.ndarray | None:
        return None

    def values(self) -> dict[str, float]:
        return {**super().values(), "aperture_radius": self.aperture_radius,
                "focus_distance": self.focus_distance}

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None,
             lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Array3f, Array3f]:
        lanes = CameraLanes(self) if lanes is None else lanes
        local = self._directions(u, v, lanes)
        focus = local * lanes.value("focus_distance")
        lens = Array3f(0.0)
        if aperture is not None:
            x, y = square_to_uniform_disk_concentric(*aperture)
            radius = lanes.value("aperture_radius")
            lens = Array3f(radius * x, radius * y, 0.0)
        d_local = dr.normalize(focus - lens)
        pose = lanes.pose()
        d = dr.normalize(pose.apply_vector(d_local))
        o = pose.apply_point(lens)
        # The near plane: the ray starts where it crosses z = near_clip.
        o = dr.fma(d, lanes.value("near_clip") / d_local.z, o)
        return o, d


@dataclass(frozen=True, kw_only=True)
class OrthographicCamera(Camera):
    """Parallel rays along the camera's +z from the near plane's points: camera-space x
    in [-1, 1] across the film (+1 on the left), y by the aspect (Mitsuba's
    ``orthographic``; its ``to_world`` may scale the view)."""

    type = "orthographic"

    def rays(self, u: Float, v: Float, aperture: tuple[Float, Float] | None = None,
             lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Array3f, Array3f]:
        lanes = CameraLanes(self) if lanes is None else lanes
        x, y = self._film_position(u, v)
        near = Array3f(1 - 2 * x, (1 - 2 * y) / self._aspect(),
                       lanes.value("near_clip") + dr.zeros(Float, dr.width(u)))
        pose = lanes.pose()
        d = dr.normalize(pose.apply_vector(Array3f(0.0, 0.0, 1.0)))
        return pose.apply_point(near), d + dr.zeros(Array3f, dr.width(u))

    def viewpoint(self) -> np.ndarray | None:
        forward = np.asarray(self.world_from_camera.matrix, np.float64)[:3, 2]
        return np.append(-forward / np.linalg.norm(forward), 0.0)

    def lane_viewpoint(self, lanes: "CameraLanes | BatchLanes") -> tuple[Array3f, float]:
        pose = lanes.pose().matrix
        return -dr.normalize(Array3f(pose[0][2], pose[1][2], pose[2][2])), 0.0

    def project(self, p: Array3f, lanes: "CameraLanes | BatchLanes | None" = None
                ) -> tuple[Float, Float, Bool]:
        lanes = CameraLanes(self) if lanes is None else lanes
        q = lanes.pose().inverse().apply_point(p)
        (sx, sy), (x0, y0) = self._film_scale(), self.window[:2]
        x = (0.5 * (1 - q.x) - x0) * sx
        y = (0.5 * (1 - q.y * self._aspect()) - y0) * sy
        return x, y, q.z > lanes.value("near_clip")

    def film_velocity(self, p: Array3f, v: Array3f,
                      lanes: "CameraLanes | BatchLanes | None" = None) -> tuple[Float, Float]:
        lanes = CameraLanes(self) if lanes is None else lanes
        dq = lanes.pose().inverse().apply_vector(v)
        sx, sy = self._film_scale()
        return -(0.5 * sx) * dq.x, -(0.5 * sy) * self._aspect() * dq.y


class CameraLanes:
    """Every lane sees one camera: its pose and :meth:`Camera.values` as opaque values (a
    moved camera reuses the compiled kernels)."""

    def __init__(self, camera: Camera):
        self._camera = camera
        #: Whether rays start on a near plane (a pinhole's start at the camera when it is 0).
        self.near_clip = bool(camera.near_clip)

    def value(self, name: str) -> Float:
        return dr.opaque(Float, self._camera.values()[name])

    def pose(self) -> Transform:
        return self._camera._lanes(self._camera.world_from_camera)


#: The entries of an affine pose that a camera batch stores per view (the rows above [0 0 0 1]).
_POSE_ENTRIES = [(i, j) for i in range(3) for j in range(4)]


class CameraBatch:
    """Cameras of one type, film size and filter traced as one wavefront: lane ``i`` renders
    view ``view[i]``, whose pose and :meth:`Camera.values` it gathers from arrays of one entry
    per view. Built on the host, before a recording (its arrays are the recording's inputs);
    one camera needs no arrays (:class:`CameraLanes`)."""

    def __init__(self, cameras: list[Camera] | tuple[Camera, ...]):
        self.cameras = tuple(cameras)
        first = self.cameras[0]
        for camera in self.cameras[1:]:
            if not first.batches_with(camera):
                raise SceneError(f"camera {camera.id or camera.type!r} cannot share a wavefront "
                                 f"with {first.id or first.type!r}: type, film size, window, filter, "
                                 "sampler, seed or pixel format differ")
        #: The representative camera: type, film size, filter and aperture samples.
        self.camera = first
        self._tables: dict = {}
        if len(self.cameras) > 1:
            self._tables = {name: Float([c.values()[name] for c in self.cameras])
                            for name in first.values()}
            for side, transform in (("matrix", lambda c: c.world_from_camera),
                                    ("inverse", lambda c: c.world_from_camera.inverse())):
                rows = [np.asarray(transform(c).matrix, np.float64) for c in self.cameras]
                self._tables[side] = [Float([m[i, j] for m in rows]) for i, j in _POSE_ENTRIES]

    def __len__(self) -> int:
        return len(self.cameras)

    @staticmethod
    def group(cameras: list[Camera], max_pixels: int) -> list[tuple["CameraBatch", list[int]]]:
        """``cameras`` as runs of consecutive cameras that can share a wavefront and together
        hold at most ``max_pixels`` pixels (at least one camera each), with each run's
        indices into ``cameras``."""
        runs: list[list[int]] = []
        for k, camera in enumerate(cameras):
            if runs:
                first = cameras[runs[-1][0]]
                if (first.batches_with(camera)
                        and (len(runs[-1]) + 1) * first.width * first.height <= max_pixels):
                    runs[-1].append(k)
                    continue
            runs.append([k])
        return [(CameraBatch([cameras[k] for k in run]), run) for run in runs]

    def lanes(self, view: UInt32 | None) -> "CameraLanes | BatchLanes":
        """Where each lane's pose and values come from: ``view`` holds each lane's view (None
        for a batch of one camera)."""
        if len(self.cameras) == 1:
            return CameraLanes(self.camera)
        return BatchLanes(self, view)


class BatchLanes:
    """Each lane's view's pose and values, gathered from a :class:`CameraBatch`'s arrays."""

    def __init__(self, batch: CameraBatch, view: UInt32):
        self._tables, self._view = batch._tables, view
        self.near_clip = any(c.near_clip for c in batch.cameras)

    def value(self, name: str) -> Float:
        return dr.gather(Float, self._tables[name], self._view)

    def pose(self) -> Transform:
        def matrix(side: str) -> Matrix4f:
            entries = dict(zip(_POSE_ENTRIES, (dr.gather(Float, table, self._view)
                                               for table in self._tables[side])))
            return Matrix4f([[entries[i, j] for j in range(4)] for i in range(3)]
                            + [[0.0, 0.0, 0.0, 1.0]])
        return Transform(matrix("matrix"), matrix("inverse"))


#: The film axes a field of view may be given along (Mitsuba's ``fov_axis``).
FOV_AXES = ("x", "y", "diagonal", "smaller", "larger")


def diagonal_fov(focal_length: float) -> float:
    """The field of view (degrees) along the film diagonal of a lens of ``focal_length`` mm
    on 35 mm film (36 x 24 mm), as Mitsuba converts a ``focal_length`` (default 50)."""
    return 2.0 * math.degrees(math.atan(math.hypot(36.0, 24.0) / (2.0 * focal_length)))


def fov_along_x(fov: float, axis: str, aspect: float) -> float:
    """The horizontal field of view (degrees) of a film of ``aspect`` (width / height) whose
    field of view along ``axis`` (:data:`FOV_AXES`) is ``fov`` degrees, as Mitsuba's
    ``parse_fov``. Raises ValueError for an unknown axis or a result outside (0, 180)."""
    axis = axis.lower()
    if axis == "smaller":
        axis = "y" if aspect > 1 else "x"
    elif axis == "larger":
        axis = "x" if aspect > 1 else "y"
    if axis == "x":
        result = fov
    elif axis == "y":
        result = math.degrees(2.0 * math.atan(math.tan(0.5 * math.radians(fov)) * aspect))
    elif axis == "diagonal":
        diagonal = 2.0 * math.tan(0.5 * math.radians(fov))
        width = diagonal / math.sqrt(1.0 + 1.0 / (aspect * aspect))
        result = math.degrees(2.0 * math.atan(width * 0.5))
    else:
        raise ValueError(f"fov_axis {axis!r} is not one of {', '.join(map(repr, FOV_AXES))}")
    if not 0.0 < result < 180.0:
        raise ValueError(f"the horizontal field of view {result} must lie in (0, 180) degrees")
    return result


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
