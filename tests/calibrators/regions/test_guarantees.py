"""What each served region guarantees (`ConformalRegions.guarantee_table`), per cell in the
profile and per ellipse in what `calibrate` serves."""

from __future__ import annotations

import numpy as np

from calibrators.regions import GUARANTEES, ConformalRegions

EDGES = (0.0, 15.0, 30.0, float("inf"))


def _scores(rng: np.random.Generator):
    """Class 0: 300 points in each bin (own groups); class 1: 150 in all, 30 of them near
    (merged bins); class 2: 20 points (too small: pooled); nothing of class 3."""
    cls = np.concatenate([np.zeros(900, int), np.ones(150, int), np.full(20, 2)])
    dist = np.concatenate([np.repeat([5.0, 20.0, 45.0], 300),
                           np.r_[rng.uniform(0, 15, 30), rng.uniform(15, 60, 120)],
                           rng.uniform(0, 60, 20)])
    return rng.rayleigh(1.0, cls.size), cls, dist


def test_every_cell_says_whether_its_own_scores_a_pool_or_all_scores_certify_it():
    s, c, d = _scores(np.random.default_rng(0))
    regions = ConformalRegions(EDGES, min_group=100).fit(s, c, d, all_classes=[0, 1, 2, 3])
    rows = {(r["class"], r["bin"]): r for r in regions.guarantees([0.5, 0.9])}
    assert rows[(0, 0)]["guarantee"] == {"0.5": "cell", "0.9": "cell"}
    assert rows[(1, 0)]["guarantee"] == {"0.5": "pooled", "0.9": "pooled"}   # merged bins
    assert rows[(2, 1)]["guarantee"]["0.9"] in ("pooled", "marginal")
    names, counts = regions.guarantee_table([0.5, 0.9])
    unseen = regions.group_index(np.array([7]), np.array([5.0]))[0]   # a class unknown at fit
    assert names[unseen].tolist() == ["marginal", "marginal"]
    assert counts[unseen].tolist() == [s.size, s.size]
    assert set(names.ravel()) <= set(GUARANTEES)


def test_a_floored_cell_names_its_own_count_and_a_pooled_one_its_group_count():
    s, c, d = _scores(np.random.default_rng(1))
    s[(c == 1) & (d < 15)] *= 2.0   # the merged near cell of class 1 is wider than its group
    regions = ConformalRegions(EDGES, min_group=100, cell_floor=True, floor_delta=0.2)
    regions.fit(s, c, d)
    g = regions.group_index(np.array([1, 1]), np.array([5.0, 45.0]))
    names, counts = regions.guarantee_table([0.5, 0.9, 0.99])
    assert names[g[0]].tolist()[:2] == ["cell", "cell"] and counts[g[0], 1] == 30
    assert names[g[0], 2] in ("scaled", "pooled")   # 30 points certify no 99 % on their own
    assert counts[g[0], 2] == regions.groups_[g[0]].base.n
