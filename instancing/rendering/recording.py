"""Repeated renders replayed from a ``dr.freeze`` recording instead of traced again.

Every call of :func:`instancing.render` would run the integrator's Python code to
trace its kernels, even when the compiled kernels come from Dr.Jit's cache:
5 - 50 ms on the bundled scenes, as much as the kernels of a low-spp frame.
``dr.freeze`` records the kernel launches of one call; later calls with the same
settings replay them. Renders are recorded by default (``render(..., frozen=False)``
traces every call).

A replayed kernel is the kernel a plain render compiles: no value enters the
traced code as a literal that a replay could not update (the small scenes' world
boxes are opaque scalars, :class:`instancing.scene.intersection.WorldBoxes`). Measured
(128x96): replayed kernels as fast as plain ones within 5 %, 1-spp frames 1.4 -
7x faster (light_area direct 10.0 -> 2.1 ms); recording costs 1 - 4 ms more
than tracing (showcase direct 30 -> 34 ms), once per setting and scene revision,
so an animation that moves instances every frame renders as fast as with plain
renders.

What a replay relies on, and how it is kept true:

- Settings that enter the traced code as Python values (integrator, spp, image
  size, camera, ...) form the key of a recording; the seed is an input (an
  opaque ``UInt32``), so every seed replays the same recording.
- Every Dr.Jit array reachable from the scene, the camera and the light set is an
  input of the recording (:func:`~instancing.core.kernel_recording.jit_state`), so
  an array replaced by one of the same shape (a material's reflectance set through
  ``instancing.traverse``) is read on replay.
- A scene changed through its methods (``set_transforms``, ``set_accel``) bumps
  ``scene.revision``; recordings of an older revision are dropped.
- A recording may not call back into Python or upload host data mid-way (Dr.Jit
  aborts the process): renders with derivatives or a progress callback are not
  recorded, the caller builds the light set before recording, and Python's
  garbage collector is paused during the call.
- A recording that fails (an array the walk did not find) is not retried: that
  key renders plainly from then on (:func:`instancing.core.kernel_recording.call_recorded`).
"""

from __future__ import annotations

from typing import Any, Callable, Hashable

from ..core.backend import UInt32
from ..core.kernel_recording import call_recorded, jit_state, recordings_of


def replay(scene: Any, key: Hashable, image: Callable, camera: Any, lights: Any,
           settings: Hashable, seed: UInt32) -> Any:
    """``image(scene, camera, lights, settings, seed)``, replayed from the recording for
    ``key`` when there is one for the scene's current revision.

    ``image`` reads Dr.Jit arrays only from its arguments and Python values only from
    ``settings`` and ``camera`` (whose values ``key`` must determine). The camera is
    pinned: later calls with this key pass the recording call's own.
    """
    return call_recorded(recordings_of(scene, "render"), key, image,
                         (scene, camera, lights, settings, seed), _state, pinned=(1,))


def _state(scene: Any, camera: Any, lights: Any, settings: Any, seed: Any) -> list:
    """The Dr.Jit arrays a render reads, as extra inputs of its recording."""
    return jit_state(scene, camera, lights)
