"""``sparsecomm.stats.bootstrap_ci``: coverage of its 95% interval at 10 seeds, degenerate cases."""

import numpy as np
import pytest
from scipy import stats

from sparsecomm.stats import bootstrap_ci, expanded_level, student_t_ci

TRIALS = 1000
"""Fixed-seed samples in the coverage test (about 5 s on one core with 1000 resamples each)."""


def test_95_interval_covers_the_mean_of_10_normal_values_about_95_percent():
    se = np.sqrt(0.95 * 0.05 / TRIALS)  # binomial standard error of a 95% coverage estimate
    ours = percentile = 0
    for trial in range(TRIALS):
        x = np.random.default_rng(trial).normal(size=10)  # true mean 0
        _, lo, hi = bootstrap_ci(x, n_resamples=1000)
        ours += lo <= 0.0 <= hi
        ci = stats.bootstrap(
            (x,), np.mean, n_resamples=1000, method="percentile", rng=np.random.default_rng(0)
        ).confidence_interval
        percentile += ci.low <= 0.0 <= ci.high
    # measured: 0.938 here (0.951 over other seeds, docstring); the nominal-level percentile
    # interval (the previous method) covers 0.902: too narrow at 10 values.
    assert abs(ours / TRIALS - 0.95) <= 3 * se, ours / TRIALS
    assert percentile / TRIALS < 0.95 - 3 * se < ours / TRIALS, percentile / TRIALS


def test_expanded_level():
    assert expanded_level(10) == pytest.approx(0.9829, abs=1e-4)
    assert expanded_level(5) == pytest.approx(0.9981, abs=1e-4)
    assert expanded_level(10_000) == pytest.approx(0.95, abs=1e-4)
    assert expanded_level(2) == 1.0  # BCa cannot give this level: Student-t instead


def test_degenerate_values_give_a_point_interval():
    assert bootstrap_ci([0.7]) == (0.7, 0.7, 0.7)
    assert bootstrap_ci([3.0, 3.0, 3.0, 3.0, 3.0]) == (3.0, 3.0, 3.0)
    assert bootstrap_ci(np.zeros((2, 5))) == (0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="non-empty"):
        bootstrap_ci([])


def test_two_values_fall_back_to_student_t():
    half = stats.t.ppf(0.975, 1) * np.sqrt(0.5) / np.sqrt(2)  # 12.706 x sd / sqrt(n)
    assert student_t_ci([0.0, 1.0]) == pytest.approx((0.5, 0.5 - half, 0.5 + half))
    assert bootstrap_ci([0.0, 1.0]) == pytest.approx((0.5, 0.5 - half, 0.5 + half))
    est, lo, hi = bootstrap_ci([0.0, 1.0], statistic=np.median)  # no t interval for a median
    assert est == 0.5 and np.isnan(lo) and np.isnan(hi)


def test_binary_values_with_one_different():
    # success flags of 5 seeds, one failed: a finite interval inside the data's range
    est, lo, hi = bootstrap_ci([1.0, 1.0, 1.0, 1.0, 0.0])
    assert est == 0.8 and 0.0 <= lo < 0.8 and hi == 1.0
    est, lo, hi = bootstrap_ci([0.0] * 9 + [1.0])
    assert est == pytest.approx(0.1) and lo == 0.0 and 0.1 < hi < 1.0


def test_deterministic_for_a_fixed_seed():
    x = np.random.default_rng(7).exponential(size=8)
    assert bootstrap_ci(x, n_resamples=2000) == bootstrap_ci(x, n_resamples=2000)
    assert bootstrap_ci(x, n_resamples=2000, seed=1) != bootstrap_ci(x, n_resamples=2000)
