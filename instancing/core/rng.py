"""Random numbers per sample, reproducible whatever the batching: an independent stream
per sample (:func:`sample_streams`, an :class:`IndependentSampler`), or numbers stratified
over a pixel's samples (:class:`PixelSampler`, for cameras whose sampler stratifies;
boundary samples always take streams). Both have the same methods, so an integrator draws
from either without asking which.

Each independent sample gets its own PCG32 stream (O'Neill 2014), chosen by its global sample
index and the render seed, so a sample's random numbers do not depend on how samples are
grouped into passes or lanes. (Dr.Jit's ``PCG32(size, initstate, initseq)`` derives each
lane's stream from its lane position as well, which would tie the numbers to the
batching.) The index and seed are scrambled by the Tiny Encryption Algorithm first
(:func:`tea`): PCG32 streams that share their state and differ only in consecutive
increments are correlated (the samples of a pixel, which have consecutive indices, varied
across renders with 0.90x the variance that independent samples give; 1.03x scrambled).
"""

from __future__ import annotations

import functools
import math

from .backend import Float, UInt32, dr, jit

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


def sample_streams(sample: UInt32, seed: UInt32) -> "IndependentSampler":
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
    return IndependentSampler(rng)


class IndependentSampler:
    """Independent random numbers: a PCG32 stream per lane (:func:`sample_streams`), with
    the methods of :class:`PixelSampler`, so that the integrators draw from either alike.
    The stream is the only state (it rides through loops as a Dr.Jit structure)."""

    DRJIT_STRUCT = {"stream": jit.PCG32}

    def __init__(self, stream: "jit.PCG32 | None" = None):
        self.stream = jit.PCG32() if stream is None else stream

    def next_uint32(self) -> UInt32:
        return self.stream.next_uint32()

    def next_float32(self) -> Float:
        return self.stream.next_float32()

    def next_pair(self) -> tuple[Float, Float]:
        """Two independent numbers in [0, 1)."""
        return self.stream.next_float32(), self.stream.next_float32()

    def next_choice_and_pair(self, count: int) -> tuple[UInt32, tuple[Float, Float]]:
        """One of ``count`` choices, uniformly, and a pair of numbers: three independent
        numbers."""
        choice = UInt32(dr.minimum(dr.floor(self.stream.next_float32() * count), count - 1))
        return choice, self.next_pair()

    def take_state(self, drawn: "IndependentSampler") -> None:
        """Continue where ``drawn`` (what a branch or loop made of this sampler) stands."""
        self.stream.state, self.stream.inc = drawn.stream.state, drawn.stream.inc

    def copy(self) -> "IndependentSampler":
        """A sampler in the same state (that draws the same numbers)."""
        copy = jit.PCG32(size=dr.width(self.stream.state))
        copy.state, copy.inc = type(self.stream.state)(self.stream.state), type(self.stream.inc)(self.stream.inc)
        return IndependentSampler(copy)


def reverse_bits(x: UInt32) -> UInt32:
    """The 32 bits of ``x`` in reverse order (five swaps of ever smaller halves)."""
    x = ((x >> 1) & 0x55555555) | ((x & 0x55555555) << 1)
    x = ((x >> 2) & 0x33333333) | ((x & 0x33333333) << 2)
    x = ((x >> 4) & 0x0F0F0F0F) | ((x & 0x0F0F0F0F) << 4)
    x = ((x >> 8) & 0x00FF00FF) | ((x & 0x00FF00FF) << 8)
    return (x >> 16) | (x << 16)


def laine_karras(x: UInt32, seed: UInt32) -> UInt32:
    """A hash of ``x`` under ``seed`` in which each bit changes with the bits below it only
    (Laine and Karras 2011, with Burley's constants, "Practical Hash-based Owen
    Scrambling", 2020): on reversed bits, an Owen scramble."""
    x = x ^ (x * 0x3D20ADEA)
    x = x + seed
    x = x * ((seed >> 16) | 1)
    x = x ^ (x * 0x05526C56)
    return x ^ (x * 0x53A22864)


def owen_scramble(x: UInt32, seed: UInt32) -> UInt32:
    """The nested uniform (Owen) scramble of the 32-bit fraction ``x``: each bit flipped by a
    hash of the bits above it."""
    return reverse_bits(laine_karras(reverse_bits(x), seed))


