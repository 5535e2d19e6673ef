"""The ids of a scene's instances, without a string per instance.

A scene entry is one named instance (``"ball"``) or a batch of N instances
from an (N, 4, 4) array, named ``"tree[0]" .. "tree[N-1]"``; an instance
without an id is named by its index (``"17"``). A million instances from one
``.npy`` file would cost ~66 bytes each as a list of strings; here a batch is
stored as its prefix and count and a run of unnamed instances as its count,
their names are made when asked for, and a lookup by name parses the index
back. Read it like a
list of strings: ``ids[i]``, ``len(ids)``, ``ids.index(name)``, ``name in
ids``, iteration, and ``==`` against any sequence of strings.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator, Sequence
from typing import Any

from ..core.errors import SceneError


class InstanceIds(Sequence):
    """Instance ids in scene order: single names and (prefix, count) batches."""

    def __init__(self) -> None:
        # Per entry: its first instance index, its name (batch prefix; None for a run of
        # instances named by their index), and its size (None for a single instance).
        self._starts: list[int] = []
        self._names: list[str | None] = []
        self._batch: list[int | None] = []
        self._count = 0
        # Lookups by name: single ids -> instance index, batch prefixes -> entry index,
        # and for single ids of the form 'p[k]' the smallest k per prefix p, so that a
        # batch added later can tell whether one of its names is taken.
        self._single: dict[str, int] = {}
        self._prefix: dict[str, int] = {}
        self._bracketed: dict[str, int] = {}
        # Single ids that are instance indices ('17'), sorted: the names a run may not take.
        self._numbers: list[int] = []

    def add(self, name: str, count: int | None = None) -> None:
        """Append one instance named ``name`` or, with ``count``, a batch ``name[0..count-1]``.

        Raises:
            SceneError: a name that is already taken.
        """
        if count is None:
            taken = (name in self._single or self._in_batch(name) is not None
                     or self._in_run(name) is not None)
            if not taken:
                self._single[name] = self._count
                parsed = _split_batch_name(name)
                if parsed is not None:
                    prefix, k = parsed
                    self._bracketed[prefix] = min(k, self._bracketed.get(prefix, k))
                elif _is_index(name):
                    bisect.insort(self._numbers, int(name))
            size = 1
        else:
            clash = 0 if name in self._prefix else self._bracketed.get(name, count)
            taken = clash < count
            if not taken:
                self._prefix[name] = len(self._names)
            size = count
        if taken:
            shown = name if count is None else f"{name}[{clash}]"
            raise SceneError(f"instance id {shown!r} is used twice; ids must be unique")
        self._starts.append(self._count)
        self._names.append(name)
        self._batch.append(count)
        self._count += size

    def add_unnamed(self, count: int) -> None:
        """Append ``count`` instances without ids: each is named by its own index.

        Raises:
            SceneError: one of those names is already a single id.
        """
        end = self._count + count
        clash = bisect.bisect_left(self._numbers, self._count)
        if clash < len(self._numbers) and self._numbers[clash] < end:
            raise SceneError(f"instance id {str(self._numbers[clash])!r} is used twice; ids "
                             "must be unique (an instance without an id is named by its index)")
        if self._names and self._names[-1] is None:
            self._batch[-1] += count
        else:
            self._starts.append(self._count)
            self._names.append(None)
            self._batch.append(count)
        self._count = end

    def _in_run(self, name: str) -> int | None:
        """Instance index of ``name`` when it names an instance without an id, else None."""
        if not _is_index(name) or int(name) >= self._count:
            return None
        k = int(name)
        return k if self._names[bisect.bisect_right(self._starts, k) - 1] is None else None

    def _in_batch(self, name: str) -> int | None:
        """Instance index of ``name`` when it is a batch member, else None."""
        parsed = _split_batch_name(name)
        if parsed is None or parsed[0] not in self._prefix:
            return None
        entry = self._prefix[parsed[0]]
        return self._starts[entry] + parsed[1] if parsed[1] < self._batch[entry] else None

    def batches(self) -> list[tuple[str, int, int]]:
        """The batches: (prefix, index of the first instance, count) each, in scene order."""
        return [(name, start, count) for name, start, count in
                zip(self._names, self._starts, self._batch) if name is not None and count is not None]

    # -- the sequence interface ----------------------------------------------------------------

    def __len__(self) -> int:
        return self._count

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self._count))]
        k = int(i)
        if k < 0:
            k += self._count
        if not 0 <= k < self._count:
            raise IndexError(f"instance index {i} out of range for {self._count} instances")
        entry = bisect.bisect_right(self._starts, k) - 1
        name = self._names[entry]
        if name is None:
            return str(k)
        return name if self._batch[entry] is None else f"{name}[{k - self._starts[entry]}]"

    def __iter__(self) -> Iterator[str]:
        for name, start, count in zip(self._names, self._starts, self._batch):
            if name is None:
                yield from map(str, range(start, start + count))
            elif count is None:
                yield name
            else:
                yield from (f"{name}[{k}]" for k in range(count))

    def index(self, name: Any, start: int = 0, stop: int | None = None) -> int:
        """Instance index of ``name`` (ValueError when no instance has it)."""
        found = self._single.get(name) if isinstance(name, str) else None
        if found is None and isinstance(name, str):
            found = self._in_batch(name)
            found = self._in_run(name) if found is None else found
        stop = self._count if stop is None else stop
        if found is None or not start <= found < stop:
            raise ValueError(f"{name!r} is not an instance id")
        return found

    def __contains__(self, name: Any) -> bool:
        return isinstance(name, str) and (name in self._single or self._in_batch(name) is not None
                                          or self._in_run(name) is not None)

    def __eq__(self, other: Any) -> bool:
        if isinstance(other, InstanceIds):
            if (self._names, self._batch) == (other._names, other._batch):
                return True
        elif not isinstance(other, Sequence) or isinstance(other, str):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other))

    def __repr__(self) -> str:
        shown = [repr(n) if c is None else f"'{s}..{s + c - 1}'" if n is None else f"'{n}[0..{c - 1}]'"
                 for n, s, c in zip(self._names[:4], self._starts[:4], self._batch[:4])]
        more = ", ..." if len(self._names) > 4 else ""
        return f"InstanceIds([{', '.join(shown)}{more}], {self._count} instances)"


def _is_index(name: str) -> bool:
    """Whether ``name`` is how an instance index is written ('17', not '017' or '+17')."""
    return name.isascii() and name.isdigit() and (name == "0" or name[0] != "0")


def _split_batch_name(name: str) -> tuple[str, int] | None:
    """('p', k) for a name 'p[k]' that a batch would generate (k without leading zeros), else None."""
    if not name.endswith("]"):
        return None
    cut = name.rfind("[")
    digits = name[cut + 1:-1]
    if cut < 0 or not (digits.isascii() and digits.isdigit()) or str(int(digits)) != digits:
        return None
    return name[:cut], int(digits)
