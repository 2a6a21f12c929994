"""calibrators.evaluation.match: the nuScenes devkit's greedy matching rule, case by case."""

from __future__ import annotations

import numpy as np
import pytest

# `DENSE_PAIR_LIMIT`, patched below, is a global of this private module read at call time: the
# module is imported for that alone (allowed in tests/test_imports.py).
import calibrators.evaluation._matching as matching
from calibrators.evaluation import DEFAULT_CLASS_RANGE, MatchResult, in_range, match


def _match(dets, gts, threshold=2.0):
    """dets: (frame, label, score, x, y); gts: (frame, label, x, y)."""
    d = np.array(dets, dtype=float).reshape(-1, 5)
    g = np.array(gts, dtype=float).reshape(-1, 4)
    return match(d[:, 0].astype(int), d[:, 1].astype(int), d[:, 2], d[:, 3:5],
                 g[:, 0].astype(int), g[:, 1].astype(int), g[:, 2:4], threshold=threshold)


def reference_match(det_frame, det_labels, det_scores, det_xy, gt_frame, gt_labels, gt_xy,
                    threshold):
    """The devkit's accumulate loop, transcribed: per class, boxes listed frame by frame."""
    n = len(det_frame)
    gt_index, tp = [-1] * n, [False] * n
    distance = [np.inf] * n
    frames = sorted(set(det_frame.tolist()) | set(gt_frame.tolist()))
    for c in sorted(set(det_labels.tolist())):
        pooled = [i for f in frames for i in range(n) if det_frame[i] == f and det_labels[i] == c]
        confs = [det_scores[i] for i in pooled]
        sortind = [i for (v, i) in sorted((v, i) for (i, v) in enumerate(confs))][::-1]
        taken = set()
        for k in sortind:
            i = pooled[k]
            frame_gt = [j for j in range(len(gt_frame)) if gt_frame[j] == det_frame[i]]
            min_dist, best = np.inf, None
            for j in frame_gt:
                if gt_labels[j] == c and j not in taken:
                    dist = np.linalg.norm(det_xy[i] - gt_xy[j])
                    if dist < min_dist:
                        min_dist, best = dist, j
            if min_dist < threshold:
                taken.add(best)
                gt_index[i], tp[i], distance[i] = best, True, min_dist
    return np.array(gt_index), np.array(distance), np.array(tp)


def test_highest_score_takes_the_ground_truth():
    r = _match([(0, 0, 0.3, 0.1, 0.0), (0, 0, 0.9, 0.5, 0.0)], [(0, 0, 0.0, 0.0)])
    assert isinstance(r, MatchResult)
    assert r.gt_index.tolist() == [-1, 0]
    assert r.tp.tolist() == [False, True]
    assert r.distance[1] == 0.5 and np.isinf(r.distance[0])


def test_equal_scores_visit_the_later_box_first():
    # The devkit reverses an ascending sort of (score, position): the later box wins the tie
    # even though the earlier one is nearer.
    r = _match([(0, 0, 0.5, 1.0, 0.0), (0, 0, 0.5, 1.5, 0.0)], [(0, 0, 0.0, 0.0)])
    assert r.tp.tolist() == [False, True]
    assert r.distance[1] == 1.5


def test_equal_scores_across_frames_follow_frame_order():
    # Frame 1's box is visited before frame 0's; both frames have their own ground truth.
    r = _match([(1, 0, 0.5, 0.0, 0.0), (0, 0, 0.5, 0.0, 0.0)], [(0, 0, 0.0, 0.0), (1, 0, 0, 0)])
    assert r.gt_index.tolist() == [1, 0]


def test_equidistant_ground_truth_goes_to_the_first_listed():
    r = _match([(0, 0, 0.9, 0.0, 0.0), (0, 0, 0.8, 0.0, 0.0)],
               [(0, 0, -1.0, 0.0), (0, 0, 1.0, 0.0)])
    assert r.gt_index.tolist() == [0, 1]
    assert r.distance.tolist() == [1.0, 1.0]


def test_distance_equal_to_threshold_is_a_false_positive():
    dets, gts = [(0, 0, 0.9, 2.0, 0.0)], [(0, 0, 0.0, 0.0)]
    assert not _match(dets, gts, threshold=2.0).tp[0]
    assert _match(dets, gts, threshold=2.0 + 1e-12).tp[0]
    assert _match(dets, gts, threshold=4.0).distance[0] == 2.0


def test_a_miss_does_not_take_the_ground_truth():
    # The first box's nearest ground truth is too far: it is a false positive and leaves the
    # ground truth for the next box.
    r = _match([(0, 0, 0.9, 3.0, 0.0), (0, 0, 0.5, 1.0, 0.0)], [(0, 0, 0.0, 0.0)])
    assert r.tp.tolist() == [False, True]


