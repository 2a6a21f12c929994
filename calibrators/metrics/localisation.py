"""Localisation-aware ECE (LaECE; Oksuz et al. CVPR 2023, Kuzucu et al. ECCV 2024): a
detection's confidence should be the IoU it is expected to reach, 0 for a false positive.

Per class c, over its detections D^c binned by confidence into M equal-width bins,

    LaECE^c = Σ_j |D_j^c| / |D^c| · | mean confidence_j − precision_j · mean IoU of TPs_j |

and `precision_j · mean IoU_j` is the sum of the true positives' IoUs over |D_j^c| (a false
positive counts IoU 0). LaECE is the mean of LaECE^c over the classes that have detections.
As the authors' code (fiveai/detection_calibration): M = 25 bins, the first `[0, 1/M]` and
then `(j/M, (j+1)/M]` (closed on the right), no weighting of classes by size. Their code also
leaves out a class whose error is exactly 0; here it counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.core.bins import ResultMixin, check_n_bins, check_nonempty
from calibrators.core.checks import as_float_array, check_length, check_probabilities
from calibrators.core.errors import FieldError

#: The authors' number of confidence bins.
LAECE_BINS = 25


@dataclass(frozen=True)
class LocalisationECE(ResultMixin):
    """LaECE of K classes (the distinct labels of the detections, sorted).

    value: the mean of `per_class`; classes: [K] labels; per_class: [K] LaECE^c;
    count: [K] detections per class; bin_edges: [M + 1].
    """

    value: float
    classes: np.ndarray
    per_class: np.ndarray
    count: np.ndarray
    bin_edges: np.ndarray


def localisation_ece(confidences: np.ndarray, iou: np.ndarray, classes: np.ndarray,
                     n_bins: int = LAECE_BINS) -> LocalisationECE:
    """LaECE (module docstring) of detections with `confidences [N]` in [0, 1], `iou [N]` in
    [0, 1] (the IoU of a true positive with its ground truth, 0 for a false positive) and
    class labels `classes [N]` (ints or strings). Ignored detections must be left out first."""
    m = check_n_bins("n_bins", n_bins)
    conf = as_float_array("confidences", confidences, ndim=1)
    check_nonempty("confidences", conf)
    check_probabilities("confidences", conf)
    quality = as_float_array("iou", iou, ndim=1)
    check_length("iou", quality, len(conf), "confidences")
    check_probabilities("iou", quality)
    labels = np.asarray(classes)
    if labels.ndim != 1:
        raise FieldError("classes", f"classes must have 1 dimension, got shape {labels.shape}")
    check_length("classes", labels, len(conf), "confidences")
    keys, codes = np.unique(labels, return_inverse=True)
    edges = np.linspace(0.0, 1.0, m + 1)
    # (e_j, e_{j+1}], the first bin closed on the left too
    bins = np.clip(np.searchsorted(edges, conf, side="left") - 1, 0, m - 1)
    cell = codes.reshape(-1) * m + bins
    size = len(keys) * m
    conf_sum = np.bincount(cell, weights=conf, minlength=size).reshape(len(keys), m)
    iou_sum = np.bincount(cell, weights=quality, minlength=size).reshape(len(keys), m)
    count = np.bincount(codes.reshape(-1), minlength=len(keys))
    # Σ_j |D_j|/|D| · |iou_sum_j/|D_j| − conf_sum_j/|D_j|| = Σ_j |iou_sum_j − conf_sum_j| / |D|
    per_class = np.abs(iou_sum - conf_sum).sum(axis=1) / count
    return LocalisationECE(float(per_class.mean()), keys, per_class, count.astype(np.int64),
                           edges)
