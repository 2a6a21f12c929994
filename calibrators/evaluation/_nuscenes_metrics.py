"""nuScenes detection evaluation (mAP, TP errors, NDS) of a dump, by the devkit's definitions.

What `NuScenesEval` does, vectorised: range filter of ground truth and predictions by class
(`filter_eval_boxes`), matching per class and threshold (`accumulate`, see
`_matching`), 101-point AP with min recall and min precision 0.1 (`calc_ap`), TP
errors at 2 m from the cumulative means resampled on confidence (`calc_tp`), mAP and NDS.

Differences from the devkit, all deliberate:
- no attribute error (dumps carry no attributes); NDS is still normalised by 10 as in the
  devkit, i.e. it equals the devkit's NDS for ground truth without attributes (attr_err = 1);
- no bike-rack filter and no `num_pts == 0` filter (a dump has neither map nor point counts;
  `load_nuscenes` drops ground truth with zero points when it reads it);
- classes missing from `class_range` are not range-filtered (the report lists the ranges used).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from calibrators.core.checks import as_float_array, check_length
from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.json_safe import to_jsonable
from calibrators.data import Dump
from calibrators.evaluation._ap import calc_ap, calc_tp, pr_curve, scale_iou, yaw_diff
from calibrators.evaluation._matching import (
    DEFAULT_CLASS_RANGE,
    Candidates,
    MatchResult,
    candidate_pairs,
    class_limits,
    devkit_rank,
    greedy_match,
    in_range,
)

TP_METRICS = ("trans_err", "scale_err", "orient_err", "vel_err")
# Errors the devkit does not score for a class (its NuScenesEval.evaluate).
NOT_APPLICABLE = {"traffic_cone": ("orient_err", "vel_err"), "barrier": ("vel_err",)}
MEAN_AP_WEIGHT = 5.0
NDS_DENOMINATOR = 10.0  # devkit: mean_ap_weight + 5 TP metrics (attr_err scores 0 here)


@dataclass(frozen=True)
class EvaluationReport:
    """Result of `evaluate`; NaN marks a TP error that does not apply (JSON: null).

    ap: class -> str(threshold) -> AP; class_ap: class -> mean AP over thresholds;
    tp_errors: class -> metric -> error at `tp_threshold`; mean_tp_errors: metric -> nan-mean
    over classes; class_range: class -> range used (None = not filtered).
    """

    mean_ap: float
    nd_score: float
    ap: dict[str, dict[str, float]]
    class_ap: dict[str, float]
    tp_errors: dict[str, dict[str, float]]
    mean_tp_errors: dict[str, float]
    thresholds: tuple[float, ...]
    tp_threshold: float
    class_range: dict[str, float | None]
    n_frames: int
    n_detections: int
    n_gt: int
    n_detections_evaluated: int
    n_gt_evaluated: int

    def to_dict(self) -> dict:
        """A JSON-safe dict (NaN -> None)."""
        return to_jsonable(asdict(self))

    def to_json(self, indent: int | None = 2) -> str:
        """The report as strict JSON (no NaN)."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)


