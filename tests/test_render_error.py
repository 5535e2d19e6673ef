"""The render benchmark's equal-error estimators on synthetic error curves with closed forms."""

import math

import pytest

from benchmarks.render_error import model_times, time_at_error, time_at_spp, variance_per_sample

SPP = [1, 2, 4, 8, 16, 32, 64, 128, 256]


def curve(variance: float, ref_noise: float, seconds_per_spp: float, overhead: float = 0.0) -> dict:
    """An unbiased renderer's expected error against a reference of noise ``ref_noise``."""
    return {"spp": list(SPP),
            "time_s": [overhead + seconds_per_spp * n for n in SPP],
            "error": [math.sqrt(ref_noise ** 2 + variance / n) for n in SPP]}


def test_variance_per_sample_recovers_the_variance_of_an_exact_curve():
    assert variance_per_sample(curve(3.0, 0.05, 1e-3), 0.05) == pytest.approx(3.0, rel=1e-12)
    assert variance_per_sample(curve(3.0, 0.0, 1e-3), 0.0) == pytest.approx(3.0, rel=1e-12)


def test_variance_per_sample_leaves_out_spp_at_the_reference_noise():
    # V / n < ref_noise^2 from n = 8 on: only spp 1, 2, 4 qualify, each giving V exactly.
    c = curve(0.5, 0.3, 1e-3)
    c["error"][-1] = 0.0  # a value that would give a negative estimate were it used
    assert variance_per_sample(c, 0.3) == pytest.approx(0.5, rel=1e-12)
    assert math.isnan(variance_per_sample(curve(0.01, 1.0, 1e-3), 1.0))


def test_one_firefly_moves_the_first_crossing_but_not_the_model():
    ours, theirs = curve(1.0, 0.01, 1e-3), curve(1.0, 0.01, 2e-3)  # equal variance, ours twice as fast
    target = theirs["error"][SPP.index(64)]
    exact = time_at_spp(theirs, 64) / time_at_spp(ours, 64)
    assert exact == pytest.approx(2.0)
    assert time_at_error(theirs, target) / time_at_error(ours, target) == pytest.approx(2.0)
    theirs["error"][SPP.index(16)] = target * 0.9  # a lucky render set without its fireflies
    assert time_at_error(theirs, target) / time_at_error(ours, target) < 0.5
    t_ours, t_mi, spp_ours = model_times({"ours": ours, "mitsuba": theirs}, 0.01, 64)
    assert spp_ours == pytest.approx(64.0)
    assert t_mi / t_ours == pytest.approx(2.0)


def test_model_times_at_unequal_variance():
    # Ours has a quarter of Mitsuba's variance per sample: 16 spp match Mitsuba's 64.
    ours, theirs = curve(0.25, 0.02, 4e-3, 0.01), curve(1.0, 0.02, 1e-3, 0.01)
    t_ours, t_mi, spp_ours = model_times({"ours": ours, "mitsuba": theirs}, 0.02, 64)
    assert spp_ours == pytest.approx(16.0)
    assert t_ours == pytest.approx(0.01 + 4e-3 * 16)
    assert t_mi == pytest.approx(0.01 + 1e-3 * 64)


def test_time_at_spp_interpolates_clamps_below_and_refuses_above():
    c = curve(1.0, 0.0, 1e-3)
    assert time_at_spp(c, 16) == pytest.approx(16e-3)
    assert time_at_spp(c, 24) == pytest.approx(24e-3)  # proportional: a line in log-log
    d = curve(1.0, 0.0, 1e-3, 0.05)
    midpoint = time_at_spp(d, math.sqrt(16 * 32))
    assert midpoint == pytest.approx(math.sqrt(d["time_s"][4] * d["time_s"][5]))
    assert time_at_spp(c, 0.25) == pytest.approx(1e-3)  # a render takes at least one spp
    assert math.isnan(time_at_spp(c, 512))
