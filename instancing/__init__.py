"""instancing: a differentiable ray tracer built around affine transforms and instancing.

Importing the package selects the Dr.Jit backend (see :mod:`instancing.core.backend`)
and fails with a clear :class:`~instancing.core.errors.BackendError` when no usable
LLVM is installed.
"""

from .ad.optimisation import OptimisationStep
from .ad.parameters import SceneParameters, traverse
from .core.backend import BACKEND_NAME
from .core.errors import (BackendError, InstancingError, MeshFileError, ResourceError, SceneError,
                          TransformError)
from .core.transform import (Transform, from_matrix, identity, look_at, reflect, rotate, rotate_x,
                             rotate_y, rotate_z, scale, translate)
from .io.image import ImageDataError, ImageFileError, read_exr, write_exr, write_png
from .io.mitsuba_export import to_mitsuba
from .io.scene_file import load_scene, parse_camera
from .rendering.film import channel_names, render
from .scene.camera import Camera, OrthographicCamera, PerspectiveCamera, ThinLensCamera
from .scene.intersection import PreliminaryHit, SurfaceHit
from .scene.scene import Hits, Scene

__version__ = "0.1.0"

__all__ = [
    "BACKEND_NAME", "BackendError", "InstancingError", "MeshFileError", "ResourceError",
    "SceneError", "TransformError", "PreliminaryHit", "SurfaceHit", "Hits", "Scene", "load_scene",
    "parse_camera", "Camera", "PerspectiveCamera", "ThinLensCamera", "OrthographicCamera",
    "render", "channel_names", "to_mitsuba", "traverse", "SceneParameters", "OptimisationStep",
    "write_exr", "read_exr", "write_png", "ImageFileError", "ImageDataError",
    "Transform", "from_matrix", "identity", "look_at", "reflect", "rotate", "rotate_x",
    "rotate_y", "rotate_z", "scale", "translate",
]
