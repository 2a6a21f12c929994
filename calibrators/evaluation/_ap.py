"""The nuScenes devkit's precision/recall curve, AP and TP-error arithmetic, step for step.

Mirrors `accumulate` (after matching), `calc_ap`, `calc_tp` and `cummean` of
`nuscenes.eval.detection.algo` / `nuscenes.eval.common.utils`, with the same numpy calls in
the same order so that the numbers agree to the last bit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

N_POINTS = 101  # recall samples 0, 0.01, ..., 1 (DetectionMetricData.nelem)
MIN_RECALL = 0.1
MIN_PRECISION = 0.1


class Curve(NamedTuple):
    """One class at one threshold, resampled on recall = linspace(0, 1, 101).

    precision [101], confidence [101]; `matched_conf` [K] scores of the true positives in
    visiting order (the x-axis the TP errors are resampled on).
    """

    precision: np.ndarray
    confidence: np.ndarray
    matched_conf: np.ndarray


def pr_curve(tp: np.ndarray, conf: np.ndarray, n_pos: int) -> Curve | None:
    """Curve from `tp` [M] bool and `conf` [M] in visiting order; None = devkit "no predictions".

    The devkit returns its no-predictions data when the class has no ground truth or when no
    prediction matched.
    """
    if n_pos == 0 or not np.any(tp):
        return None
    tp_sum = np.cumsum(tp.astype(np.int64)).astype(float)
    fp_sum = np.cumsum((~tp).astype(np.int64)).astype(float)
    prec = tp_sum / (fp_sum + tp_sum)
    rec = tp_sum / float(n_pos)
    rec_interp = np.linspace(0, 1, N_POINTS)
    prec = np.interp(rec_interp, rec, prec, right=0)
    confidence = np.interp(rec_interp, rec, conf, right=0)
    return Curve(prec, confidence, conf[tp])


def calc_ap(curve: Curve | None, min_recall: float = MIN_RECALL,
            min_precision: float = MIN_PRECISION) -> float:
    """Average precision: mean of (precision - min_precision)+ above min_recall, normalised."""
    precision = np.zeros(N_POINTS) if curve is None else np.copy(curve.precision)
    prec = precision[round(100 * min_recall) + 1:]
    prec -= min_precision
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - min_precision)


def calc_tp(curve: Curve | None, errors: np.ndarray, min_recall: float = MIN_RECALL) -> float:
    """Mean TP error between min recall and the maximum recall reached.

    `errors` [K]: the error of each true positive, in visiting order. No predictions -> 1.0.
    """
    if curve is None:
        return 1.0
    resampled = np.interp(curve.confidence[::-1], curve.matched_conf[::-1],
                          cummean(errors)[::-1])[::-1]
    first = round(100 * min_recall) + 1
    non_zero = np.nonzero(curve.confidence)[0]
    last = 0 if len(non_zero) == 0 else int(non_zero[-1])
    if last < first:
        return 1.0
    return float(np.mean(resampled[first:last + 1]))


def cummean(x: np.ndarray) -> np.ndarray:
    """NaN-aware cumulative mean; all-NaN input gives ones (devkit `cummean`)."""
    nan = np.isnan(x)
    if nan.sum() == len(x):
        return np.ones(len(x))
    sums = np.nancumsum(x.astype(float))
    counts = np.cumsum(~nan)
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def yaw_diff(yaw_gt: np.ndarray, yaw_est: np.ndarray, period: np.ndarray | float) -> np.ndarray:
    """`[K]` absolute smallest yaw difference with the given period (devkit angle_diff)."""
    diff = (yaw_gt - yaw_est + period / 2) % period - period / 2
    diff = np.where(diff > np.pi, diff - 2 * np.pi, diff)
    return np.abs(diff)


def scale_iou(size_gt: np.ndarray, size_est: np.ndarray) -> np.ndarray:
    """`[K]` IoU of aligned boxes from sizes `[K, 3]` (w, l, h), devkit `scale_iou`."""
    intersection = np.prod(np.minimum(size_gt, size_est), axis=1)
    union = np.prod(size_gt, axis=1) + np.prod(size_est, axis=1) - intersection
    return intersection / union
