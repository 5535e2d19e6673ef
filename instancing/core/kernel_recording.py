"""Kernel launches recorded once with ``dr.freeze`` and replayed instead of traced again.

Tracing runs the Python code of a query or a render to build its kernels, even when the
compiled kernels come from Dr.Jit's cache. ``dr.freeze`` records the kernel launches of one
call; later calls with compatible arguments replay them. This module holds what every
recorded entry point shares (renders, :mod:`instancing.rendering.recording`; optimisation
steps, :mod:`instancing.ad.optimisation`; ray queries, :meth:`instancing.Scene.intersect`):

- :func:`jit_state`: every Dr.Jit array reachable from the objects a recorded function
  reads, passed as extra inputs, so that an array replaced by one of the same shape is
  read on replay; :func:`python_state` the Python values beside them, for keys.
- :class:`Recordings`, :func:`recordings_of`: an owner's recording tables, one per
  purpose, dropped when its ``revision`` changes (a scene changed through its methods).
- :func:`call_recorded`: a function called through its recording for a key, made on first
  use (or the ``record_at``-th), with the least recently used dropped beyond
  MAX_RECORDINGS; a recording that fails (an array the walk did not find) is not retried:
  that key runs plainly from then on.
"""

from __future__ import annotations

import gc
from typing import Any, Callable, Hashable

from .backend import BACKEND_NAME, dr

#: Objects of this package are walked for the arrays a recording reads.
_PACKAGE = __package__.split(".")[0] + "."

#: Recordings kept per table (each holds its kernels' launch list): least recently used go.
MAX_RECORDINGS = 8
#: Keys per table whose calls are counted before they are recorded (``record_at``).
MAX_PENDING = 64


def jit_state(*roots: Any) -> list:
    """Every Dr.Jit array reachable from ``roots`` through this package's objects.

    Walks attributes, lists, tuples and dicts; NumPy arrays, Dr.Jit's host-side
    (scalar) arrays and other packages' objects are not entered: kernels read
    only JIT arrays, and the rest enters traced code as literals, which the
    recording's key or the owner's revision covers.
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


# How :func:`_walk` treats an object, by its type (decided once per type).
_VALUE, _ARRAY, _SKIP, _SEQUENCE, _MAPPING, _OBJECT = range(6)
_KINDS: dict[type, int] = {}


def _kind(cls: type) -> int:
    """How :func:`_walk` treats objects of type ``cls``."""
    kind = _KINDS.get(cls)
    if kind is None:
        if cls is type(None) or issubclass(cls, (bool, int, float, str, bytes)):
            kind = _VALUE
        elif dr.is_array_v(cls):
            kind = _ARRAY
        elif issubclass(cls, Recordings):
            kind = _SKIP
        elif issubclass(cls, (list, tuple)):
            kind = _SEQUENCE
        elif issubclass(cls, dict):
            kind = _MAPPING
        elif (cls.__module__ or "").startswith(_PACKAGE):
            kind = _OBJECT
        else:
            kind = _SKIP
        _KINDS[cls] = kind
    return kind


def _walk(roots: tuple, on_array: Callable[[Any], None], on_value: Callable[[Any], None]) -> None:
    seen: set[int] = set()

    def visit(obj: Any) -> None:
        kind = _KINDS.get(type(obj))
        if kind is None:
            kind = _kind(type(obj))
        if kind == _VALUE:
            on_value(obj)
            return
        if kind == _SKIP or id(obj) in seen:
            return
        seen.add(id(obj))
        if kind == _ARRAY:
            on_array(obj)
        elif kind == _SEQUENCE:
            for item in obj:
                visit(item)
        elif kind == _MAPPING:
            for item in obj.values():
                visit(item)
        else:
            if hasattr(obj, "__dict__"):
                for item in vars(obj).values():
                    visit(item)
            for slot in getattr(type(obj), "__slots__", ()):
                visit(getattr(obj, slot, None))

    for root in roots:
        visit(root)


class RecordingTable:
    """Recordings by key, the least recently used dropped beyond MAX_RECORDINGS, and the
    calls so far of keys traced before their recording (``record_at``, :func:`call_recorded`)."""

    def __init__(self) -> None:
        #: key -> (frozen function, or None where recording failed; the pinned arguments).
        self.entries: dict[Hashable, tuple[Any, dict]] = {}
        #: key -> plain calls so far, for keys not recorded yet (the most recent MAX_PENDING).
        self.calls: dict[Hashable, int] = {}

    def functions(self) -> list:
        """The frozen functions held (recordings that failed left out)."""
        return [frozen for frozen, _ in self.entries.values() if frozen is not None]


class Recordings:
    """The recording tables of one owner (a scene), by purpose, for the owner's current
    revision.

    The owner holds its own (as an attribute, :func:`recordings_of`): a frozen function
    keeps the arguments of its calls, the owner among them, so tables outside the owner (a
    weak dictionary keyed by it) would keep every recorded owner alive; held by the owner,
    they form a cycle that the garbage collector frees with the owner. :func:`jit_state`
    does not walk into them.
    """

    def __init__(self) -> None:
        self._revision: int | None = None
        self._tables: dict[str, RecordingTable] = {}

    def table(self, purpose: str, revision: int) -> RecordingTable:
        """The table for ``purpose`` at ``revision``: all tables are emptied when the
        revision differs from the last call's."""
        if revision != self._revision:
            self._revision, self._tables = revision, {}
        return self._tables.setdefault(purpose, RecordingTable())


