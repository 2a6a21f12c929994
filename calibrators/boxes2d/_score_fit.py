"""The score stage of a 2-D fit: fit each candidate score calibrator on the fitting part's
images, pick the lowest held-out NLL on the calibration part's, as the 3-D fit's score stage
does (`calibrators.fit`), and serve the chosen one (`ScoreStage2D`).

Every candidate calibrates the label's logit `z` (`score_inputs`: the label's logit from
`logits`, or `logit(score)`) against "is a COCO true positive" (`match_labels`):

- `temperature`: one temperature, `p = sigmoid(z / T)` (`TemperatureScaler` on the label's
  logit; always fit, the baseline);
- `class_temperature`, `platt`, `isotonic`, `histogram`: the per-class calibrators of
  `calibrators.scores`;
- `position`: `PositionCalibrator`, per class with the box position terms `cx, cy, w, h`.

Each candidate is fit on the fitting part and scored on the calibration part by the binary
NLL, the ECE and the D-ECE (confidence × box centre, `SELECTION_FEATURES`) of its
probabilities; `auto` picks the lowest NLL. The chosen method is then refit on both parts
together. Without a calibration part `auto` means `temperature` (nothing to choose on).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy.special import expit

from calibrators import metrics
from calibrators.boxes2d._boxes import Detections2D
from calibrators.boxes2d._calibration_errors import detection_ece_2d
from calibrators.boxes2d._features import box_features
from calibrators.boxes2d._fit_options import SCORE_METHODS_2D
from calibrators.boxes2d._labels import MatchLabels
from calibrators.boxes2d._position import PositionCalibrator
from calibrators.core.checks import check_choice
from calibrators.core.selection import choose_lowest_nll
from calibrators.scores import (
    TemperatureScaler,
    make_score_calibrator,
    score_calibrator_from_dict,
)

__all__ = ["SELECTION_FEATURES", "ScoreData", "ScoreStage2D", "fit_score_stage_2d"]

#: The box features of the D-ECE that the fit and its report record (confidence × centre).
SELECTION_FEATURES: tuple[str, ...] = ("cx", "cy")


class ScoreData(NamedTuple):
    """What the score stage reads, one row per detection [N]: the label's logit `z`, the
    label's class index `labels` (C = `n_classes`), `image_size [N, 2]` (width, height),
    the detections and their `MatchLabels` (the outcome: `true_positive`)."""

    z: np.ndarray
    labels: np.ndarray
    image_size: np.ndarray
    detections: Detections2D
    match: MatchLabels
    n_classes: int


@dataclass(frozen=True)
class ScoreStage2D:
    """The fitted score calibration of a 2-D profile: `method` (one of `SCORE_METHODS_2D`),
    the global `temperature` (always fit) and the per-class `calibrator` (None for
    `temperature`)."""

    method: str
    temperature: float
    calibrator: Any = None

    def transform(self, z: np.ndarray, labels: np.ndarray, image_size: np.ndarray | None,
                  bbox: np.ndarray) -> np.ndarray:
        """`[N]` calibrated probability that each detection (label's logit `z [N]`, class
        index `labels [N]`, COCO `bbox [N, 4]` in an image of `image_size [N, 2]`; the size
        is read by `position` alone) is a true positive."""
        if self.calibrator is None:
            return expit(np.asarray(z, dtype=np.float64) / self.temperature)
        if isinstance(self.calibrator, PositionCalibrator):
            feats = box_features(bbox, image_size, self.calibrator.features)
            return self.calibrator.transform(z, labels, feats)
        return self.calibrator.transform(z, labels)

    @property
    def uses_position(self) -> bool:
        """Whether serving reads the box position (and so the image size)."""
        return isinstance(self.calibrator, PositionCalibrator)

    def to_dict(self) -> dict[str, Any]:
        """`{"method", "temperature", "params"}`: params the calibrator's `to_dict()`."""
        return {"method": self.method, "temperature": self.temperature,
                "params": None if self.calibrator is None else self.calibrator.to_dict()}

    @classmethod
    def from_dict(cls, data: Any) -> ScoreStage2D:
        """The stage `to_dict` wrote; ValueError naming a missing or bad key."""
        if not isinstance(data, dict) or set(data) != {"method", "temperature", "params"}:
            raise ValueError("score_calibration must be an object with method, temperature "
                             "and params")
        check_choice("score_calibration.method", data["method"], SCORE_METHODS_2D)
        t = data["temperature"]
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0 < t < np.inf:
            raise ValueError(f"score_calibration.temperature must be a number > 0, got {t!r}")
        params = data["params"]
        if (params is None) != (data["method"] == "temperature"):
            raise ValueError("score_calibration.params must be null for temperature and the "
                             "calibrator's parameters otherwise")
        if params is None:
            return cls("temperature", float(t))
        if data["method"] == "position":
            return cls("position", float(t), PositionCalibrator.from_dict(params))
        calibrator = score_calibrator_from_dict(params)
        if calibrator.method_name != data["method"]:
            raise ValueError(f"score_calibration.params are a {calibrator.method_name!r} "
                             f"calibrator, not {data['method']!r}")
        return cls(data["method"], float(t), calibrator)


