"""Inputs for the identity property tests: a dump with duplicate boxes, empty frames and frames
without ground truth, the same dump permuted (detections within and across frames, frames
interleaved), and the served values of each detection keyed by its identity."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from hypothesis import strategies as st

from calibrators.data import Dump

#: What a property test draws: a seed for the permutation and which awkward cases to add.
CASES = st.fixed_dictionaries({"seed": st.integers(0, 2**31 - 1),
                               "duplicates": st.integers(0, 3), "empty_frames": st.integers(0, 2),
                               "no_gt_frames": st.integers(0, 2)})


def awkward(dump: Dump, case: dict[str, int]) -> Dump:
    """`dump` with `duplicates` detections repeated (the same box twice), `empty_frames` frames
    with no detections (and no ground truth) added, and the ground truth of `no_gt_frames`
    frames removed."""
    rng = np.random.default_rng(case["seed"] + 1)
    out = dump
    if case["duplicates"]:
        again = rng.choice(dump.n_detections, case["duplicates"], replace=False)
        out = _take_detections(out, np.concatenate([np.arange(dump.n_detections), again]))
    if case["no_gt_frames"]:
        drop = rng.choice(dump.n_frames, case["no_gt_frames"], replace=False)
        g = ~np.isin(out.gt_frame, drop)
        out = replace(out, gt_frame=out.gt_frame[g], gt_labels=out.gt_labels[g],
                      gt_boxes=out.gt_boxes[g])
    if case["empty_frames"]:
        extra = np.array([f"empty-{i}" for i in range(case["empty_frames"])])
        ego = out.ego_translation
        out = replace(out, frame_ids=np.concatenate([out.frame_ids.astype(str), extra]),
                      ego_translation=None if ego is None else
                      np.concatenate([ego, np.zeros((len(extra), 3))]))
    return out


def shuffled(dump: Dump, seed: int) -> tuple[Dump, np.ndarray]:
    """`dump` with its detections permuted across frames and its frames reordered; and
    `perm [N]`: row j of the result is row perm[j] of `dump`."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(dump.n_detections)
    frames = rng.permutation(dump.n_frames)          # new frame k is old frame frames[k]
    new_of_old = np.argsort(frames)
    out = _take_detections(dump, perm)
    ego = dump.ego_translation
    out = replace(out, frame_ids=dump.frame_ids[frames], det_frame=new_of_old[out.det_frame],
                  gt_frame=new_of_old[dump.gt_frame],
                  ego_translation=None if ego is None else ego[frames])
    return out, perm


#: The per-detection arrays of a `Dump`.
_PER_DETECTION = ("det_frame", "det_logits", "det_boxes", "det_cov", "det_hyp_boxes",
                  "det_hyp_scores", "det_label")


def _take_detections(dump: Dump, index: np.ndarray) -> Dump:
    """`dump` with its detections `index` (positions, repeats allowed)."""
    return replace(dump, **{k: None if getattr(dump, k) is None else getattr(dump, k)[index]
                            for k in _PER_DETECTION})


def permuted_document(doc: dict[str, Any], seed: int) -> tuple[dict[str, Any], dict]:
    """A results document with its tokens reordered and each token's boxes permuted, and
    `order`: box j of token t in it is box `order[t][j]` of `doc`."""
    rng = np.random.default_rng(seed)
    tokens = list(doc["results"])
    order = {t: rng.permutation(len(doc["results"][t])) for t in tokens}
    moved = {"meta": doc["meta"], "results": {
        t: [doc["results"][t][k] for k in order[t]] for t in rng.permutation(tokens).tolist()}}
    return moved, order


def assert_same_boxes(first: dict[str, Any], second: dict[str, Any], order: dict) -> None:
    """The calibrated `second` (of `permuted_document`'s document) gives every box what the
    calibrated `first` gives it, with its own detection_row, and lists every token."""
    assert sorted(second["results"]) == sorted(first["results"])
    for t, boxes in second["results"].items():
        for j, box in enumerate(boxes):
            assert box["detection_row"] == j
            original = first["results"][t][int(order[t][j])]
            assert {k: v for k, v in box.items() if k != "detection_row"} == \
                {k: v for k, v in original.items() if k != "detection_row"}


def served(box: dict[str, Any], *keys: str) -> tuple:
    """The served values of one output detection (JSON), comparable with `==`."""
    return tuple(repr(box.get(k)) for k in keys)


#: The served values of a results document's box and of a JSON detection.
NUSCENES_KEYS = ("sample_token", "translation", "size", "detection_name", "detection_score",
                 "detection_score_raw", "covariance", "ellipse", "ellipses")
RECORD_KEYS = ("label", "score", "score_raw", "class_scores", "covariance", "ellipse",
               "ellipses", "distance")


def document_values(doc: dict[str, Any]) -> list[tuple]:
    """The served values of every box of a calibrated results document, sorted (identity not
    included: what a reader of the boxes sees)."""
    return sorted(served(box, *NUSCENES_KEYS) for boxes in doc["results"].values()
                  for box in boxes)


def document_by_row(doc: dict[str, Any]) -> dict[int, tuple]:
    """detection_row -> served values of every box of a calibrated results document."""
    out = {}
    for token, boxes in doc["results"].items():
        for box in boxes:
            assert box["sample_token"] == token
            out[box["detection_row"]] = served(box, *NUSCENES_KEYS)
    return out
