"""Merging of stochastic detections (thesis Algorithms 1 and 2) on hand-made clusters."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit, logit, softmax

from detectors.baselines import (
    dbscan_merge,
    iou_merge,
    merged_dump,
    paired_bev_iou,
    pairwise_bev_iou,
)


def box(x: float, y: float, yaw: float = 0.0, w: float = 2.0, l: float = 4.0) -> list[float]:
    return [x, y, 0.8, w, l, 1.6, yaw, 0.0, 0.0]


# two car boxes 0.4 m / 0.2 m apart: IoU = 3.6·1.8 / (16 − 6.48) ≈ 0.68, and a far one
PAIR = np.array([box(10.0, 5.0), box(10.4, 5.2)])
FAR = np.array([box(30.0, -5.0)])


def test_bev_iou_of_known_shapes():
    rotated = box(0.0, 0.0, yaw=np.pi / 2)
    a = np.array([box(0.0, 0.0), box(0.0, 0.0), box(0.0, 0.0), PAIR[0]])
    b = np.array([box(0.0, 0.0), rotated, box(0.0, 10.0), PAIR[1]])
    np.testing.assert_allclose(paired_bev_iou(a, b), [1.0, 1 / 3, 0.0, 6.48 / 9.52])
    iou = pairwise_bev_iou(np.concatenate([PAIR, FAR]))
    np.testing.assert_allclose(iou, [[1, 6.48 / 9.52, 0], [6.48 / 9.52, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"boxes\[1\] has a non-positive width or length"):
        pairwise_bev_iou(np.array([box(0, 0), box(1, 1, w=0.0)]))


@pytest.mark.parametrize("merge", ["dbscan", "iou"])
def test_two_overlapping_boxes_of_one_class_merge(merge):
    scores, labels = np.array([0.8, 0.6]), np.array([0, 0])
    dims = ("x", "y", "yaw")
    out = (dbscan_merge(PAIR, scores, labels, dims=dims) if merge == "dbscan"
           else iou_merge(PAIR, scores, labels, groups=np.array([7, 7]), dims=dims))
    assert len(out) == 1 and out.n_members.tolist() == [2] and out.cluster.tolist() == [0, 0]
    np.testing.assert_allclose(out.boxes[0], PAIR.mean(axis=0), atol=1e-12)
    assert out.scores[0] == pytest.approx(0.7) and out.labels.tolist() == [0]
    # sample covariance (ddof = 1) of two points a, b is (a − b)(a − b)ᵀ / 2
    diff = np.array([0.4, 0.2, 0.0])
    np.testing.assert_allclose(out.covariances[0], np.outer(diff, diff) / 2, atol=1e-12)
    assert out.dims == dims


def test_different_classes_do_not_merge():
    scores, labels = np.array([0.8, 0.6]), np.array([0, 3])
    out = dbscan_merge(PAIR, scores, labels)
    assert len(out) == 2 and sorted(out.labels.tolist()) == [0, 3]
    assert out.n_members.tolist() == [1, 1]
    np.testing.assert_array_equal(out.covariances, np.zeros((2, 2, 2)))
    # the class-agnostic variant (tried and dropped in the thesis) merges them; tie -> score
    mixed = dbscan_merge(PAIR, scores, labels, classwise=False)
    assert len(mixed) == 1 and mixed.labels.tolist() == [0]


def test_dbscan_noise_points_kept_as_singletons_or_dropped():
    boxes = np.concatenate([PAIR, FAR])
    scores, labels = np.array([0.8, 0.6, 0.9]), np.zeros(3, dtype=int)
    kept = dbscan_merge(boxes, scores, labels)               # min_samples=2: FAR is noise
    assert len(kept) == 2
    assert kept.scores.tolist() == pytest.approx([0.9, 0.7])  # ordered by score
    assert kept.n_members.tolist() == [1, 2] and kept.cluster.tolist() == [1, 1, 0]
    np.testing.assert_array_equal(kept.boxes[0], FAR[0])
    np.testing.assert_array_equal(kept.covariances[0], np.zeros((2, 2)))
    assert np.all(np.isfinite(kept.covariances))
    dropped = dbscan_merge(boxes, scores, labels, noise="drop")
    assert len(dropped) == 1 and dropped.cluster.tolist() == [0, 0, -1]
    # min_samples=1: every detection is a core point, there is no noise to drop
    every = dbscan_merge(boxes, scores, labels, min_samples=1, noise="drop")
    assert every.n_members.tolist() == [1, 2]
    # a stricter eps (IoU >= 0.9 needed) splits the pair
    strict = dbscan_merge(boxes, scores, labels, eps=0.1)
    assert strict.n_members.tolist() == [1, 1, 1]


@pytest.mark.parametrize("merge", ["dbscan", "iou"])
def test_label_by_vote_in_a_mixed_cluster(merge):
    boxes = np.array([box(0.0, 0.0), box(0.1, 0.0), box(0.0, 0.1)])
    scores, labels = np.array([0.9, 0.3, 0.4]), np.array([2, 5, 5])
    out = (dbscan_merge(boxes, scores, labels, classwise=False) if merge == "dbscan"
           else iou_merge(boxes, scores, labels, groups=np.zeros(3, dtype=int)))
    assert len(out) == 1 and out.labels.tolist() == [5]      # two votes beat one higher score
    assert out.scores[0] == pytest.approx(np.mean(scores))


def test_yaw_is_averaged_across_the_wrap():
    boxes = np.array([box(0.0, 0.0, yaw=np.pi - 0.1), box(0.0, 0.0, yaw=-np.pi + 0.1)])
    out = dbscan_merge(boxes, np.array([0.5, 0.5]), np.zeros(2, dtype=int), dims=("x", "yaw"))
    assert len(out) == 1
    assert abs(out.boxes[0, 6]) == pytest.approx(np.pi)        # not 0
    np.testing.assert_allclose(out.covariances[0], [[0.0, 0.0], [0.0, 0.2 ** 2 / 2]],
                               atol=1e-12)


def test_iou_merge_ignores_members_that_do_not_overlap_the_reference():
    boxes = np.concatenate([PAIR, FAR])                  # one cluster (one query), 3 passes
    scores, labels, groups = np.array([0.8, 0.6, 0.5]), np.zeros(3, int), np.zeros(3, int)
    out = iou_merge(boxes, scores, labels, groups)
    assert out.cluster.tolist() == [0, 0, -1] and out.n_members.tolist() == [2]
    np.testing.assert_allclose(out.boxes[0], PAIR.mean(axis=0), atol=1e-12)
    assert out.scores[0] == pytest.approx(0.7)
    # the reference is the top-scoring member (row 0); IoU 0.68 is not above 0.9
    strict = iou_merge(boxes, scores, labels, groups, iou_threshold=0.9)
    assert strict.cluster.tolist() == [0, -1, -1] and strict.n_members.tolist() == [1]
    np.testing.assert_array_equal(strict.boxes[0], PAIR[0])
    # separate clusters stay separate even where their boxes overlap
    two = iou_merge(PAIR, np.array([0.8, 0.6]), np.zeros(2, int), groups=np.array([0, 1]))
    assert two.n_members.tolist() == [1, 1]


def test_empty_input():
    for out in (dbscan_merge(np.zeros((0, 9)), np.zeros(0), np.zeros(0, dtype=int)),
                iou_merge(np.zeros((0, 9)), np.zeros(0), np.zeros(0, dtype=int),
                          groups=np.zeros(0, dtype=int), layer_logits=np.zeros((0, 3, 4)))):
        assert len(out) == 0
        assert out.boxes.shape == (0, 9) and out.covariances.shape == (0, 2, 2)
        assert out.cluster.shape == (0,) and out.labels.dtype == np.int64


def test_merging_does_not_depend_on_input_order():
    rng = np.random.default_rng(0)
    centres = rng.uniform(-40, 40, size=(6, 2))
    boxes = np.array([box(*(c + rng.normal(scale=0.15, size=2)), yaw=rng.normal(scale=0.05))
                      for c in centres for _ in range(4)])
    scores, labels = rng.uniform(0.2, 0.9, len(boxes)), rng.integers(0, 2, len(boxes))
    a = dbscan_merge(boxes, scores, labels, dims=("x", "y", "yaw"))
    perm = rng.permutation(len(boxes))
    b = dbscan_merge(boxes[perm], scores[perm], labels[perm], dims=("x", "y", "yaw"))
    order_a, order_b = np.lexsort(a.boxes[:, :2].T), np.lexsort(b.boxes[:, :2].T)
    np.testing.assert_allclose(a.boxes[order_a], b.boxes[order_b], atol=1e-12)
    np.testing.assert_allclose(a.covariances[order_a], b.covariances[order_b], atol=1e-12)
    np.testing.assert_array_equal(a.n_members[order_a], b.n_members[order_b])


@pytest.mark.parametrize("score_mode", ["sigmoid", "softmax"])
def test_layer_logits_average_the_class_distributions(score_mode):
    rng = np.random.default_rng(1)
    width = 3 if score_mode == "sigmoid" else 4
    layer_logits = rng.normal(scale=2.0, size=(2, 2, width))
    layer_boxes = np.stack([np.stack([PAIR[0] + 0.1, PAIR[0]]), np.stack([PAIR[1] - 0.1,
                                                                          PAIR[1]])])
    out = dbscan_merge(PAIR, np.array([0.8, 0.6]), np.zeros(2, dtype=int),
                       layer_logits=layer_logits, layer_boxes=layer_boxes,
                       score_mode=score_mode)
    assert out.layer_logits.shape == (1, 2, width) and out.layer_boxes.shape == (1, 2, 9)
    if score_mode == "sigmoid":
        expected = logit(expit(layer_logits).mean(axis=0))
        np.testing.assert_allclose(out.layer_logits[0], expected, rtol=1e-10)
    else:
        np.testing.assert_allclose(softmax(out.layer_logits[0], axis=-1),
                                   softmax(layer_logits, axis=-1).mean(axis=0), rtol=1e-10)
    np.testing.assert_allclose(out.layer_boxes[0], layer_boxes.mean(axis=0), atol=1e-12)
    # extreme logits stay finite (log-sum-exp, no logit(1.0) = inf)
    huge = dbscan_merge(PAIR, np.array([1.0, 1.0]), np.zeros(2, dtype=int),
                        layer_logits=np.full((2, 2, 3), 60.0))
    assert np.all(np.isfinite(huge.layer_logits))


def test_merged_frames_write_a_validation_dump():
    final = np.array([[2.0, -3.0], [1.0, -2.0], [-1.0, 0.5]])     # two cars, one pedestrian
    layer_logits = np.stack([final - 0.5, final], axis=1)         # [3, 2, 2]
    boxes = np.concatenate([PAIR, FAR])
    labels = final.argmax(axis=1)
    scores = expit(final.max(axis=1))
    frame = dbscan_merge(boxes, scores, labels, layer_logits=layer_logits,
                         layer_boxes=np.repeat(boxes[:, None], 2, axis=1))
    dump = merged_dump([frame, frame], frame_ids=["a", "b"], classes=("car", "pedestrian"),
                       score_mode="sigmoid", gt_frame=np.array([0, 1]),
                       gt_labels=np.array([0, 1]), gt_boxes=np.concatenate([PAIR[:1], FAR]))
    assert dump.n_detections == 4 and dump.n_layers == 2 and dump.cov_dims == ("x", "y")
    assert dump.det_frame.tolist() == [0, 0, 1, 1]
    np.testing.assert_allclose(dump.det_scores[:2], frame.scores, rtol=1e-12)
    np.testing.assert_allclose(dump.det_cov[:2], frame.covariances)
    with pytest.raises(ValueError, match="has no layer_logits"):
        merged_dump([dbscan_merge(boxes, scores, labels)], ["a"], ("car", "pedestrian"),
                    "sigmoid", np.zeros(0, int), np.zeros(0, int), np.zeros((0, 9)))


@pytest.mark.parametrize("call, match", [
    (lambda: dbscan_merge(PAIR, np.ones(3), np.zeros(2, int)), "scores has 3 rows but boxes"),
    (lambda: dbscan_merge(PAIR, np.ones(2), np.zeros(2, int), eps=1.0), r"eps must be in"),
    (lambda: dbscan_merge(PAIR, np.ones(2), np.zeros(2, int), min_samples=0), "min_samples"),
    (lambda: dbscan_merge(PAIR, np.ones(2), np.zeros(2, int), noise="x"), "noise must be"),
    (lambda: dbscan_merge(PAIR, np.ones(2), np.zeros(2, int), dims=("q",)), "unknown box"),
    (lambda: dbscan_merge(PAIR[:, :7], np.ones(2), np.zeros(2, int)), r"shape \[M, 9\]"),
    (lambda: iou_merge(PAIR, np.ones(2), np.zeros(2, int), np.zeros(3, int)),
     "groups has 3 rows"),
    (lambda: iou_merge(PAIR, np.ones(2), np.zeros(2, int), np.zeros(2, int),
                       iou_threshold=1.0), "iou_threshold must be in"),
    (lambda: iou_merge(PAIR, np.ones(2), np.zeros(2, int), np.zeros(2, int),
                       layer_logits=np.zeros((3, 2, 2))), "layer_logits has 3 rows"),
])
def test_bad_input_names_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()
