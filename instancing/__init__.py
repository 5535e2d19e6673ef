"""instancing: a differentiable ray tracer built around affine transforms and instancing.

Importing the package selects the Dr.Jit backend (see :mod:`instancing.backend`)
and fails with a clear :class:`~instancing.errors.BackendError` when no usable
LLVM is installed.
"""

from .backend import BACKEND_NAME
from .errors import BackendError, InstancingError, MeshFileError, SceneError, TransformError
from .intersection import PreliminaryHit, SurfaceHit
from .io.image import ImageDataError, ImageFileError, read_exr, write_exr, write_png
from .mitsuba_export import to_mitsuba
from .optimisation import OptimisationStep
from .parameters import SceneParameters, traverse
from .rendering import channel_names, render
from .scene import Hits, Scene, load_scene
from .transform import (Transform, from_matrix, identity, look_at, reflect, rotate, rotate_x,
                        rotate_y, rotate_z, scale, translate)

__version__ = "0.1.0"

__all__ = [
    "BACKEND_NAME", "BackendError", "InstancingError", "MeshFileError", "SceneError",
    "TransformError", "PreliminaryHit", "SurfaceHit", "Hits", "Scene", "load_scene", "render",
    "channel_names", "to_mitsuba", "traverse", "SceneParameters", "OptimisationStep", "write_exr", "read_exr", "write_png", "ImageFileError", "ImageDataError",
    "Transform", "from_matrix", "identity", "look_at", "reflect", "rotate", "rotate_x",
    "rotate_y", "rotate_z", "scale", "translate",
]