def test_greedy_not_optimal_assignment():
    # A takes the nearer ground truth, so B gets the farther one (an optimal assignment would
    # swap them). Both within 2 m.
    r = _match([(0, 0, 0.9, 0.9, 0.0), (0, 0, 0.5, 0.0, 0.0)],
               [(0, 0, 0.0, 0.0), (0, 0, 1.8, 0.0)])
    assert r.gt_index.tolist() == [0, 1]
    np.testing.assert_allclose(r.distance, [0.9, 1.8])


def test_only_same_class_and_frame_match():
    r = _match([(0, 1, 0.9, 0.0, 0.0), (1, 0, 0.9, 0.0, 0.0)], [(0, 0, 0.0, 0.0), (1, 1, 0, 0)])
    assert r.gt_index.tolist() == [-1, -1]


def test_empty_inputs():
    r = _match([], [(0, 0, 0.0, 0.0)])
    assert r.gt_index.shape == (0,) and r.tp.dtype == bool
    r = _match([(0, 0, 0.9, 0.0, 0.0)], [])
    assert r.gt_index.tolist() == [-1] and np.isinf(r.distance[0])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dense", [True, False])
def test_random_against_reference_loop(seed, dense, monkeypatch):
    if not dense:
        monkeypatch.setattr(matching, "DENSE_PAIR_LIMIT", 0)  # candidates from the k-d tree
    rng = np.random.default_rng(seed)
    n, g = 150, 40
    det_frame, gt_frame = rng.integers(0, 5, n), rng.integers(0, 5, g)
    det_labels, gt_labels = rng.integers(0, 3, n), rng.integers(0, 3, g)
    gt_xy = rng.uniform(-6, 6, (g, 2))
    det_xy = rng.uniform(-6, 6, (n, 2))
    near = rng.random(n) < 0.6
    pick = rng.integers(0, g, n)
    det_xy[near] = gt_xy[pick[near]] + rng.normal(0, 0.8, (near.sum(), 2))
    det_frame[near], det_labels[near] = gt_frame[pick[near]], gt_labels[pick[near]]
    det_scores = np.round(rng.random(n), 1)  # many ties
    for th in (0.5, 1.0, 2.0, 4.0):
        got = match(det_frame, det_labels, det_scores, det_xy, gt_frame, gt_labels, gt_xy, th)
        want = reference_match(det_frame, det_labels, det_scores, det_xy, gt_frame, gt_labels,
                               gt_xy, th)
        np.testing.assert_array_equal(got.gt_index, want[0])
        # The devkit's per-pair np.linalg.norm is a dot product that numpy may round
        # differently (numpy 2.4.6: 8 % of random pairs one ulp apart): equal to one ulp.
        np.testing.assert_array_max_ulp(got.distance, want[1], maxulp=1)
        np.testing.assert_array_equal(got.tp, want[2])


def test_bad_input_is_named():
    args = dict(det_frame=[0], det_labels=[0], det_scores=[0.5], det_xy=[[0.0, 0.0]],
                gt_frame=[0], gt_labels=[0], gt_xy=[[0.0, 0.0]])
    with pytest.raises(ValueError, match="det_xy has NaN"):
        match(**{**args, "det_xy": [[np.nan, 0.0]]})
    with pytest.raises(ValueError, match="gt_xy must have shape"):
        match(**{**args, "gt_xy": [[0.0, 0.0, 0.0]]})
    with pytest.raises(ValueError, match="det_scores has 2 rows"):
        match(**{**args, "det_scores": [0.5, 0.4]})
    with pytest.raises(ValueError, match="threshold"):
        match(**args, threshold=0.0)
    with pytest.raises(ValueError, match="det_labels must hold integers"):
        match(**{**args, "det_labels": [0.5]})


def test_in_range_is_strict_and_per_class():
    classes = ("car", "pedestrian", "custom")
    xy = np.array([[50.0, 0.0], [49.9, 0.0], [40.0, 0.0], [30.0, 40.0], [1e4, 0.0]])
    ego = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 10.0], [0.0, 0.0]])
    labels = np.array([0, 0, 1, 0, 2])
    keep = in_range(xy, ego, labels, classes, DEFAULT_CLASS_RANGE)
    assert keep.tolist() == [False, True, False, True, True]  # custom: no range, not filtered
    assert in_range(xy, ego, labels, classes, None).all()
    with pytest.raises(ValueError, match="class_range"):
        in_range(xy, ego, labels, classes, {"car": -1.0})


def test_default_class_range_is_detection_cvpr_2019():
    assert DEFAULT_CLASS_RANGE == {
        "car": 50, "truck": 50, "bus": 50, "trailer": 50, "construction_vehicle": 50,
        "pedestrian": 40, "motorcycle": 40, "bicycle": 40, "traffic_cone": 30, "barrier": 30}


def test_negative_indices_are_refused():
    with pytest.raises(ValueError, match=r"gt_frame\[0\] is negative"):
        match([0], [0], [0.5], [[0.0, 0.0]], [-1], [0], [[0.0, 0.0]])
