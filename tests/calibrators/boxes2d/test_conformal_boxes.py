"""ConformalBoxes: joint four-edge coverage per group on exchangeable synthetic data, the
region's geometry, what each cell records, and the estimator convention."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.boxes2d import (
    COCO_SIZE_EDGES,
    BoxRegions,
    ConformalBoxes,
    box_edges,
    box_scores,
    edges_box,
)
from calibrators.core.errors import FieldError, NotFittedError

LEVELS = (0.8, 0.9, 0.95)
#: Detections per class in one synthetic draw: classes 0 and 1 fill their own cells (class 1's
#: large bin is sparse and merges), classes 2 and 3 are too small alone (below `min_group` =
#: 100 in a half) and are pooled.
PER_CLASS = {0: 1800, 1: 1200, 2: 140, 3: 120}


def synthetic(seed: int):
    """(boxes, true boxes, labels, sigma) of exchangeable detections: sizes log-uniform over
    COCO's three bins, edge errors Student-t (5 dof) scaled by a per-class, per-size σ; the
    detector's σ is that σ with 30 % log-normal noise."""
    rng = np.random.default_rng(seed)
    labels = np.repeat(list(PER_CLASS), list(PER_CLASS.values()))
    n = len(labels)
    size = np.exp(rng.uniform(np.log(8.0), np.log(300.0), n))
    size[labels == 1] = np.minimum(size[labels == 1], 60.0 + 140.0 * (rng.random(
        int((labels == 1).sum())) < 0.03))   # class 1: few boxes above 96 px
    aspect = np.exp(rng.uniform(-0.5, 0.5, n))
    boxes = np.c_[rng.uniform(0, 600, (n, 2)), size * aspect, size / aspect]
    spread = 0.04 * (1.0 + labels)[:, None] * np.c_[boxes[:, 2], boxes[:, 3], boxes[:, 2],
                                                     boxes[:, 3]] + 0.5
    errors = rng.standard_t(5, (n, 4)) * spread
    true_edges = box_edges(boxes) + errors
    true_edges[:, 2:] = np.maximum(true_edges[:, 2:], true_edges[:, :2])   # a valid true box
    sigma = spread * np.exp(rng.normal(0.0, 0.3, (n, 4)))
    order = rng.permutation(n)
    return boxes[order], edges_box(true_edges)[order], labels[order], sigma[order]


def covered(inner: np.ndarray, outer: np.ndarray, true_boxes: np.ndarray) -> np.ndarray:
    """`[N, Q]` bool: every true edge lies between the inner and the outer box's."""
    t = box_edges(true_boxes)[:, None, :]
    lo_out, lo_in = box_edges(outer), box_edges(inner)
    return ((t[..., :2] >= lo_out[..., :2]) & (t[..., :2] <= lo_in[..., :2])
            & (t[..., 2:] <= lo_out[..., 2:]) & (t[..., 2:] >= lo_in[..., 2:])).all(axis=-1)


@pytest.mark.parametrize("score", ["additive", "scaled"])
def test_each_group_is_covered_at_its_level_over_many_splits(score):
    """Over 80 seeded draws split half / half (calibration, test), each group's joint
    four-edge coverage averages at least q less three standard errors of that average, and at
    most q + 1/(n+1) (the conformal slack of the group's calibration count n) plus three. The
    groups are own cells, merged bins and pooled classes; the group of all scores (served to
    classes unseen or too small even pooled) guarantees nothing per group and never serves
    here."""
    per_group: dict[tuple, list[np.ndarray]] = {}
    for seed in range(80):
        boxes, true, labels, sigma = synthetic(seed)
        half = len(boxes) // 2
        est = ConformalBoxes(score=score).fit(boxes[:half], true[:half], labels[:half],
                                              sigma[:half])
        test = slice(half, None)
        inner, outer = est.regions(boxes[test], labels[test], sigma[test], LEVELS)
        hit = covered(inner, outer, true[test])
        groups = est.conformal_.groups_
        kinds = est.conformal_.guarantee_table(LEVELS)[0][:, 0]
        index = est.conformal_.group_index(labels[test], np.sqrt(boxes[test, 2] *
                                                                 boxes[test, 3]))
        for g in np.unique(index):
            key = (groups[g].label, groups[g].bins, kinds[g])
            per_group.setdefault(key, []).append(
                np.r_[hit[index == g].mean(axis=0), groups[g].n])
    assert {key[2] for key in per_group} == {"cell", "pooled"}, sorted(per_group)
    assert len(per_group) >= 6      # 3 own cells, class 1's merged bins, the pooled classes
    for key, rows in per_group.items():
        table = np.array(rows)                       # [splits, Q + 1]
        mean = table[:, :-1].mean(axis=0)
        se = table[:, :-1].std(axis=0, ddof=1) / np.sqrt(len(table))
        slack = 1.0 / (table[:, -1].min() + 1.0)
        assert len(table) >= 70, key
        assert (mean >= np.array(LEVELS) - 3 * se).all(), (key, mean, se)
        assert (mean <= np.array(LEVELS) + slack + 3 * se).all(), (key, mean, se, slack)