def evaluate(dump: Dump, thresholds: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
             class_range: Mapping[str, float] | None = DEFAULT_CLASS_RANGE,
             scores: np.ndarray | None = None, max_boxes_per_frame: int | None = 500,
             tp_threshold: float = MATCH_THRESHOLD) -> EvaluationReport:
    """Evaluate the final-layer detections of `dump` against its ground truth.

    `scores` [N] optionally replaces the dump's raw scores (e.g. calibrated ones); labels are
    always the dump's. `max_boxes_per_frame` (None = no limit) refuses frames with more
    detections, as the devkit does (500). `class_range=None` disables the range filter.
    """
    if not isinstance(dump, Dump):
        raise ValueError(f"dump must be a calibrators.Dump, got {type(dump).__name__}")
    ths = _thresholds(thresholds)
    tp_th = _thresholds((tp_threshold,), "tp_threshold")[0]
    det_scores = _scores(dump, scores)
    _check_box_count(dump, max_boxes_per_frame)

    limits = class_limits(dump.classes, class_range)
    kept = _Kept.of(dump, det_scores, class_range)
    rank = devkit_rank(kept.det_scores, kept.det_frame)
    pairs = candidate_pairs(rank, kept.det_frame, kept.det_labels, kept.det_boxes[:, :2],
                            kept.gt_frame, kept.gt_labels, kept.gt_boxes[:, :2],
                            max(*ths, tp_th))
    visiting = np.argsort(rank)
    by_class = [visiting[kept.det_labels[visiting] == c] for c in range(len(dump.classes))]
    n_pos = np.bincount(kept.gt_labels, minlength=len(dump.classes))

    ap = _ap_table(dump.classes, kept, rank, pairs, ths, by_class, n_pos)
    tp_result = greedy_match(rank, pairs, tp_th, len(kept.gt_frame))
    tp_errors = _tp_error_table(dump.classes, kept, tp_result, by_class, n_pos)

    class_ap = {name: float(np.mean(list(ap[name].values()))) for name in dump.classes}
    mean_ap = float(np.mean(list(class_ap.values())))
    mean_tp = {m: _nanmean([tp_errors[c][m] for c in dump.classes]) for m in TP_METRICS}
    tp_scores = [max(0.0, 1.0 - e) for e in mean_tp.values()]  # NaN -> 0, as the devkit's max
    nd_score = (MEAN_AP_WEIGHT * mean_ap + float(np.sum(tp_scores))) / NDS_DENOMINATOR
    return EvaluationReport(
        mean_ap=mean_ap, nd_score=nd_score, ap=ap, class_ap=class_ap, tp_errors=tp_errors,
        mean_tp_errors=mean_tp, thresholds=ths, tp_threshold=tp_th,
        class_range={c: (None if np.isinf(r) else float(r))
                     for c, r in zip(dump.classes, limits, strict=True)},
        n_frames=dump.n_frames, n_detections=dump.n_detections, n_gt=len(dump.gt_boxes),
        n_detections_evaluated=int(kept.det_keep.sum()),
        n_gt_evaluated=int(kept.gt_keep.sum()))


def _scores(dump: Dump, scores: np.ndarray | None) -> np.ndarray:
    """`[N]` the scores to rank by: `scores` when given (checked), else the dump's."""
    if scores is None:
        return dump.det_scores
    det_scores = as_float_array("scores", scores, ndim=1)
    check_length("scores", det_scores, dump.n_detections, "det_logits")
    return det_scores


@dataclass(frozen=True)
class _Kept:
    """The final-layer detections and the ground truth within their class's range."""

    det_keep: np.ndarray
    gt_keep: np.ndarray
    det_boxes: np.ndarray
    gt_boxes: np.ndarray
    det_frame: np.ndarray
    gt_frame: np.ndarray
    det_labels: np.ndarray
    gt_labels: np.ndarray
    det_scores: np.ndarray

    @classmethod
    def of(cls, dump: Dump, det_scores: np.ndarray,
           class_range: Mapping[str, float] | None) -> _Kept:
        det_keep = in_range(dump.final_boxes[:, :2], dump.ego_xy(dump.det_frame),
                            dump.det_labels, dump.classes, class_range)
        gt_keep = in_range(dump.gt_boxes[:, :2], dump.ego_xy(dump.gt_frame), dump.gt_labels,
                           dump.classes, class_range)
        return cls(det_keep=det_keep, gt_keep=gt_keep,
                   det_boxes=dump.final_boxes[det_keep], gt_boxes=dump.gt_boxes[gt_keep],
                   det_frame=dump.det_frame[det_keep], gt_frame=dump.gt_frame[gt_keep],
                   det_labels=dump.det_labels[det_keep], gt_labels=dump.gt_labels[gt_keep],
                   det_scores=det_scores[det_keep])