def fit_score_stage_2d(data: ScoreData, train: np.ndarray, calib: np.ndarray | None,
                       method: str, min_samples: int
                       ) -> tuple[ScoreStage2D, dict[str, Any]]:
    """The fitted stage and the report's `selection` (`{"chosen", "candidates": {name: {"nll",
    "ece", "d_ece"}}}`, empty candidates when nothing was chosen): `method` is `auto` or a
    name of `SCORE_METHODS_2D`, `train [N]` and `calib [N]` (None: no calibration part) the
    masks of the two parts' counted detections (module docstring)."""
    names = list(SCORE_METHODS_2D) if method == "auto" else [method]
    if method == "auto" and calib is None:
        names = ["temperature"]
    candidates: dict[str, dict[str, float]] = {}
    if calib is not None and len(names) > 1:
        tp = data.match.true_positive
        def held_out(name: str) -> dict[str, float]:
            p = _fit(name, data, train, min_samples).transform(
                data.z[calib], data.labels[calib], data.image_size[calib],
                data.detections.bbox[calib])
            return {"nll": metrics.classification_nll(p, tp[calib]),
                    "ece": metrics.expected_calibration_error(p, tp[calib]),
                    "d_ece": selection_dece(data, calib, p)}

        chosen, candidates = choose_lowest_nll(names, held_out)
    else:
        chosen = names[0]
    both = train if calib is None else train | calib
    return _fit(chosen, data, both, min_samples), {"chosen": chosen, "candidates": candidates}


def selection_dece(data: ScoreData, rows: np.ndarray, scores: np.ndarray) -> float:
    """D-ECE over (confidence, `SELECTION_FEATURES`) of the detections at the mask `rows [N]`
    with calibrated `scores` (one per such row)."""
    m = data.match
    sub = MatchLabels(m.true_positive[rows], m.gt_row[rows], m.iou[rows], m.ignored[rows],
                      m.iou_threshold)
    return detection_ece_2d(data.detections.take(rows), sub, data.image_size[rows],
                            scores=scores, features=SELECTION_FEATURES)


def _fit(name: str, data: ScoreData, rows: np.ndarray, min_samples: int) -> ScoreStage2D:
    """Candidate `name` fit on the detections at the mask `rows [N]` (with the global
    temperature, always fit)."""
    z, labels, tp = data.z[rows], data.labels[rows], data.match.true_positive[rows]
    if tp.all() or not tp.any():
        raise ValueError(f"the score calibration needs both true and false positives; the "
                         f"{int(rows.sum())} detections it is fit on have {int(tp.sum())} "
                         f"true positives (check the categories and iou_threshold)")
    scaler = TemperatureScaler(mode="sigmoid").fit(z[:, None], tp.astype(np.int64))
    temperature = float(scaler.temperature_)
    if name == "temperature":
        return ScoreStage2D(name, temperature)
    if name == "position":
        position = PositionCalibrator(min_samples=min_samples)
        feats = box_features(data.detections.bbox[rows], data.image_size[rows],
                             position.features)
        return ScoreStage2D(name, temperature,
                            position.fit(z, labels, tp, data.n_classes, feats))
    calibrator = make_score_calibrator(name, min_samples=min_samples)
    return ScoreStage2D(name, temperature, calibrator.fit(z, labels, tp, data.n_classes))
