"""Random streams per sample (instancing.core.rng): the scrambling against a NumPy
reference, independence of the streams of consecutive samples, and reproducibility
whatever the batching."""

import numpy as np
import pytest

from instancing.core.backend import UInt32, dr
from instancing.core.rng import TEA_DELTA, TEA_KEY, permuted, pixel_samplers, sample_streams, tea


def _tea_reference(v0: np.ndarray, v1: np.ndarray, rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """TEA in NumPy: 64-bit integers reduced modulo 2^32 after every operation."""
    mask = (1 << 32) - 1
    v0, v1, total = v0.astype(np.int64), v1.astype(np.int64), 0
    k0, k1, k2, k3 = TEA_KEY
    for _ in range(rounds):
        total = (total + TEA_DELTA) & mask
        v0 = (v0 + ((((v1 << 4) & mask) + k0) ^ (v1 + total) ^ ((v1 >> 5) + k1))) & mask
        v1 = (v1 + ((((v0 << 4) & mask) + k2) ^ (v0 + total) ^ ((v0 >> 5) + k3))) & mask
    return v0, v1


@pytest.mark.parametrize("rounds", [1, 4, 8])
def test_tea_matches_a_numpy_reference(rounds):
    rng = np.random.default_rng(3)
    v0, v1 = (rng.integers(0, 1 << 32, 4096, dtype=np.uint64).astype(np.uint32) for _ in range(2))
    ours = tea(UInt32(v0), UInt32(v1), rounds)
    expected = _tea_reference(v0, v1, rounds)
    for got, want in zip(ours, expected):
        np.testing.assert_array_equal(np.asarray(got, np.int64), want)


def test_the_streams_of_consecutive_samples_are_independent():
    """The means of 16 consecutive streams' k-th numbers (a pixel's samples) vary as those
    of independent uniform numbers, variance 1 / (12 * 16), within 3 % (the estimate's own
    standard deviation over 2^16 groups: 0.55 %), for each of the first 8 numbers; their
    neighbours are uncorrelated (|r| < 0.005, 5 standard deviations). PCG32 streams that
    differ only in consecutive increments gave 0.72 - 0.99x that variance."""
    n = 1 << 20
    rng = sample_streams(dr.arange(UInt32, n), UInt32(7))
    for k in range(8):
        u = np.asarray(rng.next_float32(), np.float64)
        assert 0 <= u.min() and u.max() < 1
        ratio = u.reshape(-1, 16).mean(axis=1).var() / (1 / 12 / 16)
        assert abs(ratio - 1) < 0.03, (k, ratio)
        assert abs(np.corrcoef(u[:-1], u[1:])[0, 1]) < 0.005, k


def test_a_samples_numbers_depend_on_its_index_and_the_seed_only():
    """Samples 5 .. 10 draw the same numbers in a batch of their own as among 100; another
    seed gives other numbers."""
    alone = sample_streams(dr.arange(UInt32, 6) + 5, UInt32(11))
    among = sample_streams(dr.arange(UInt32, 100), UInt32(11))
    other = sample_streams(dr.arange(UInt32, 6) + 5, UInt32(12))
    for _ in range(3):
        a, b, c = (np.asarray(r.next_uint32()) for r in (alone, among, other))
        np.testing.assert_array_equal(a, b[5:11])
        assert not np.any(a == c)


def _pixel_draws(pixels: int, spp: int, draws: int, pairs: bool = False) -> np.ndarray:
    """(pixels, spp, draws[, 2]) numbers of PixelSampler, pixel-major lanes."""
    lane = dr.arange(UInt32, pixels * spp)
    sampler = pixel_samplers(lane // spp, lane % spp, spp, UInt32(3))
    out = [np.asarray(sampler.next_pair() if pairs else sampler.next_float32(), np.float64)
           for _ in range(draws)]
    shape = (pixels, spp, draws) + ((2,) if pairs else ())
    return np.stack([o.T if pairs else o for o in out], axis=1).reshape(shape)


def test_a_pixels_samples_are_stratified_in_every_draw_and_pair():
    """Over a pixel's 2^m samples, each draw hits each of the 2^m intervals [k, k + 1) / 2^m
    once, and each pair each elementary rectangle of area 2^-m (2^a by 2^(m-a) cells, every
    a): a (0, m, 2)-net, as Owen-scrambled Sobol points are; also with 8 draws in between."""
    for spp in (4, 16, 64):
        single = _pixel_draws(50, spp, 6)
        assert 0 <= single.min() and single.max() < 1
        strata = np.sort(np.floor(single * spp), axis=1)
        np.testing.assert_array_equal(strata, np.broadcast_to(np.arange(spp)[None, :, None], strata.shape))
        pairs = _pixel_draws(50, spp, 3, pairs=True)
        m = spp.bit_length() - 1
        for a in range(m + 1):
            cells = (np.floor(pairs[..., 0] * 2 ** a) * 2 ** (m - a) + np.floor(pairs[..., 1] * 2 ** (m - a)))
            np.testing.assert_array_equal(np.sort(cells, axis=1),
                                          np.broadcast_to(np.arange(spp)[None, :, None], cells.shape))


def test_a_pixel_samplers_numbers_are_uniform_and_their_draws_and_pixels_independent():
    """Each draw is uniform over many pixels (the means and variances of 4 096 pixels x 16
    samples within 5 standard errors of 1/2 and 1/12), draws of one sample and the same draw
    of neighbouring pixels are uncorrelated (|r| within 5 standard deviations of 0), and a
    sample's numbers depend on its pixel, index and the seed only (its pass's other lanes
    change nothing)."""
    draws = _pixel_draws(4096, 16, 8)
    u = draws.reshape(-1, 8)
    n = len(u)
    assert np.all(np.abs(u.mean(axis=0) - 0.5) < 5 * np.sqrt(1 / 12 / n))
    assert np.all(np.abs(u.var(axis=0) - 1 / 12) < 5 * np.sqrt(1 / 180 / n))
    r = np.corrcoef(u.T)
    assert np.abs(r[np.triu_indices(8, 1)]).max() < 5 / np.sqrt(n)
    per_pixel = draws[:, 0, 0]
    assert abs(np.corrcoef(per_pixel[:-1], per_pixel[1:])[0, 1]) < 5 / np.sqrt(4096)
    alone = pixel_samplers(UInt32([7, 7]), UInt32([3, 9]), 16, UInt32(3))
    np.testing.assert_array_equal(np.asarray(alone.next_float32()), draws[7, [3, 9], 0].astype(np.float32))


def test_a_copied_sampler_draws_what_the_original_draws_and_takes_its_state_back():
    """``copy`` (what path replay draws from) gives the numbers the sampler itself then
    draws, for a PixelSampler and an IndependentSampler alike, and ``take_state`` moves a
    sampler on to what a copy of it drew."""
    lane = dr.arange(UInt32, 64)
    for sampler in (pixel_samplers(lane // 16, lane % 16, 16, UInt32(5)), sample_streams(lane, UInt32(5))):
        sampler.next_float32()
        copy = sampler.copy()
        ahead = [np.asarray(copy.next_float32()) for _ in range(3)]
        for expected in ahead:
            np.testing.assert_array_equal(np.asarray(sampler.next_float32()), expected)
        moved = sampler.copy()
        moved.next_float32()
        sampler.take_state(moved)
        np.testing.assert_array_equal(np.asarray(sampler.next_float32()), np.asarray(moved.next_float32()))


def test_a_samples_draws_are_paired_at_random_within_its_pixel():
    """Two draws of a pixel's 16 samples pair their strata at random: the samples below 1/2
    in both number a hypergeometric count (8 of 16 drawn, 8 marked: mean 4, variance
    16/15), its mean square deviation over 4 096 pixels within 10 % of that (4.5 standard
    errors). Shuffling each draw's index by an Owen scramble instead keeps the index's
    nested strata, so that the first digits of two draws all agree or all disagree (a
    count of 0 or 8, 15x the variance; a point light sampled along the rays of a fog scene
    then had 2.4x the variance of independent samples), and one round of the permutation
    hash gives 1.6x."""
    draws = _pixel_draws(4096, 16, 6)
    low = draws < 0.5
    for k in range(1, 6):
        both = np.sum(low[:, :, 0] & low[:, :, k], axis=1)
        assert abs(np.mean((both - 4.0) ** 2) / (16 / 15) - 1) < 0.1, k


@pytest.mark.parametrize("count", [1, 2, 3, 12, 49, 64, 121])
def test_permuted_is_a_permutation_of_the_samples_for_every_seed(count):
    """Whatever the seed, ``permuted`` maps [0, count) onto itself one to one (by the hash on
    the next power of two and cycle walking where count is none), and each sample goes
    to each position about equally often over 2 000 seeds (chi-square of the counts below
    its 0.999 quantile)."""
    seeds = 2000
    lane = dr.arange(UInt32, count * seeds)
    out = np.asarray(permuted(lane % count, count, (lane // count) * 7919 + 12345)).reshape(seeds, count)
    np.testing.assert_array_equal(np.sort(out, axis=1), np.broadcast_to(np.arange(count), out.shape))
    if count > 1:
        cells = np.zeros((count, count))
        np.add.at(cells, (np.broadcast_to(np.arange(count), out.shape), out), 1)
        expected = seeds / count
        chi2 = ((cells[0] - expected) ** 2 / expected).sum()
        assert chi2 < {2: 10.8, 3: 13.8, 12: 31.3, 49: 84.0, 64: 103.4, 121: 173.6}[count], chi2


def test_a_choice_and_its_pair_come_from_one_stratified_pair():
    """``next_choice_and_pair`` over a pixel's 16 samples, of 2 and 4 choices: each choice is
    taken by 16 / count samples, whose pairs fall once into each of 16 / count intervals of
    either number (the elementary intervals of the pixel's net, stretched); a PCG32 stream
    (an IndependentSampler) picks with one number and draws the pair from the next two."""
    lane = dr.arange(UInt32, 1024 * 16)
    for count in (2, 4):
        choice, (x, y) = pixel_samplers(lane // 16, lane % 16, 16, UInt32(3)).next_choice_and_pair(count)
        choice, x, y = (np.asarray(v).reshape(1024, 16) for v in (choice, x, y))
        taken = 16 // count
        for c in range(count):
            mine = choice == c
            np.testing.assert_array_equal(mine.sum(axis=1), taken)
            for values in (x, y):
                strata = np.sort(np.floor(values[mine] * taken).reshape(1024, taken), axis=1)
                np.testing.assert_array_equal(strata, np.broadcast_to(np.arange(taken), strata.shape))
    stream, alone = sample_streams(lane, UInt32(3)), sample_streams(lane, UInt32(3))
    choice, (x, y) = stream.next_choice_and_pair(3)
    u = [np.asarray(alone.next_float32()) for _ in range(3)]
    np.testing.assert_array_equal(np.asarray(choice), np.minimum(np.floor(u[0] * 3), 2).astype(np.uint32))
    np.testing.assert_array_equal(np.asarray(x), u[1])
    np.testing.assert_array_equal(np.asarray(y), u[2])


@pytest.mark.parametrize("count, grid", [(1, (1, 1)), (4, (2, 2)), (8, (4, 2)), (9, (3, 3)), (12, (4, 3)),
                                         (16, (4, 4)), (5, (3, 2))])
def test_centred_samples_sit_at_the_centres_of_their_strata(count, grid):
    """Without jitter, over each pixel's samples every single draw takes each of the values
    (k + 1/2) / count once, and every pair the centres of distinct cells of a columns x rows
    grid (2^ceil(m/2) x 2^floor(m/2) for 2^m samples, n x n for n^2, else near-square), in
    an order that differs between pixels."""
    pixels = 6
    lane = dr.arange(UInt32, pixels * count)
    sampler = pixel_samplers(lane // count, lane % count, count, UInt32(11), jitter=False)
    assert sampler.grid == grid
    columns, rows = grid
    orders = []
    for _ in range(2):
        single = np.asarray(sampler.next_float32(), np.float64).reshape(pixels, count)
        x, y = (np.asarray(v, np.float64).reshape(pixels, count) for v in sampler.next_pair())
        expected = (np.arange(count) + 0.5) / count
        for p in range(pixels):
            np.testing.assert_allclose(np.sort(single[p]), expected, rtol=0, atol=1e-7)
            cells = np.round(x[p] * columns - 0.5) + columns * np.round(y[p] * rows - 0.5)
            np.testing.assert_allclose(x[p] * columns % 1, 0.5, atol=1e-6)
            np.testing.assert_allclose(y[p] * rows % 1, 0.5, atol=1e-6)
            assert len(set(cells)) == count and cells.min() >= 0 and cells.max() < columns * rows
        orders.append(np.argsort(single, axis=1))
    if count > 2:
        assert len({tuple(o) for o in orders[0]}) > 1
