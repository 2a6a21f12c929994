"""Binned calibration of confidences: ECE, MCE and the reliability diagram (thesis Eq. 2-19).

Bins are `n_bins` equal-width intervals of [0, 1], `[e_m, e_{m+1})` with the last one closed
so a confidence of exactly 1.0 is counted. `correct` is bool or 0/1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.core.bins import (
    ResultMixin,
    calibration_bins,
    check_n_bins,
    check_weights,
    confidences_and_correct,
)


@dataclass(frozen=True)
class ReliabilityDiagram(ResultMixin):
    """Per-bin data of a reliability diagram with M bins.

    bin_edges: [M+1]; confidence: [M] mean confidence (NaN for an empty bin);
    accuracy: [M] fraction correct (NaN for an empty bin); count: [M] samples per bin.
    `to_dict()` writes NaN as None.
    """

    bin_edges: np.ndarray
    confidence: np.ndarray
    accuracy: np.ndarray
    count: np.ndarray


def reliability_diagram(confidences: np.ndarray, correct: np.ndarray, n_bins: int = 10
                        ) -> ReliabilityDiagram:
    """Reliability diagram of `confidences [N]` against `correct [N]` in `n_bins` bins."""
    n_bins = check_n_bins("n_bins", n_bins)
    conf, hit = confidences_and_correct(confidences, correct)
    edges, count, conf_sum, hit_sum = calibration_bins(conf, hit, n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_conf = np.where(count > 0, conf_sum / count, np.nan)
        acc = np.where(count > 0, hit_sum / count, np.nan)
    return ReliabilityDiagram(edges, mean_conf, acc, count.astype(np.int64))


def _gaps(confidences: np.ndarray, correct: np.ndarray, n_bins: int,
          sample_weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """|acc - conf| `[M]` (0 for empty bins) and bin weights |B_m| / n `[M]`."""
    n_bins = check_n_bins("n_bins", n_bins)
    conf, hit = confidences_and_correct(confidences, correct)
    w = None if sample_weight is None else check_weights(sample_weight, conf.shape[0])
    _, count, conf_sum, hit_sum = calibration_bins(conf, hit, n_bins, w)
    safe = np.where(count > 0, count, 1)
    gap = np.abs(hit_sum - conf_sum) / safe
    return gap, count / count.sum()


def expected_calibration_error(confidences: np.ndarray, correct: np.ndarray,
                               n_bins: int = 10, sample_weight: np.ndarray | None = None
                               ) -> float:
    """ECE = sum_m |B_m|/n · |acc(B_m) − conf(B_m)| over equal-width bins (Eq. 2-19), every
    detection counted `sample_weight [N]` times (>= 0) when given.

    confidences: [N] in [0, 1]; correct: [N] bool or 0/1.
    """
    gap, weight = _gaps(confidences, correct, n_bins, sample_weight)
    return float(np.sum(weight * gap))


def max_calibration_error(confidences: np.ndarray, correct: np.ndarray,
                          n_bins: int = 10) -> float:
    """MCE = max over non-empty bins of |acc(B_m) − conf(B_m)|.

    confidences: [N] in [0, 1]; correct: [N] bool or 0/1.
    """
    gap, weight = _gaps(confidences, correct, n_bins)
    return float(np.max(gap[weight > 0]))