def test_the_pooling_is_recorded_per_cell():
    boxes, true, labels, _ = (a[:1665] for a in synthetic(0))    # a calibration half
    est = ConformalBoxes().fit(boxes, true, labels)
    rows = {(r["class"], r["bin"]): r for r in est.guarantees([0.9])}
    assert set(rows) == {(c, b) for c in PER_CLASS for b in range(3)}
    assert rows[(0, 0)]["guarantee"] == {"0.9": "cell"}
    assert rows[(0, 0)]["count"] == rows[(0, 0)]["group_n"] >= 100
    assert rows[(0, 2)]["size_range"] == [96.0, None]
    # class 1's sparse large bin is merged with its medium one: "pooled", the pair's count
    assert rows[(1, 2)]["guarantee"] == {"0.9": "pooled"}
    assert rows[(1, 2)]["group_n"] == rows[(1, 1)]["count"] + rows[(1, 2)]["count"]
    # classes 2 and 3 (about 130 scores together) are pooled per run of bins
    assert rows[(2, 0)]["guarantee"] == rows[(3, 0)]["guarantee"] == {"0.9": "pooled"}
    assert rows[(2, 0)]["group_n"] >= 100
    reasons = est.conformal_.reasons_
    assert reasons[0] == ["own"] * 3 and reasons[2][0] == "pooled_classes"
    # a tiny class alone below min_group with no other small class: the marginal group
    few = labels != 3
    alone = ConformalBoxes().fit(boxes[few], true[few], np.where(labels[few] == 2, 2, 0))
    tiny = {(r["class"], r["bin"]): r for r in alone.guarantees([0.9])}
    assert tiny[(2, 1)]["guarantee"] == {"0.9": "marginal"}
    served = alone.serve(boxes[:3], np.array([2, 2, 9]), None, [0.9])
    assert served.guarantee[:, 0].tolist() == ["marginal"] * 3       # 9: unseen at fit


def test_regions_are_the_edges_moved_by_the_radius():
    boxes = np.array([[10.0, 20.0, 30.0, 40.0]])
    true = np.array([[12.0, 17.0, 30.0, 45.0]])            # edge errors 2, -3, 2, 2
    assert box_scores(boxes, true).tolist() == [3.0]
    sigma = np.array([[1.0, 6.0, 0.5, 2.0]])
    assert box_scores(boxes, true, sigma, "scaled").tolist() == [4.0]   # 2 / 0.5
    rng = np.random.default_rng(3)
    cal = np.repeat(boxes, 200, axis=0)
    cal_true = cal + np.c_[rng.normal(0, 1, (200, 2)), np.zeros((200, 2))]
    est = ConformalBoxes(min_group=10).fit(cal, cal_true, np.zeros(200, int))
    r = est.radii([0.5, 0.9], boxes, [0])[0]
    inner, outer = est.regions(boxes, [0], None, [0.5, 0.9])
    np.testing.assert_allclose(outer[0], np.c_[10 - r, 20 - r, 30 + 2 * r, 40 + 2 * r])
    np.testing.assert_allclose(inner[0], np.c_[10 + r, 20 + r, 30 - 2 * r, 40 - 2 * r])
    scaled = ConformalBoxes("scaled", min_group=10).fit(cal, cal_true, np.zeros(200, int),
                                                         np.ones((200, 4)))
    _, wide = scaled.regions(boxes, [0], 2.0 * np.ones((1, 4)), [0.9])
    rs = scaled.radii([0.9], boxes, [0])[0, 0]
    np.testing.assert_allclose(wide[0, 0], [10 - 2 * rs, 20 - 2 * rs, 30 + 4 * rs, 40 + 4 * rs])