def _sobol_second(i: UInt32) -> UInt32:
    """The second dimension of the Sobol sequence at index ``i`` (32-bit fraction): the
    direction numbers of the polynomial x + 1, one per bit of the index."""
    v, out = 1 << 31, UInt32(0)
    for bit in range(32):
        out = out ^ dr.select((i & (1 << bit)) != 0, UInt32(v), UInt32(0))
        v ^= v >> 1
    return out


def _permutation_hash(x: UInt32, seed: UInt32, mask: UInt32) -> UInt32:
    """A bijection of [0, mask] (mask + 1 a power of two) chosen by ``seed``: xors with the
    seed, multiplications by odd constants and xors of the masked bits shifted down, each
    a bijection of the low bits (Kensler, "Correlated Multi-Jittered Sampling", 2013, with
    his constants)."""
    x = (x ^ seed) * 0xE170893D
    x = x ^ (seed >> 16)
    x = x ^ ((x & mask) >> 4)
    x = (x ^ (seed >> 8)) * 0x0929EB3F
    x = x ^ (seed >> 23)
    x = (x ^ ((x & mask) >> 1)) * ((seed >> 27) | 1)
    x = x * 0x6935FA69
    x = (x ^ ((x & mask) >> 11)) * 0x74DCB303
    x = (x ^ ((x & mask) >> 2)) * 0x9E501CC3
    x = (x ^ ((x & mask) >> 2)) * 0xC860A3DF
    x = x & mask
    return x ^ (x >> 5)


def permuted(i: UInt32, count: int, seed: UInt32) -> UInt32:
    """Element ``i`` of a random permutation of [0, count) chosen by ``seed``: two rounds of
    :func:`_permutation_hash` on the next power of two (one round pairs the strata of two
    draws visibly unevenly: the samples below 1/2 in both vary 1.6x as much as under a
    uniformly random pairing of 16), repeated while it falls past ``count`` (cycle walking:
    the first element of i's cycle inside the range), then rotated by the seed."""
    mask = dr.opaque(UInt32, (1 << (count - 1).bit_length()) - 1)
    second = (seed ^ (seed >> 16)) * 0x7FEB352D
    second = second ^ (second >> 15)

    def permute(x: UInt32) -> UInt32:
        return _permutation_hash(_permutation_hash(x, seed, mask), second, mask)

    x = permute(i)
    if count & (count - 1):
        n = dr.opaque(UInt32, count)
        x = dr.while_loop((x,), lambda x: x >= n, lambda x: (permute(x),))[0]
        return (x + seed % n) % n
    return (x + seed) & mask


