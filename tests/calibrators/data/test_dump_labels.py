"""`det_label`: detections that assert a class other than the arg-max of their logits (a
top-K (query, class) decoder gives one query a detection per class)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit, softmax

from calibrators import fit_profile
from calibrators.data import Dump, concat_frames, synthetic_dump
from calibrators.evaluation import evaluate, match_dump
from calibrators.io import load_dump, load_parquet, open_parquet, save_dump, save_parquet
from calibrators.profile import apply_profile, calibrate_detections
from calibrators.scores import TemperatureScaler

CLASSES = ("bus", "trailer")


def box(x: float, y: float) -> list[float]:
    return [x, y, 1.5, 2.9, 11.0, 3.5, 0.0, 0.0, 0.0]


def look_alike_dump(label: np.ndarray | None) -> Dump:
    """One frame, one bus; the detector's one query calls it a trailer (0.6) over a bus
    (0.4). With `label` the query is given twice, once per class."""
    z = np.log([0.4 / 0.6, 0.6 / 0.4])          # sigmoid logits: bus 0.4, trailer 0.6
    n = 1 if label is None else len(label)
    return Dump(classes=CLASSES, score_mode="sigmoid", frame_ids=np.array(["f"]),
                det_frame=np.zeros(n, int), det_logits=np.tile(z, (n, 1, 1)),
                det_boxes=np.tile(box(10.0, 0.0), (n, 1, 1)), gt_frame=np.zeros(1, int),
                gt_labels=np.zeros(1, int), gt_boxes=np.array([box(10.2, 0.1)]),
                det_label=label)


def test_labels_and_scores_follow_the_given_label():
    d = look_alike_dump(np.array([1, 0]))
    assert d.det_labels.tolist() == [1, 0]
    np.testing.assert_allclose(d.det_scores, [0.6, 0.4])
    assert look_alike_dump(None).det_labels.tolist() == [1]        # arg-max without


def test_softmax_scores_are_the_labels_probability():
    z = np.array([[[2.0, 1.0, 0.5]], [[2.0, 1.0, 0.5]]])
    d = Dump(classes=CLASSES, score_mode="softmax", frame_ids=np.array(["f"]),
             det_frame=np.zeros(2, int), det_logits=z, det_boxes=np.zeros((2, 1, 9)),
             gt_frame=np.zeros(0, int), gt_labels=np.zeros(0, int), gt_boxes=np.zeros((0, 9)),
             det_label=np.array([1, 0]))
    np.testing.assert_allclose(d.det_scores, softmax(z[0, 0])[[1, 0]])


@pytest.mark.parametrize("label, words", [
    (np.array([2, 0]), "det_label .*out of range|det_label.*classes"),
    (np.array([0]), "det_label"),
    (np.array([0.5, 1.0]), "det_label"),
])
def test_bad_labels_are_named(label, words):
    with pytest.raises(ValueError, match=words):
        look_alike_dump(np.array([1, 0])).__class__(
            **{**_fields(look_alike_dump(np.array([1, 0]))), "det_label": label})


def _fields(d: Dump) -> dict:
    return {k: getattr(d, k) for k in ("classes", "score_mode", "frame_ids", "det_frame",
                                       "det_logits", "det_boxes", "gt_frame", "gt_labels",
                                       "gt_boxes")}


def test_the_second_class_of_a_query_finds_the_look_alike():
    # Arg-max decoding calls the bus a trailer: bus AP 0. The query's second detection, a
    # bus at 0.4, finds it.
    only_argmax = evaluate(look_alike_dump(None))
    both = evaluate(look_alike_dump(np.array([1, 0])))
    assert only_argmax.class_ap["bus"] == 0.0
    assert both.class_ap["bus"] == pytest.approx(1.0)
    assert both.class_ap["trailer"] == only_argmax.class_ap["trailer"] == 0.0


def test_selections_concatenation_and_files_keep_labels(tmp_path):
    d = look_alike_dump(np.array([1, 0]))
    assert d.select_detections(np.array([False, True])).det_labels.tolist() == [0]
    assert d.select_frames(np.array([True])).det_label.tolist() == [1, 0]
    both = concat_frames([d, d.__class__(**{**_fields(d), "frame_ids": np.array(["g"])})])
    assert both.det_labels.tolist() == [1, 0, 1, 1]          # arg-max where none was given
    save_dump(tmp_path / "d.npz", d)
    assert load_dump(tmp_path / "d.npz").det_label.tolist() == [1, 0]
    save_parquet(tmp_path / "pq", d)
    assert load_parquet(tmp_path / "pq").det_label.tolist() == [1, 0]
    part = open_parquet(tmp_path / "pq").read_part(0, logits_only=True)
    np.testing.assert_allclose(part.det_scores, [0.6, 0.4])
    save_dump(tmp_path / "plain.npz", look_alike_dump(None))
    assert load_dump(tmp_path / "plain.npz").det_label is None   # old dumps: no key


def _top2(dump: Dump) -> Dump:
    """Every detection of `dump` twice: its arg-max class and its second class."""
    z = dump.det_logits[:, -1]
    second = np.argsort(-z, axis=1)[:, 1]
    rows = np.repeat(np.arange(dump.n_detections), 2)
    label = np.stack([dump.det_labels, second], axis=1).reshape(-1)
    take = dump.select_detections(np.ones(dump.n_detections, bool))
    return Dump(**{**_fields(take), "det_frame": take.det_frame[rows],
                   "det_logits": take.det_logits[rows], "det_boxes": take.det_boxes[rows],
                   "det_label": label}, det_cov=take.det_cov[rows], cov_dims=take.cov_dims)


def test_temperature_fit_reads_the_labels_logit():
    d = _top2(synthetic_dump(n_frames=30, temperature=2.0, seed=3))
    profile = fit_profile(d, score_method="temperature", holdout=0.0, calibration=0.0)
    tp = match_dump(d, 2.0).tp
    z = d.det_logits[np.arange(d.n_detections), -1, d.det_label]
    by_hand = TemperatureScaler(mode="sigmoid").fit(z[:, None], tp.astype(np.int64))
    assert profile.temperature == pytest.approx(by_hand.temperature_, rel=1e-9)


def test_serving_scores_the_given_label():
    d = _top2(synthetic_dump(n_frames=10, temperature=2.0, seed=4))
    profile = fit_profile(d, score_method="temperature", holdout=0.0, calibration=0.0)
    out = apply_profile(d, profile)
    assert out.labels.tolist() == d.det_labels.tolist()
    z = d.det_logits[np.arange(d.n_detections), -1, d.det_label]
    np.testing.assert_allclose(out.scores, expit(z / profile.temperature), rtol=1e-12)
    with pytest.raises(ValueError, match="labels"):
        calibrate_detections(profile, logits=d.det_logits[:2, -1], labels=np.array([0, 10]),
                             boxes=d.final_boxes[:2])