def recordings_of(owner: Any, purpose: str) -> RecordingTable:
    """The recordings table of ``owner`` (an object with a ``revision`` number and a
    :class:`Recordings` as ``recordings``) for ``purpose`` at its current revision."""
    return owner.recordings.table(purpose, owner.revision)


def call_recorded(table: RecordingTable, key: Hashable, function: Callable, args: tuple,
                  state_fn: Callable, pinned: tuple[int, ...] = (),
                  on_failure: Callable[[], None] | None = None, record_at: int = 1) -> Any:
    """``function(*args)``, replayed from the recording for ``key`` in ``table``.

    The ``record_at``-th call of a key records it (the calls before it are traced plainly):
    where keys may not repeat (a query per batch width), only keys that do pay for a
    recording, which costs more than tracing. ``function`` reads Dr.Jit arrays only from
    its arguments and from ``state_fn(*args)`` (a replay reads no others), and Python
    values only from what ``key`` determines. The arguments at the positions ``pinned``
    are objects that ``key`` determines but that callers build anew (a camera): a frozen
    function compares such arguments by identity, so the recording call's own are passed
    again. A recording that fails calls ``on_failure`` (to restore what the attempt
    changed), and the key is traced plainly from then on.
    """
    entries = table.entries
    if key in entries:
        entries[key] = entries.pop(key)  # most recently used last
    else:
        calls = table.calls.pop(key, 0) + 1
        if calls < record_at:
            if len(table.calls) >= MAX_PENDING:
                del table.calls[next(iter(table.calls))]
            table.calls[key] = calls
            return function(*args)
        if len(entries) >= MAX_RECORDINGS:
            del entries[next(iter(entries))]
        backend = dr.JitBackend.CUDA if BACKEND_NAME == "cuda" else dr.JitBackend.LLVM
        entries[key] = (dr.freeze(function, backend=backend, state_fn=state_fn),
                        {k: args[k] for k in pinned})
    frozen, recorded = entries[key]
    if frozen is not None:
        call_args = tuple(recorded.get(k, arg) for k, arg in enumerate(args))
        # No garbage collection while recording: freeing a Dr.Jit array that wraps NumPy
        # memory enqueues a host callback, and Dr.Jit aborts a recording that meets one
        # (seen in the test suite: a collection of earlier garbage in the middle of a render).
        collecting = gc.isenabled()
        gc.disable()
        try:
            return frozen(*call_args)
        except RuntimeError as err:
            _raise_interrupt(err)
            # The recording failed (and left nothing behind): run plainly from now on.
            entries[key] = (None, {})
            if on_failure is not None:
                on_failure()
        finally:
            if collecting:
                gc.enable()
    return function(*args)


def _raise_interrupt(err: RuntimeError) -> None:
    """Re-raise the Ctrl-C (or exit) that ``err`` wraps: ``dr.freeze`` reports anything raised
    while it records, KeyboardInterrupt included, as a RuntimeError caused by it, which
    must stop the program rather than count as a failed recording."""
    cause = err.__cause__
    if cause is not None and not isinstance(cause, Exception):
        raise cause from None
