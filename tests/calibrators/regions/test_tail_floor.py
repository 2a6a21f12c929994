"""Tail floors of `ConformalRegions` (`floor_delta`): at levels >= 80 % a cell served by a larger
group keeps its own training-conditional radius, even where its few scores cannot show the
binomial test that the group's radius is too small for it.

The world: Rayleigh scores (a calibrated 2-D Gaussian) of scale 1 everywhere but one rare
near-range cell of class 1, whose law is the same in the bulk and wider in the tail (a mixture:
most points of scale 1, a fifth of scale 2.2), with 30 calibration points: too few for a group
of its own, and too few for the test to see the wider tail in most draws."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.regions import ConformalRegions

EDGES = (0.0, 15.0, 30.0, float("inf"))
Q = 0.9
TAIL_SHARE, TAIL_SCALE = 0.2, 2.2


def _draw(rng: np.random.Generator, n_rare: int = 30):
    cls = np.concatenate([np.zeros(600, int), np.ones(200, int), np.ones(n_rare, int)])
    dist = np.concatenate([rng.uniform(0, 60, 600), rng.uniform(30, 60, 200),
                           rng.uniform(0, 15, n_rare)])
    rare = (cls == 1) & (dist < 15)
    scale = np.where(rare & (rng.random(cls.size) < TAIL_SHARE), TAIL_SCALE, 1.0)
    return rng.rayleigh(scale), cls, dist


def _rare_coverage(radius: float) -> float:
    """True coverage of the rare cell's mixture law at `radius`."""
    cdf = [1.0 - np.exp(-radius ** 2 / (2 * s ** 2)) for s in (1.0, TAIL_SCALE)]
    return (1 - TAIL_SHARE) * cdf[0] + TAIL_SHARE * cdf[1]


def _rare_radius(regions: ConformalRegions, level: float = Q) -> float:
    return float(regions.radii([level], np.array([1]), np.array([5.0]))[0, 0])


def test_tail_floors_cover_the_rare_cell_in_at_least_one_minus_delta_of_the_draws():
    rng = np.random.default_rng(11)
    delta, n_draws = 0.2, 300
    tail_hits = test_hits = 0
    for _ in range(n_draws):
        s, c, d = _draw(rng)
        tail = ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=delta)
        test_only = ConformalRegions(EDGES, min_group=100, cell_floor=True)
        tail_hits += _rare_coverage(_rare_radius(tail.fit(s, c, d))) >= Q
        test_hits += _rare_coverage(_rare_radius(test_only.fit(s, c, d))) >= Q
    # binomial sampling allowance of 3 standard deviations on the fraction of draws
    assert tail_hits / n_draws >= 1 - delta - 3 * np.sqrt(delta * (1 - delta) / n_draws)
    assert test_hits / n_draws < 0.6   # the test alone leaves the group's radius in most draws


def test_below_the_tail_the_test_decides_as_before():
    s, c, d = _draw(np.random.default_rng(12))
    tail = ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=0.2).fit(s, c, d)
    test_only = ConformalRegions(EDGES, min_group=100, cell_floor=True).fit(s, c, d)
    probe = (np.array([0, 1, 1, 1]), np.array([5.0, 5.0, 20.0, 45.0]))
    low = [0.5, 0.6, 0.79]
    assert np.array_equal(tail.radii(low, *probe), test_only.radii(low, *probe))
    high = [0.8, 0.9, 0.95]
    assert (tail.radii(high, *probe) >= test_only.radii(high, *probe)).all()


def test_radii_grow_with_the_level_across_the_tail_boundary():
    s, c, d = _draw(np.random.default_rng(13))
    regions = ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=0.2).fit(s, c, d)
    levels = np.round(np.arange(0.70, 0.896, 0.01), 2)   # 20 levels around 0.8
    radii = regions.radii(levels, np.array([0, 1, 1]), np.array([5.0, 5.0, 45.0]))
    assert (np.diff(radii, axis=1) >= 0).all()


def test_tail_floors_round_trip_and_regions_without_them_keep_their_json():
    s, c, d = _draw(np.random.default_rng(14))
    tail = ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=0.2).fit(s, c, d)
    back = ConformalRegions.from_dict(tail.to_dict())
    probe, levels = (np.array([0, 1, 1]), np.array([5.0, 5.0, 45.0])), [0.5, 0.9, 0.95, 0.99]
    assert np.array_equal(back.radii(levels, *probe), tail.radii(levels, *probe))
    assert back.to_dict() == tail.to_dict()
    plain = ConformalRegions(EDGES, min_group=100, cell_floor=True).fit(s, c, d).to_dict()
    assert "floor_delta" not in plain["hyper"]   # profiles fit before load and serve as before


@pytest.mark.parametrize("floor_delta", [0.0, 1.0, -0.2, "0.2", True])
def test_a_bad_floor_delta_is_refused_naming_it(floor_delta):
    s, c, d = _draw(np.random.default_rng(15))
    with pytest.raises(ValueError, match="floor_delta"):
        ConformalRegions(EDGES, cell_floor=True, floor_delta=floor_delta).fit(s, c, d)
