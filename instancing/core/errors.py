"""Exceptions raised for input a user can get wrong.

Every error names its culprit (the file, the instance, the model or the
matrix entry) so that a user can find it in a scene of thousands of lines.
"""


class InstancingError(Exception):
    """Base class of every error this package raises on bad input."""


class BackendError(InstancingError, ImportError):
    """No usable Dr.Jit backend (for LLVM: no suitable system libLLVM)."""


class TransformError(InstancingError, ValueError):
    """A transform is singular, non-finite, projective or malformed."""


class SceneError(InstancingError, ValueError):
    """A scene description is malformed or refers to something unknown."""


class MeshFileError(SceneError):
    """A mesh file is missing, unreadable or malformed."""


class ResourceError(InstancingError, MemoryError):
    """A scene or render would need more memory than the machine has (refused before
    allocating, with the estimate)."""