def test_an_unbounded_level_and_an_empty_inner_box():
    boxes = np.tile([[0.0, 0.0, 4.0, 4.0]], (20, 1))
    true = boxes + np.c_[np.linspace(1, 5, 20), np.zeros((20, 3))]
    est = ConformalBoxes(min_group=5).fit(boxes, true, np.zeros(20, int))
    served = est.serve(boxes[:1], [0], None, [0.5, 0.99])
    assert isinstance(served, BoxRegions) and len(served) == 1
    assert served.inner[0, 0, 2] < 0                # radius 3 > half the width: crossed edges
    assert np.isinf(served.outer[0, 1]).all() and not np.isnan(served.inner).any()


def test_size_bins_from_quantiles_and_explicit_edges():
    boxes, true, labels, _ = synthetic(1)
    est = ConformalBoxes(size_edges=4, min_group=20).fit(boxes, true, labels)
    sizes = np.sqrt(boxes[:, 2] * boxes[:, 3])
    assert est.size_edges_[0] == 0.0 and np.isinf(est.size_edges_[-1])
    np.testing.assert_allclose(est.size_edges_[1:-1], np.quantile(sizes, [0.25, 0.5, 0.75]))
    counts = est.conformal_.counts_.sum(axis=0)
    assert counts.min() >= len(sizes) // 4 - 1
    explicit = ConformalBoxes(size_edges=(0, 50, float("inf"))).fit(boxes, true, labels)
    assert explicit.size_edges_.tolist() == [0.0, 50.0, float("inf")]
    assert ConformalBoxes().size_edges == COCO_SIZE_EDGES


def test_estimator_convention_and_round_trip():
    boxes, true, labels, sigma = synthetic(2)
    for make in (lambda: ConformalBoxes("scaled"), lambda: ConformalBoxes(size_edges=3)):
        est = make()
        before = set(vars(est))
        with pytest.raises(NotFittedError):
            est.regions(boxes, labels, sigma, [0.9])
        with pytest.raises(NotFittedError):
            est.to_dict()
        assert est.fit(boxes, true, labels, sigma) is est
        added = set(vars(est)) - before
        assert added == {"conformal_", "size_edges_"}
        text = json.dumps(est.to_dict(), allow_nan=False)
        back = ConformalBoxes.from_dict(json.loads(text))
        a, b = est.serve(boxes, labels, sigma, (0.5, 0.9, 0.999)), \
            back.serve(boxes, labels, sigma, (0.5, 0.9, 0.999))
        assert a.inner.tobytes() == b.inner.tobytes() and a.outer.tobytes() == b.outer.tobytes()
        assert (a.guarantee == b.guarantee).all() and (a.calibration_n == b.calibration_n).all()
        assert json.dumps(back.to_dict(), allow_nan=False) == text
    with pytest.raises(ValueError, match="must be a dict"):
        ConformalBoxes.from_dict([1])
    with pytest.raises(ValueError, match="lacks"):
        ConformalBoxes.from_dict({})


@pytest.mark.parametrize(("call", "field"), [
    (lambda b, t, l, s: ConformalBoxes("scaled").fit(b, t, l), "sigma"),
    (lambda b, t, l, s: ConformalBoxes("scaled").fit(b, t, l, -s), "sigma"),
    (lambda b, t, l, s: ConformalBoxes("median").fit(b, t, l), "score"),
    (lambda b, t, l, s: ConformalBoxes().fit(b, t[:-1], l), "true_boxes"),
    (lambda b, t, l, s: ConformalBoxes().fit(b, t, l[:-1]), "labels"),
    (lambda b, t, l, s: ConformalBoxes(size_edges=(0, 50, 20)).fit(b, t, l), "size_edges"),
    (lambda b, t, l, s: ConformalBoxes().fit(-b, t, l), "boxes"),
])
def test_bad_input_names_the_field(call, field):
    boxes, true, labels, sigma = synthetic(4)
    with pytest.raises(FieldError) as info:
        call(boxes, true, labels, sigma)
    assert info.value.field == field
