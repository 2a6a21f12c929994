"""Cell ceilings of `ConformalRegions` (issue: honest in every class × range cell, classes
judged on both sides of their level).

The world: Mahalanobis scores of a Rayleigh law, scale 1 in every cell but one small far cell
of class 1 (about 60 calibration points, too few for a group of its own), whose scores are
0.5 times as wide. Merged with its wider neighbours, the group's radius covers it far above q;
with a ceiling it is served its own split-conformal radius and covered at q on average."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.regions import ConformalRegions

EDGES = (0.0, 15.0, 30.0, float("inf"))
NARROW = 0.5
Q = 0.9


def _draw(rng: np.random.Generator, n_narrow: int = 60):
    """(scores, classes, distances): class 0 everywhere, class 1 near (200 points) and the
    narrow far cell (class 1, 30+ m) with `n_narrow` points."""
    cls = np.concatenate([np.zeros(900, int), np.ones(200, int), np.ones(n_narrow, int)])
    dist = np.concatenate([rng.uniform(0, 60, 900), rng.uniform(0, 30, 200),
                           rng.uniform(30, 60, n_narrow)])
    scale = np.where((cls == 1) & (dist >= 30), NARROW, 1.0)
    return rng.rayleigh(scale), cls, dist


def _narrow_coverage(radius: float) -> float:
    return 1.0 - np.exp(-radius ** 2 / (2 * NARROW ** 2))


def _fit(s, c, d, ceiling: bool, floor_delta: float | None = None) -> ConformalRegions:
    return ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=floor_delta,
                            cell_ceiling=ceiling).fit(s, c, d)


@pytest.mark.parametrize("ceiling", [False, True])
def test_a_narrow_pooled_cell_is_covered_at_q_only_with_its_ceiling(ceiling):
    rng = np.random.default_rng(0)
    coverage = []
    for _ in range(200):
        regions = _fit(*_draw(rng), ceiling)
        coverage.append(_narrow_coverage(float(regions.radii([Q], np.array([1]),
                                                             np.array([45.0]))[0, 0])))
    mean = float(np.mean(coverage))
    if ceiling:   # its own 60 points: q on average (≤ q + 1/(n+1) for continuous scores)
        assert Q - 0.01 <= mean <= Q + 0.03, mean
    else:         # the merged group's radius: far above q
        assert mean > 0.99, mean


def test_the_ceiling_says_cell_and_its_count_and_leaves_wide_and_exact_cells_alone():
    rng = np.random.default_rng(1)
    s, c, d = _draw(rng)
    with_, without = _fit(s, c, d, True), _fit(s, c, d, False)
    names, counts = with_.guarantee_table([Q])
    narrow = with_.group_index(np.array([1]), np.array([45.0]))[0]
    assert names[narrow, 0] == "cell" and counts[narrow, 0] == int(((c == 1) & (d >= 30)).sum())
    near = (np.array([0, 0, 1]), np.array([5.0, 45.0, 5.0]))
    np.testing.assert_array_equal(with_.radii([0.5, Q], *near), without.radii([0.5, Q], *near))


def test_with_tail_floors_the_ceiling_serves_the_cells_own_pac_radius():
    rng = np.random.default_rng(2)
    s, c, d = _draw(rng, n_narrow=80)
    regions = _fit(s, c, d, True, floor_delta=0.2)
    served = float(regions.radii([Q], np.array([1]), np.array([45.0]))[0, 0])
    pooled = float(_fit(s, c, d, False).radii([Q], np.array([1]), np.array([45.0]))[0, 0])
    own = np.sort(s[(c == 1) & (d >= 30)])
    assert own[int(np.ceil(81 * Q)) - 1] <= served < pooled


def test_ceilings_round_trip_and_regions_without_them_keep_their_json():
    rng = np.random.default_rng(3)
    s, c, d = _draw(rng)
    with_, without = _fit(s, c, d, True), _fit(s, c, d, False)
    assert with_.to_dict()["hyper"]["cell_ceiling"] is True
    assert "cell_ceiling" not in without.to_dict()["hyper"]
    levels, at = [0.5, 0.9, 0.99], (np.array([0, 1, 1]), np.array([5.0, 5.0, 45.0]))
    for regions in (with_, without):
        again = ConformalRegions.from_dict(regions.to_dict())
        np.testing.assert_array_equal(again.radii(levels, *at), regions.radii(levels, *at))
    assert not np.array_equal(with_.radii(levels, *at), without.radii(levels, *at))
