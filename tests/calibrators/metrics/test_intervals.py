"""Sampling intervals of proportions and the coverage allowance of a served level."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from calibrators.metrics import coverage_allowance, proportion_bounds


@pytest.mark.parametrize(("hits", "n"), [(0, 10), (10, 10), (7, 10), (243, 300), (1, 1)])
def test_bounds_are_the_exact_clopper_pearson_interval(hits, n):
    lo, hi = proportion_bounds(hits, n)
    ref = stats.binomtest(hits, n).proportion_ci(confidence_level=0.95, method="exact")
    assert float(lo) == pytest.approx(ref.low, abs=1e-12)
    assert float(hi) == pytest.approx(ref.high, abs=1e-12)


def test_bounds_are_elementwise_and_nan_without_trials():
    lo, hi = proportion_bounds(np.array([0, 5, 0]), np.array([4, 10, 0]))
    assert lo[0] == 0.0 and 0 < lo[1] < 0.5 < hi[1] < 1 and np.isnan(lo[2]) and np.isnan(hi[2])


def test_the_allowance_is_two_points_plus_a_one_sided_99_percent_sampling_margin():
    assert float(coverage_allowance(0.9, 900)) == pytest.approx(0.9 - 0.02 - 2.33 * 0.01)
    wide, narrow = coverage_allowance(0.95, np.array([100, 10_000]))
    assert wide < narrow < 0.93
