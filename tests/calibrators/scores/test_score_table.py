"""`ScoreTable`: the tables of any split of the data add to the table of the whole, and a
calibrator fit on its weighted rows is the fit of the detections they stand for (a row of
weight w is w copies of itself); on cells, fits move by what the cell width allows; the
number of cells is bounded whatever the number of detections."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.core.errors import FieldError
from calibrators.metrics import classification_nll, expected_calibration_error
from calibrators.scores import SCORE_CALIBRATION_METHODS, ScoreTable, make_score_calibrator

C = 4


def sample(n: int, seed: int):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, C, n)
    d = rng.uniform(0, 70, n)
    z = rng.normal(0, 2, n) + 0.3 * labels
    hit = rng.random(n) < 1 / (1 + np.exp(-(1.3 * z - 0.02 * d)))
    return z, labels, hit, d


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 300), seed=st.integers(0, 10_000), cuts=st.lists(
    st.floats(0, 1), max_size=5), exact=st.booleans())
def test_tables_of_any_split_add_to_the_whole(n, seed, cuts, exact):
    z, labels, hit, d = sample(n, seed)
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)                        # any interleaving of the rows
    bounds = sorted({0, n, *(int(c * n) for c in cuts)})
    parts = [ScoreTable.build(z[o], labels[o], hit[o], d[o], C, exact=exact)
             for o in (order[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True))]
    whole = ScoreTable.build(z, labels, hit, d, C, exact=exact)
    merged = ScoreTable.empty(C, exact=exact)
    for part in parts[::-1]:
        merged = merged + part
    assert merged.n == whole.n == n
    for by_range in (False, True):
        got, want = merged.rows(by_range), whole.rows(by_range)
        if exact:   # the rows themselves, as a multiset
            assert sorted(zip(got.z, got.labels, got.hit, got.distances, strict=True)) == \
                sorted(zip(z, labels, hit, d, strict=True))
            continue
        assert (got.labels == want.labels).all() and (got.hit == want.hit).all()
        np.testing.assert_allclose(got.weight, want.weight)
        np.testing.assert_allclose(got.z, want.z, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(got.distances, want.distances, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("by_range", [False, True])
def test_rows_keep_class_outcome_and_cell_sums(by_range):
    z, labels, hit, d = sample(2000, 1)
    rows = ScoreTable.build(z, labels, hit, d, C).rows(by_range)
    assert rows.weight.sum() == 2000
    for k in range(C):
        for h in (False, True):
            mine = (labels == k) & (hit == h)
            cell = (rows.labels == k) & (rows.hit == h)
            assert rows.weight[cell].sum() == mine.sum()
            assert np.dot(rows.weight[cell], rows.z[cell]) == pytest.approx(z[mine].sum())
            assert np.dot(rows.weight[cell], rows.distances[cell]) == pytest.approx(
                d[mine].sum())


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_a_weight_is_that_many_copies_of_the_row(method):
    z, labels, hit, d = sample(900, 2)
    w = np.random.default_rng(3).integers(1, 4, z.size).astype(np.float64)
    copies = np.repeat(np.arange(z.size), w.astype(np.int64))
    weighted = make_score_calibrator(method).fit(z, labels, hit, C, distances=d,
                                                 sample_weight=w)
    repeated = make_score_calibrator(method).fit(z[copies], labels[copies], hit[copies], C,
                                                 distances=d[copies])
    assert (weighted.n_samples_ == repeated.n_samples_).all()
    assert (weighted.n_positives_ == repeated.n_positives_).all()
    grid = np.linspace(-6, 6, 200)
    lab, dist = np.arange(200) % C, np.linspace(0, 70, 200)
    np.testing.assert_allclose(weighted.transform(grid, lab, dist),
                               repeated.transform(grid, lab, dist), atol=1e-6)


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_a_fit_on_cells_moves_by_what_the_cell_width_allows(method):
    z, labels, hit, d = sample(20_000, 4)
    cells = make_score_calibrator(method)
    rows = ScoreTable.build(z, labels, hit, d, C).rows(by_range=cells.uses_distances)
    cells = cells.fit(rows.z, rows.labels, rows.hit, C,
                                              distances=rows.distances,
                                              sample_weight=rows.weight)
    exact = make_score_calibrator(method).fit(z, labels, hit, C, distances=d)
    p_cells, p_exact = cells.transform(z, labels, d), exact.transform(z, labels, d)
    assert classification_nll(p_cells, hit) == pytest.approx(classification_nll(p_exact, hit),
                                                             abs=1e-4)
    limit = 1e-4 if method in ("class_temperature", "platt", "platt_range") else 5e-3
    assert np.abs(p_cells - p_exact).mean() < limit


def test_weighted_metrics_count_each_row_its_weight():
    rng = np.random.default_rng(5)
    p, y = rng.random(300), rng.random(300) < 0.4
    w = rng.integers(0, 3, 300).astype(np.float64)
    copies = np.repeat(np.arange(300), w.astype(np.int64))
    assert classification_nll(p, y, sample_weight=w) == pytest.approx(
        classification_nll(p[copies], y[copies]))
    assert expected_calibration_error(p, y, sample_weight=w) == pytest.approx(
        expected_calibration_error(p[copies], y[copies]))
    with pytest.raises(FieldError, match="sample_weight"):
        classification_nll(p, y, sample_weight=-w)


def test_the_cells_are_bounded_whatever_the_detections():
    """Logits within ±8 and distances within 70 m fill at most their grids' cells."""
    from calibrators.scores import D_WIDTH, RANGE_Z_WIDTH, Z_WIDTH

    z, labels, hit, d = sample(400_000, 6)
    z = np.clip(z, -8, 8 - 1e-9)
    table = ScoreTable.build(z, labels, hit, d, C)
    assert len(table.rows().z) <= C * 2 * 16 / Z_WIDTH
    assert len(table.rows(by_range=True).z) <= C * 2 * (16 / RANGE_Z_WIDTH) * (70 / D_WIDTH)
    assert len(table.rows().z) < z.size / 4
