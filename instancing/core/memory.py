"""Memory estimates checked before large allocations.

A scene of 1e8 instances or a 100 000 x 100 000 film would exhaust the machine part-way
(or overflow Dr.Jit's 32-bit array sizes); :func:`require_memory` refuses such work up
front with the estimate, so that nothing is half-built or swapped to a standstill.
"""

from __future__ import annotations

import os

from .errors import ResourceError

#: Peak bytes per instance while a scene is parsed and built: the float64 matrices and
#: their inverses, the float32 instance table, world boxes and the acceleration
#: structure's build arrays (benchmarks/scale.py: peak 997 B per instance at 1e6).
PEAK_BYTES_PER_INSTANCE = 1000
#: Largest Dr.Jit array (entries): sizes are 32-bit.
MAX_ARRAY_ENTRIES = (1 << 32) - 1


def physical_memory() -> int:
    """Bytes of physical memory of this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _size(n: float) -> str:
    return f"{n / 2 ** 30:.3g} GiB" if n >= 2 ** 30 else f"{n / 2 ** 20:.3g} MiB"


def require_memory(estimate: float, what: str) -> None:
    """Raise :class:`ResourceError` if ``estimate`` bytes for ``what`` exceed the
    machine's physical memory."""
    total = physical_memory()
    if estimate > total:
        raise ResourceError(f"{what} would need about {_size(estimate)} of memory; this "
                            f"machine has {_size(total)}")


def require_entries(entries: int, what: str) -> None:
    """Raise :class:`ResourceError` if one array of ``entries`` would overflow Dr.Jit's
    32-bit sizes."""
    if entries > MAX_ARRAY_ENTRIES:
        raise ResourceError(f"{what} would need arrays of {entries:.3g} entries; Dr.Jit "
                            f"arrays hold at most 2^32 - 1")