def _ap_table(classes: Sequence[str], kept: _Kept, rank: np.ndarray, pairs: Candidates,
              ths: tuple[float, ...], by_class: list[np.ndarray], n_pos: np.ndarray
              ) -> dict[str, dict[str, float]]:
    """class -> str(threshold) -> AP."""
    ap: dict[str, dict[str, float]] = {c: {} for c in classes}
    for th in ths:
        result = greedy_match(rank, pairs, th, len(kept.gt_frame))
        for c, name in enumerate(classes):
            rows = by_class[c]
            ap[name][str(th)] = calc_ap(pr_curve(result.tp[rows], kept.det_scores[rows],
                                                 n_pos[c]))
    return ap


def _tp_error_table(classes: Sequence[str], kept: _Kept, result: MatchResult,
                    by_class: list[np.ndarray], n_pos: np.ndarray
                    ) -> dict[str, dict[str, float]]:
    """class -> TP metric -> error at the TP threshold's matching `result` (NaN where the
    devkit does not score it)."""
    tp_errors = {}
    for c, name in enumerate(classes):
        rows = by_class[c]
        curve = pr_curve(result.tp[rows], kept.det_scores[rows], n_pos[c])
        errors = _tp_errors(name, rows[result.tp[rows]], result, kept.det_boxes, kept.gt_boxes)
        tp_errors[name] = {m: (np.nan if m in NOT_APPLICABLE.get(name, ()) else
                               calc_tp(curve, errors[m])) for m in TP_METRICS}
    return tp_errors


def _tp_errors(name: str, rows: np.ndarray, result: MatchResult, det_boxes: np.ndarray,
               gt_boxes: np.ndarray) -> dict[str, np.ndarray]:
    """`[K]` errors of the true positives `rows` (visiting order), devkit definitions."""
    det, gt = det_boxes[rows], gt_boxes[result.gt_index[rows]]
    bad = ~(det[:, 3:6] > 0).all(axis=1)
    if bad.any():
        raise ValueError(f"det_boxes has a non-positive size (w, l, h) at a matched {name} "
                         f"detection: {det[np.argmax(bad), 3:6].tolist()}")
    bad = ~(gt[:, 3:6] > 0).all(axis=1)
    if bad.any():
        raise ValueError(f"gt_boxes has a non-positive size (w, l, h) at a matched {name} "
                         f"box: {gt[np.argmax(bad), 3:6].tolist()}")
    period = np.pi if name == "barrier" else 2 * np.pi
    return {
        "trans_err": result.distance[rows],
        "scale_err": 1 - scale_iou(gt[:, 3:6], det[:, 3:6]),
        "orient_err": yaw_diff(gt[:, 6], det[:, 6], period),
        "vel_err": np.sqrt(np.sum((det[:, 7:9] - gt[:, 7:9]) ** 2, axis=1)),
    }


def _check_box_count(dump: Dump, limit: int | None) -> None:
    if limit is None:
        return
    counts = np.bincount(dump.det_frame, minlength=dump.n_frames)
    if len(counts) and counts.max() > limit:
        f = int(np.argmax(counts))
        raise ValueError(f"frame {dump.frame_ids[f]!r} has {int(counts[f])} detections; at most "
                         f"max_boxes_per_frame={limit} are allowed (nuScenes devkit rule)")


def _thresholds(values: Sequence[float], name: str = "thresholds") -> tuple[float, ...]:
    out = tuple(float(v) for v in np.asarray(values, dtype=float).reshape(-1))
    if not out:
        raise ValueError(f"{name} must name at least one distance")
    for v in out:
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be finite distances > 0, got {v}")
    if len(set(out)) != len(out):
        raise ValueError(f"{name} has duplicates: {list(out)}")
    return out


def _nanmean(values: list[float]) -> float:
    arr = np.asarray(values, dtype=float)
    return float(np.mean(arr[~np.isnan(arr)])) if (~np.isnan(arr)).any() else float("nan")


