"""Validation dumps (`calibrators.Dump`) from cached passes: vanilla, merged sampling methods.

- `vanilla_dump`: the kept queries of the shipped model with all decoder layers (optionally
  with the attention covariance of the final layer as `det_cov`);
- `merged_sampling_dump`: the N members of a sampling method merged frame by frame, either
  by query index (`iou_merge`, thesis Algorithm 1; MC dropout and sub-ensembles share the
  query initialisation, so query q is the same object in every member) or by class-wise
  DBSCAN on 1 − BEV IoU (Algorithm 2; ensembles, whose queries do not correspond). The
  merged covariance is the cluster's sample covariance; the `max_detections` best merged
  detections per frame are kept, as for the vanilla model, so every row of the report
  scores the same number of detections per frame.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import NamedTuple

import numpy as np
from scipy.special import expit

from calibrators import Dump
from detectors.baselines import MergedDetections, dbscan_merge, iou_merge, merged_dump
from detectors.report.runner import Passes, Truth

MERGE_RULES = ("query", "dbscan")


class MergedDump(NamedTuple):
    """A merged sampling dump and the merging time per frame (ms)."""

    dump: Dump
    merge_ms: float


def vanilla_dump(passes: Passes, truth: Truth, classes: tuple[str, ...],
                 attention_cov: bool = False) -> Dump:
    """The vanilla passes as a dump with L layers; with `attention_cov`, `det_cov [N, 2, 2]`
    is the final layer's attention covariance C_K plus the variance of a uniform position in
    one token cell (cell² / 12 per axis, as `detectors.dumpwriter`)."""
    cov = None
    if attention_cov:
        if passes.attn_cov is None:
            raise ValueError(f"the {passes.method} passes carry no attention covariance")
        cov = passes.attn_cov[:, -1] + np.eye(2) * passes.token_cell ** 2 / 12.0
    return Dump(classes=classes, score_mode="sigmoid", frame_ids=truth.frame_ids,
                det_frame=passes.frame, det_logits=passes.layer_logits,
                det_boxes=passes.layer_boxes, gt_frame=truth.gt_frame,
                gt_labels=truth.gt_labels, gt_boxes=truth.gt_boxes, det_cov=cov,
                cov_dims=("x", "y"))


def merged_sampling_dump(passes: Passes, truth: Truth, classes: tuple[str, ...],
                         rule: str = "query", max_detections: int = 100) -> MergedDump:
    """Merge the members of `passes` per frame by `rule` ("query" or "dbscan")."""
    if rule not in MERGE_RULES:
        raise ValueError(f"rule must be one of {list(MERGE_RULES)}, got {rule!r}")
    order = np.argsort(passes.frame, kind="stable")
    bounds = np.searchsorted(passes.frame[order], np.arange(passes.n_frames + 1))
    merged: list[MergedDetections] = []
    start = time.perf_counter()
    for f in range(passes.n_frames):
        rows = order[bounds[f]:bounds[f + 1]]
        merged.append(_top(_merge_frame(passes, rows, rule), max_detections))
    merge_ms = 1000.0 * (time.perf_counter() - start) / max(passes.n_frames, 1)
    dump = merged_dump(merged, truth.frame_ids, classes, "sigmoid", truth.gt_frame,
                       truth.gt_labels, truth.gt_boxes)
    return MergedDump(dump, merge_ms)


def _merge_frame(passes: Passes, rows: np.ndarray, rule: str) -> MergedDetections:
    """Merge one frame's pooled member detections `rows`."""
    logits = passes.layer_logits[rows].astype(np.float64)          # [M, L', C]
    boxes = passes.layer_boxes[rows, -1].astype(np.float64)        # [M, 9]
    probs = expit(logits[:, -1])
    labels = probs.argmax(axis=1)
    scores = probs[np.arange(len(rows)), labels]
    if rule == "query":
        return iou_merge(boxes, scores, labels, passes.query[rows], layer_logits=logits)
    return dbscan_merge(boxes, scores, labels, eps=0.5, min_samples=2, classwise=True,
                        noise="keep", layer_logits=logits)


def _top(m: MergedDetections, k: int) -> MergedDetections:
    """The `k` best merged detections (they are sorted by descending score)."""
    if len(m) <= k:
        return m
    return replace(m, boxes=m.boxes[:k], scores=m.scores[:k], labels=m.labels[:k],
                   covariances=m.covariances[:k], n_members=m.n_members[:k],
                   layer_logits=None if m.layer_logits is None else m.layer_logits[:k],
                   layer_boxes=None if m.layer_boxes is None else m.layer_boxes[:k])
