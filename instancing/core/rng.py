"""Independent random streams per sample, reproducible whatever the batching.

Each camera sample gets its own PCG32 stream (O'Neill 2014) selected by its
global sample index and seeded by the render seed, so a sample's random
numbers do not depend on how samples are grouped into passes or lanes.
(Dr.Jit's ``PCG32(size, initstate, initseq)`` derives each lane's stream from
its lane position as well, which would tie the numbers to the batching.)
"""

from __future__ import annotations

from .backend import UInt32, dr, jit


def sample_streams(sample: UInt32, seed: UInt32) -> "jit.PCG32":
    """One PCG32 generator per lane: stream ``sample[i]``, seeded by ``seed``.

    Follows PCG32's own seeding (state 0, increment 2 * stream + 1, one step,
    add the seed, one step).
    """
    width = dr.width(sample)
    rng = jit.PCG32(size=width)
    rng.state = dr.zeros(jit.UInt64, width)
    rng.inc = (jit.UInt64(sample) << 1) | 1
    rng.next_uint32()
    rng.state += jit.UInt64(seed)
    rng.next_uint32()
    return rng
