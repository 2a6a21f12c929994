"""ConformalRegions: finite-sample coverage per group on heavy-tailed exchangeable data,
conservative stored tables, merging and pooling of small groups, levels, round trip."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrators.core.errors import NotFittedError
from calibrators.regions import ConformalRegions, stored_ranks

LEVELS = np.array([0.5, 0.9, 0.95, 0.99])
EDGES = (0.0, 15.0, 30.0, math.inf)
# calibration scores per cell (class x distance bin), all >= 100 (own groups) and <= 500
N_CAL = np.array([[150, 300, 200], [120, 180, 400]])
SCALE = np.array([[0.6, 1.0, 1.8], [0.8, 1.5, 3.0]])  # a different distribution per cell
N_TEST = 1000


def cells(rng: np.random.Generator, counts: np.ndarray):
    """Scores `‖t‖·scale` of 2-D Student-t (df = 3) residuals (the Mahalanobis distance of a
    heavy-tailed residual under a Σ' of the right shape), with classes and distances."""
    cls = np.repeat(np.repeat([0, 1], 3), counts.ravel())
    b = np.repeat(np.tile([0, 1, 2], 2), counts.ravel())
    d = rng.uniform(0.0, 15.0, b.size) + 15.0 * b
    t = rng.standard_t(3, size=(b.size, 2))
    return np.hypot(t[:, 0], t[:, 1]) * SCALE[cls, b], cls, d, b


def test_coverage_per_group_over_200_splits_student_t():
    """Mean test coverage of each group lies in [q, q + 1/(n+1)] up to 4 standard errors."""
    splits = 200
    total = np.zeros((2, 3, LEVELS.size))
    for seed in range(splits):
        rng = np.random.default_rng(seed)
        s, c, d, _ = cells(rng, N_CAL)
        regions = ConformalRegions(distance_edges=EDGES).fit(s, c, d)
        s_t, c_t, d_t, b_t = cells(rng, np.full((2, 3), N_TEST))
        inside = s_t[:, None] <= regions.radii(LEVELS, c_t, d_t)
        for k in range(2):
            for b in range(3):
                total[k, b] += inside[(c_t == k) & (b_t == b)].mean(axis=0)
    mean = total / splits
    n = N_CAL[..., None]
    sd = np.sqrt(LEVELS * (1 - LEVELS) * (1 / (n + 2) + 1 / N_TEST) / splits)
    assert (mean >= LEVELS - 4 * sd).all(), mean - LEVELS
    assert (mean <= LEVELS + 1 / (n + 1) + 4 * sd).all(), mean - LEVELS


def test_exact_order_statistic_and_infinite_beyond_rank_n():
    rng = np.random.default_rng(1)
    s = rng.standard_t(3, 300) ** 2
    regions = ConformalRegions(min_group=1).fit(s, np.zeros(300, int), np.full(300, 5.0))
    exact = np.sort(s)
    levels = [0.1, 0.5, 0.9, 0.99, 0.996, 0.999]
    got = regions.radii(levels, [0], [5.0])[0]
    for q, r in zip(levels, got, strict=True):
        k = math.ceil(301 * q - 1e-9)
        assert r == (exact[k - 1] if k <= 300 else np.inf), q
    assert regions.radius(0.9, [0, 0], [1.0, 50.0]).tolist() == [exact[270]] * 2


def test_rank_rounding_is_not_fooled_by_float_error():
    s = np.arange(1.0, 100.0)  # n = 99: (n + 1)·0.9 = 90.00000000000001 in float64
    regions = ConformalRegions(min_group=1).fit(s, np.zeros(99, int), np.ones(99))
    assert regions.radius(0.9, [0], [1.0])[0] == 90.0


@pytest.mark.parametrize("n", [501, 5000, 200_000])
def test_stored_table_is_conservative_and_compact(n):
    rng = np.random.default_rng(n)
    s = np.abs(rng.standard_t(3, n))
    regions = ConformalRegions(min_group=1).fit(s, np.zeros(n, int), np.ones(n))
    group = regions.groups_[regions.serving_[0, 0]]
    assert group.n == n and len(group.ranks) <= 600
    exact = np.sort(s)
    q = np.linspace(0.0005, 0.9995, 1999)
    served = group.radius(q)
    k = np.ceil((n + 1) * q - 1e-9).astype(int)
    finite = k <= n
    assert (served[finite] >= exact[k[finite] - 1]).all()  # never below the exact statistic
    served_rank = np.searchsorted(exact, served[finite], side="right")
    excess = (served_rank - k[finite]) / (n + 1)
    assert excess.max() <= 0.004 + 1 / (n + 1)  # bulk spacing
    upper = q[finite] >= 0.9
    assert (excess[upper] <= 0.03 * (1 - q[finite][upper]) + 1 / (n + 1)).all()  # tail


def test_rank_grid_always_ends_at_n_and_one():
    for n in (501, 10**4, 10**7):
        ranks = stored_ranks(n, 500, 600)
        assert ranks[0] == 1 and ranks[-1] == n and (np.diff(ranks) > 0).all()
        assert len(ranks) <= 600


def small_groups():
    """car: [300, 40, 150]; ped: [60, 20, 10]; bus: [0, 0, 5]; bike: none."""
    counts = {"car": [300, 40, 150], "ped": [60, 20, 10], "bus": [0, 0, 5]}
    rng = np.random.default_rng(3)
    cls, d = [], []
    for name, row in counts.items():
        for b, m in enumerate(row):
            cls += [name] * m
            d += list(rng.uniform(0, 15, m) + 15 * b)
    return rng.exponential(size=len(cls)), np.array(cls), np.array(d)


def test_small_groups_are_merged_then_pooled_and_recorded():
    s, cls, d = small_groups()
    regions = ConformalRegions(min_group=100).fit(s, cls, d,
                                                  all_classes=["car", "ped", "bus", "bike"])
    table = {(row["class"], row["bin"]): row for row in regions.serving_table()}
    # car [300, 40, 150]: bin 1 joins its smaller neighbour, bin 2; that run serves both
    assert [table["car", b]["reason"] for b in range(3)] == ["own", "merged_bins",
                                                             "merged_bins"]
    assert table["car", 1]["group_bins"] == table["car", 2]["group_bins"] == [1, 2]
    assert table["car", 2]["group_n"] == 190
    # ped (90), bus (5), bike (0) are too small; pooled they hold 95 < 100: all scores serve
    for name in ("ped", "bus", "bike"):
        assert [table[name, b]["reason"] for b in range(3)] == ["global"] * 3
        assert table[name, 0]["group_class"] is None and table[name, 0]["group_n"] == s.size
    assert table["car", 2]["distance_range"] == [30.0, None]
    # the merged group's radius is the order statistic of car scores in bins 1 and 2
    car12 = np.sort(s[(cls == "car") & (d >= 15)])
    assert regions.radius(0.9, ["car"], [20.0])[0] == car12[math.ceil(191 * 0.9) - 1]
    # an unseen class is served by all scores
    np.testing.assert_array_equal(regions.radii(LEVELS, ["zzz"] * 3, [1.0, 20.0, 40.0]),
                                  regions.radii(LEVELS, ["bike"] * 3, [1.0, 20.0, 40.0]))
    assert regions.groups(["ped"], [20.0]) == [{"class": None, "bins": [0, 2], "n": s.size,
                                                "reason": "global"}]


def test_groups_partition_the_scores_so_each_group_covers_its_own_cells():
    s, cls, d = small_groups()
    regions = ConformalRegions(min_group=50).fit(s, cls, d, all_classes=["car", "ped", "bus"])
    served = regions._group_of(cls, d)
    # ped [60, 20, 10] is one run; bus (5) alone is too small and pooled small classes too
    table = {(row["class"], row["bin"]): row for row in regions.serving_table()}
    assert {table["ped", b]["group_bins"][0] for b in range(3)} == {0}
    for g in np.unique(served[cls != "bus"]):
        mine = served == g
        assert mine.sum() == regions.groups_[g].n           # a group = the scores it serves
        r = regions.groups_[g].radius(np.array([0.5, 0.9]))
        assert ((s[mine][:, None] <= r).mean(axis=0) >= [0.5, 0.9]).all()


@pytest.mark.parametrize("levels", [[0.0], [1.0], [float("nan")], [0.5, 0.5], [],
                                    list(np.linspace(0.01, 0.99, 21)), [-0.5], ["x"]])
def test_bad_levels_name_levels(levels):
    s, cls, d = small_groups()
    regions = ConformalRegions().fit(s, cls, d)
    with pytest.raises(ValueError, match="levels"):
        regions.radii(levels, cls[:3], d[:3])


def test_validation_names_the_argument():
    s, cls, d = small_groups()
    with pytest.raises(NotFittedError):
        ConformalRegions().radius(0.9, cls, d)
    regions = ConformalRegions().fit(s, cls, d)
    with pytest.raises(ValueError, match="level"):
        regions.radius(1.0, cls, d)
    with pytest.raises(ValueError, match="scores"):
        ConformalRegions().fit(-s, cls, d)
    with pytest.raises(ValueError, match="distance_edges"):
        ConformalRegions(distance_edges=(0, 30, 15)).fit(s, cls, d)
    with pytest.raises(ValueError, match="min_group"):
        ConformalRegions(min_group=0).fit(s, cls, d)
    with pytest.raises(ValueError, match="all_classes"):
        ConformalRegions().fit(s, cls, d, all_classes=["car"])
    with pytest.raises(ValueError, match="distances"):
        ConformalRegions().fit(s, cls, d[:-1])


def test_round_trip_serves_identically():
    s, cls, d = small_groups()
    regions = ConformalRegions(min_group=50, n_exact=100, max_ranks=120).fit(s, cls, d)
    data = regions.to_dict()
    assert data["distance_edges"][-1] is None
    back = ConformalRegions.from_dict(json.loads(json.dumps(data, allow_nan=False)))
    np.testing.assert_array_equal(back.radii(LEVELS, cls, d), regions.radii(LEVELS, cls, d))
    assert back.to_dict() == data and back.serving_table() == regions.serving_table()