class PixelSampler:
    """The random numbers of a pixel's ``count`` samples, stratified over them (a padded,
    Owen-scrambled Sobol sequence): draw k of sample i of a pixel is the point of a base-2
    (0, 2)-sequence at index pi_k(i), pi_k a random permutation of the pixel's samples
    (:func:`permuted`), the point Owen-scrambled (Burley, "Practical Hash-based Owen
    Scrambling", 2020); pi_k and the scramble are keyed by the pixel and the draw, so the
    draws of a sample are independent of each other. Over a pixel's 2^m samples each draw
    hits each of 2^m equal intervals once, and a pair drawn by :meth:`next_pair` each of
    the elementary rectangles of area 2^-m; any sample's numbers are uniform, so every
    estimator stays unbiased. The draw counter is the only state that changes (it rides
    through loops as a Dr.Jit structure).

    Without :attr:`jitter` (Mitsuba's stratified samplers' ``jitter`` false), draw k of
    sample i is the centre of stratum pi_k(i) of the pixel's ``count`` (a pair's: of a cell
    of the :attr:`grid`): one sample is at the pixel's centre, 16 at the centres of a 4 x 4
    grid, as Mitsuba's ``stratified`` places them; an estimator of fixed points, no longer
    unbiased."""

    DRJIT_STRUCT = {"index": UInt32, "key": UInt32, "draw": UInt32}
    #: The pixel's samples: a constant of the class (:meth:`of`), not a traced value, which
    #: survives Dr.Jit's loops and branches (they make new instances of the class).
    count = 1
    #: Whether each draw lies at random within its stratum (else at its centre, as
    #: Mitsuba's stratified samplers without ``jitter``): a constant of the class too.
    jitter = True

    def __init__(self, index: UInt32 | None = None, key: UInt32 | None = None, draw: UInt32 | None = None):
        self.index = UInt32(0) if index is None else index
        self.key = UInt32(0) if key is None else key
        self.draw = UInt32(0) if draw is None else draw

    @staticmethod
    @functools.cache
    def of(count: int, jitter: bool = True) -> type["PixelSampler"]:
        """The class of the samplers of pixels with ``count`` samples (``jitter``: see
        :attr:`jitter`)."""
        return type(f"PixelSampler{count}{'' if jitter else 'Centred'}", (PixelSampler,),
                    {"count": count, "jitter": jitter})

    @property
    def grid(self) -> tuple[int, int]:
        """The columns and rows of the cells that centred pairs (without :attr:`jitter`) lie
        at the centres of, at least as many as the pixel's samples: 2^ceil(m/2) x
        2^floor(m/2) for 2^m samples, else the nearest to a square (n x n for n^2, as
        Mitsuba's stratified sampler)."""
        count = self.count
        if count & (count - 1) == 0:
            m = count.bit_length() - 1
            return 1 << (m + 1) // 2, 1 << m // 2
        columns = math.isqrt(count - 1) + 1
        return columns, -(-count // columns)

    def _next_point(self) -> tuple[UInt32, UInt32, UInt32]:
        """The next draw's permuted index and the keys of its two scrambles; the draw
        counter moved on."""
        shuffle, scramble = tea(self.key, self.draw)
        self.draw = self.draw + 1
        return permuted(self.index, self.count, shuffle), scramble, laine_karras(scramble, shuffle)

    def next_uint32(self) -> UInt32:
        """32 random bits (a fraction of 2^32), stratified over the pixel's samples."""
        i, scramble, _ = self._next_point()
        if not self.jitter:
            return _centre(i, self.count)
        return owen_scramble(reverse_bits(i), scramble)

    def next_float32(self) -> Float:
        """One number in [0, 1), stratified over the pixel's samples."""
        return _fraction(self.next_uint32())

    def _next_pair_bits(self) -> tuple[UInt32, UInt32]:
        """Two 32-bit fractions jointly stratified over the pixel's samples (the first two
        Sobol dimensions at one permuted index, each scrambled by its own key); without
        :attr:`jitter`, the centre of the permuted index's cell of the :attr:`grid`."""
        i, scramble, second = self._next_point()
        if not self.jitter:
            columns, rows = self.grid
            row = i // columns
            return _centre(i - row * columns, columns), _centre(row, rows)
        return owen_scramble(reverse_bits(i), scramble), owen_scramble(_sobol_second(i), second)

    def next_pair(self) -> tuple[Float, Float]:
        """Two numbers in [0, 1)^2, jointly stratified over the pixel's samples."""
        x, y = self._next_pair_bits()
        return _fraction(x), _fraction(y)

    def next_choice_and_pair(self, count: int) -> tuple[UInt32, tuple[Float, Float]]:
        """One of ``count`` choices and a pair of numbers in [0, 1)^2 from one stratified
        pair: the first number picks (floor(x count)) and what is left of it, stretched back
        to [0, 1), is the pair's first, so that the samples that pick one choice keep their
        pairs stratified (as Mitsuba reuses the sample that picks an emitter)."""
        x, y = self._next_pair_bits()
        scaled = jit.UInt64(x) * count
        return UInt32(scaled >> 32), (_fraction(UInt32(scaled & 0xFFFFFFFF)), _fraction(y))

    def take_state(self, drawn: "PixelSampler") -> None:
        """Continue where ``drawn`` (what a branch or loop made of this sampler) stands."""
        self.draw = drawn.draw

    def copy(self) -> "PixelSampler":
        """A sampler in the same state (that draws the same numbers)."""
        return type(self)(UInt32(self.index), UInt32(self.key), UInt32(self.draw))


def _centre(i: UInt32, count: int) -> UInt32:
    """The centre of stratum ``i`` of ``count`` equal ones of [0, 1), (i + 1/2) / count, as
    a 32-bit fraction."""
    return UInt32((jit.UInt64(i) * 2 + 1) * (1 << 31) // count)


def _fraction(bits: UInt32) -> Float:
    """The top 24 bits of a 32-bit fraction as a float32 in [0, 1)."""
    return Float(bits >> 8) * (1.0 / (1 << 24))


def pixel_samplers(pixel: UInt32, index: UInt32, count: int, seed: UInt32,
                   jitter: bool = True) -> PixelSampler:
    """A :class:`PixelSampler` per lane for sample ``index`` of the ``count`` of ``pixel``
    (the render's global pixel number), keyed by (pixel, seed) through :func:`tea`;
    ``jitter``: :attr:`PixelSampler.jitter`."""
    key, _ = tea(UInt32(pixel), UInt32(seed))
    return PixelSampler.of(count, jitter)(UInt32(index), key, dr.zeros(UInt32, dr.width(index)))
