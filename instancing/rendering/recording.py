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
  input of the recording (:func:`jit_state`), so an array replaced by one of the
  same shape (a material's reflectance set through ``instancing.traverse``) is
  read on replay.
- A scene changed through its methods (``set_transforms``, ``set_accel``) bumps
  ``scene.revision``; recordings of an older revision are dropped.
- A recording may not call back into Python or upload host data mid-way (Dr.Jit
  aborts the process): renders with derivatives or a progress callback are not
  recorded, the caller builds the light set before recording, and Python's
  garbage collector is paused during the call.
- A recording that fails (an array the walk did not find) is not retried: that
  key renders plainly from then on.
"""

from __future__ import annotations

import gc
import weakref
from typing import Any, Callable, Hashable

from ..core.backend import BACKEND_NAME, UInt32, dr

#: Objects of this package are walked for the arrays a recording reads.
_PACKAGE = __package__.split(".")[0] + "."

#: Recordings kept per scene (each holds its kernels' launch list): least recently used go.
MAX_RECORDINGS = 8

#: Per scene: (revision, {key: frozen function or None where recording failed}).
_recordings: "weakref.WeakKeyDictionary[Any, tuple[int, dict]]" = weakref.WeakKeyDictionary()


def jit_state(*roots: Any) -> list:
    """Every Dr.Jit array reachable from ``roots`` through this package's objects.

    Walks attributes, lists, tuples and dicts; NumPy arrays, Dr.Jit's host-side
    (scalar) arrays and other packages' objects are not entered: kernels read
    only JIT arrays, and the rest enters traced code as literals, which the
    recording's key or the scene's revision covers.
    """
    found: list = []
    # (Empty arrays hold nothing to read, and a recording cannot take them as inputs.)
    _walk(roots, lambda obj: found.append(obj) if dr.is_jit_v(obj) and dr.width(obj) else None,
          lambda obj: None)
    return found


def python_state(*roots: Any) -> tuple:
    """The Python numbers and strings reachable from ``roots`` as :func:`jit_state` walks
    them (NumPy arrays and Dr.Jit arrays left out), as a hashable key."""
    found: list = []
    _walk(roots, lambda obj: None, found.append)
    return tuple(found)


def _walk(roots: tuple, on_array: Callable[[Any], None], on_value: Callable[[Any], None]) -> None:
    seen: set[int] = set()

    def visit(obj: Any) -> None:
        if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
            on_value(obj)
            return
        if id(obj) in seen:
            return
        seen.add(id(obj))
        if dr.is_array_v(obj):
            on_array(obj)
        elif isinstance(obj, (list, tuple)):
            for item in obj:
                visit(item)
        elif isinstance(obj, dict):
            for item in obj.values():
                visit(item)
        elif (type(obj).__module__ or "").startswith(_PACKAGE):
            attrs = dict(vars(obj)) if hasattr(obj, "__dict__") else {}
            for slot in getattr(type(obj), "__slots__", ()):
                attrs[slot] = getattr(obj, slot, None)
            for item in attrs.values():
                visit(item)

    for root in roots:
        visit(root)


def replay(scene: Any, key: Hashable, image: Callable, camera: Any, lights: Any,
           settings: Hashable, seed: UInt32) -> Any:
    """``image(scene, camera, lights, settings, seed)``, replayed from the recording for
    ``key`` when there is one for the scene's current revision.

    ``image`` reads Dr.Jit arrays only from its arguments and Python values only from
    ``settings`` and ``camera`` (whose values ``key`` must determine); it must not close
    over the scene (the recordings would keep it alive).
    """
    revision, recordings = _recordings.get(scene, (None, {}))
    if revision != scene.revision:
        recordings = {}
        _recordings[scene] = (scene.revision, recordings)
    if key in recordings:
        recordings[key] = recordings.pop(key)  # most recently used last
    else:
        if len(recordings) >= MAX_RECORDINGS:
            del recordings[next(iter(recordings))]
        backend = dr.JitBackend.CUDA if BACKEND_NAME == "cuda" else dr.JitBackend.LLVM
        # Recorded with this call's camera, which later calls with this key pass again
        # (a frozen function compares non-array arguments by identity).
        recordings[key] = (dr.freeze(image, backend=backend, state_fn=_state), camera)
    function, camera = recordings[key]
    if function is None:
        return image(scene, camera, lights, settings, seed)
    # No garbage collection while recording: freeing a Dr.Jit array that wraps NumPy
    # memory enqueues a host callback, and Dr.Jit aborts a recording that meets one
    # (seen in the test suite: a collection of earlier garbage in the middle of a render).
    collecting = gc.isenabled()
    gc.disable()
    try:
        return function(scene, camera, lights, settings, seed)
    except RuntimeError as err:
        raise_interrupt(err)
        # The recording failed (and left nothing behind): render plainly from now on.
        recordings[key] = (None, camera)
    finally:
        if collecting:
            gc.enable()
    return image(scene, camera, lights, settings, seed)


def raise_interrupt(err: RuntimeError) -> None:
    """Re-raise the Ctrl-C (or exit) that ``err`` wraps: ``dr.freeze`` reports anything raised
    while it records, KeyboardInterrupt included, as a RuntimeError caused by it, which
    must stop the program rather than count as a failed recording."""
    cause = err.__cause__
    if cause is not None and not isinstance(cause, Exception):
        raise cause from None


def _state(scene: Any, camera: Any, lights: Any, settings: Any, seed: Any) -> list:
    """The Dr.Jit arrays a render reads, as extra inputs of its recording."""
    return jit_state(scene, camera, lights)
