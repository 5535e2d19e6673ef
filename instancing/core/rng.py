"""Independent random streams per sample, reproducible whatever the batching.

Each camera sample gets its own PCG32 stream (O'Neill 2014), chosen by its global sample
index and the render seed, so a sample's random numbers do not depend on how samples are
grouped into passes or lanes. (Dr.Jit's ``PCG32(size, initstate, initseq)`` derives each
lane's stream from its lane position as well, which would tie the numbers to the
batching.) The index and seed are scrambled by the Tiny Encryption Algorithm first
(:func:`tea`): PCG32 streams that share their state and differ only in consecutive
increments are correlated (the samples of a pixel, which have consecutive indices, varied
across renders with 0.90x the variance that independent samples give; 1.03x scrambled).
"""

from __future__ import annotations

from .backend import UInt32, dr, jit

#: TEA's round constant (2^32 / golden ratio) and the key of its scrambling of (seed, index):
#: those of Zafar, Olano and Curtis, "GPU Random Numbers via the Tiny Encryption Algorithm"
#: (2010).
TEA_DELTA = 0x9E3779B9
TEA_KEY = (0xA341316C, 0xC8013EA4, 0xAD90777D, 0x7E95761E)
#: Feistel rounds of the scrambling (4 pass the statistical tests of Zafar et al.).
TEA_ROUNDS = 4


def tea(v0: UInt32, v1: UInt32, rounds: int = TEA_ROUNDS) -> tuple[UInt32, UInt32]:
    """The Tiny Encryption Algorithm (Wheeler and Needham 1994) of the 64-bit block (v0, v1)
    under :data:`TEA_KEY`: two 32-bit words that change unpredictably with every bit of
    either input."""
    # (No in-place operators: the inputs may be the caller's arrays.)
    k0, k1, k2, k3 = TEA_KEY
    for r in range(1, rounds + 1):
        total = (TEA_DELTA * r) & 0xFFFFFFFF
        v0 = v0 + (((v1 << 4) + k0) ^ (v1 + total) ^ ((v1 >> 5) + k1))
        v1 = v1 + (((v0 << 4) + k2) ^ (v0 + total) ^ ((v0 >> 5) + k3))
    return UInt32(v0), UInt32(v1)


def sample_streams(sample: UInt32, seed: UInt32) -> "jit.PCG32":
    """One PCG32 generator per lane: the state and stream that :func:`tea` makes of
    (``sample[i]``, ``seed``).

    Follows PCG32's own seeding (state 0, increment 2 * stream + 1, one step, add the
    initial state, one step).
    """
    width = dr.width(sample)
    # (Index first: Mitsuba's independent sampler scrambles (seed, index) with the same
    # cipher, and the same numbers would make renders compared with its at equal seeds
    # share their noise.)
    state, stream = tea(UInt32(sample), UInt32(seed))
    rng = jit.PCG32(size=width)
    rng.state = dr.zeros(jit.UInt64, width)
    rng.inc = (jit.UInt64(stream) << 1) | 1
    rng.next_uint32()
    rng.state += jit.UInt64(state)
    rng.next_uint32()
    return rng
