"""Cell floors and training-conditional (PAC) radii of `ConformalRegions` (issue: honest in
every class × range cell).

The world: Mahalanobis scores of a Rayleigh law (a calibrated 2-D Gaussian), scale 1 in every
class × range cell but one rare near-range cell of class 1, whose scores are 1.6 times wider
and which holds too few calibration points (about 40) for a group of its own. Pooled with the
other cells, its radius is too small; with a cell floor, its coverage over calibration draws is
q; with `delta`, at least (1 - delta) of the draws cover q of it."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.regions import ConformalRegions

EDGES = (0.0, 15.0, 30.0, float("inf"))
WIDE = 1.6          # the rare cell's scale
Q = 0.9


def _draw(rng: np.random.Generator, n_common: int = 600, n_rare: int = 40):
    """(scores, classes, distances): class 0 in every bin, class 1 mostly far, and the rare
    cell (class 1, 0-15 m) with `n_rare` points."""
    cls = np.concatenate([np.zeros(n_common, int), np.ones(n_common // 3, int),
                          np.ones(n_rare, int)])
    dist = np.concatenate([rng.uniform(0, 60, n_common), rng.uniform(30, 60, n_common // 3),
                           rng.uniform(0, 15, n_rare)])
    scale = np.where((cls == 1) & (dist < 15), WIDE, 1.0)
    return rng.rayleigh(scale), cls, dist


def _rare_coverage(radius: float) -> float:
    """True coverage of the rare cell at `radius` (Rayleigh law with scale WIDE)."""
    return 1.0 - np.exp(-radius ** 2 / (2 * WIDE ** 2))


def _rare_radius(regions: ConformalRegions) -> float:
    return float(regions.radii([Q], np.array([1]), np.array([5.0]))[0, 0])


@pytest.mark.parametrize("cell_floor", [False, True])
def test_the_rare_cell_is_covered_on_average_only_with_its_floor(cell_floor):
    rng = np.random.default_rng(0)
    coverage = []
    for _ in range(300):
        s, c, d = _draw(rng)
        regions = ConformalRegions(EDGES, min_group=100, cell_floor=cell_floor).fit(s, c, d)
        coverage.append(_rare_coverage(_rare_radius(regions)))
    mean = float(np.mean(coverage))
    if cell_floor:   # split-conformal over the cell's own 40 points: >= q on average
        assert mean >= Q - 3 * np.std(coverage) / np.sqrt(len(coverage))
    else:            # pooled with scale-1 scores: far below q
        assert mean < Q - 0.1


def test_pac_radii_cover_q_in_at_least_one_minus_delta_of_the_draws():
    rng = np.random.default_rng(1)
    delta, hits, marginal_hits, n_draws = 0.1, 0, 0, 300
    for _ in range(n_draws):
        s, c, d = _draw(rng)
        pac = ConformalRegions(EDGES, min_group=100, cell_floor=True, delta=delta).fit(s, c, d)
        plain = ConformalRegions(EDGES, min_group=100, cell_floor=True).fit(s, c, d)
        hits += _rare_coverage(_rare_radius(pac)) >= Q
        marginal_hits += _rare_coverage(_rare_radius(plain)) >= Q
    # binomial sampling allowance of 3 standard deviations on the fraction of draws
    assert hits / n_draws >= 1 - delta - 3 * np.sqrt(delta * (1 - delta) / n_draws)
    assert marginal_hits < hits   # marginal radii miss q in more draws (about half)


def test_the_profile_records_what_holds_per_cell_and_round_trips():
    s, c, d = _draw(np.random.default_rng(2))
    regions = ConformalRegions(EDGES, min_group=100, cell_floor=True, delta=0.05).fit(s, c, d)
    rows = {(r["class"], r["bin"]): r for r in regions.guarantees([0.5, 0.9, 0.99])}
    rare = rows[(1, 0)]
    assert rare["count"] == 40 and rare["group_n"] > 40
    assert rare["guarantee"]["0.5"] == "cell"
    assert rare["guarantee"]["0.99"] in ("scaled", "pooled")   # 40 points certify no 99 %
    back = ConformalRegions.from_dict(regions.to_dict())
    probe_c, probe_d = np.array([0, 1, 1, 1]), np.array([5.0, 5.0, 20.0, 45.0])
    levels = [0.5, 0.9, 0.95, 0.99]
    assert np.array_equal(back.radii(levels, probe_c, probe_d),
                          regions.radii(levels, probe_c, probe_d))
    assert back.to_dict() == regions.to_dict()


def test_regions_fit_without_floors_keep_their_json():
    s, c, d = _draw(np.random.default_rng(3))
    data = ConformalRegions(EDGES, min_group=100).fit(s, c, d).to_dict()
    assert set(data["hyper"]) == {"distance_edges", "min_group", "n_exact", "max_ranks"}
    assert all("base" not in g for g in data["groups"])


@pytest.mark.parametrize("delta", [0.0, 1.0, -0.1, "0.1", True])
def test_a_bad_delta_is_refused_naming_it(delta):
    s, c, d = _draw(np.random.default_rng(4))
    with pytest.raises(ValueError, match="delta"):
        ConformalRegions(EDGES, delta=delta).fit(s, c, d)


def test_a_cell_as_wide_as_its_group_keeps_the_group_radius_in_most_draws():
    """A floor only where the cell's scores show the group's radius too small: a small cell
    drawn like its group is not over-covered by the largest of its few scores."""
    rng = np.random.default_rng(5)
    floored, coverage = 0, []
    for _ in range(300):
        s, c, d = _draw(rng)
        s[(c == 1) & (d < 15)] /= WIDE          # the rare cell now drawn like the others
        with_floor = ConformalRegions(EDGES, min_group=100, cell_floor=True).fit(s, c, d)
        plain = ConformalRegions(EDGES, min_group=100).fit(s, c, d)
        r = _rare_radius(with_floor)
        floored += r != _rare_radius(plain)
        coverage.append(1.0 - np.exp(-r ** 2 / 2))   # Rayleigh law of scale 1
    assert floored / 300 < 0.3
    assert float(np.mean(coverage)) < Q + 0.03
