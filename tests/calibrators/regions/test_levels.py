"""Levels, Gaussian radii and distance bins of served regions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from calibrators.regions import (
    MAX_LEVELS,
    check_distance_edges,
    check_levels,
    distance_bins,
    gaussian_radius,
)


def test_check_levels_accepts_up_to_twenty_distinct_levels():
    assert check_levels(0.95).tolist() == [0.95]
    levels = np.linspace(0.01, 0.99, MAX_LEVELS)
    np.testing.assert_array_equal(check_levels(levels), levels)


@pytest.mark.parametrize("bad, why", [([0.0], "not a level"), ([1.0], "not a level"),
                                      ([math.nan], "not a level"), ([math.inf], "not a level"),
                                      ([0.5, 0.9, 0.5], r"levels\[2\] = 0.5 repeats levels\[0\]"),
                                      (list(np.linspace(0.01, 0.99, 21)), "at most 20"),
                                      ([], "non-empty"), ("abc", "numbers")])
def test_check_levels_names_the_field(bad, why):
    with pytest.raises(ValueError, match=why) as info:
        check_levels(bad)
    assert "levels" in str(info.value) and info.value.field == "levels"


def test_gaussian_radius():
    assert gaussian_radius(0.95) == pytest.approx(math.sqrt(-2 * math.log(0.05)), rel=1e-15)
    assert gaussian_radius(0.95, dim=1) == pytest.approx(stats.norm.ppf(0.975), rel=1e-12)
    assert gaussian_radius(0.5, dim=3) == pytest.approx(math.sqrt(stats.chi2.ppf(0.5, 3)))
    with pytest.raises(ValueError, match="level"):
        gaussian_radius(1.0)
    with pytest.raises(ValueError, match="dim"):
        gaussian_radius(0.5, dim=0)


def test_distance_bins_clip_to_the_outer_bins():
    edges = check_distance_edges((0, 15, 30, math.inf))
    d = np.array([0.0, 14.99, 15.0, 29.0, 30.0, 1e6])
    assert distance_bins(d, edges).tolist() == [0, 0, 1, 1, 2, 2]
    assert distance_bins(np.array([3.0, 50.0]), check_distance_edges((10, 20, 40))).tolist() \
        == [0, 1]
    for bad in [(0,), (0, 30, 15), (-1, 10), (0, math.inf, 50), (math.nan, 1)]:
        with pytest.raises(ValueError, match="distance_edges"):
            check_distance_edges(bad)
