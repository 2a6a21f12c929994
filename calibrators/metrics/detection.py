"""Detection ECE (D-ECE): calibration of detection confidence jointly over box position.

Küppers et al. 2020, "Multivariate confidence calibration for object detection"; thesis
Eq. 2-20. Bins are the cartesian product of equal-width confidence bins on [0, 1] and
equal-width bins over each feature column (e.g. box centre x, y); in each non-empty bin the
precision (fraction of true positives) is compared to the mean confidence, weighted by |B|/n.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.core.bins import bin_index, check_n_bins, confidences_and_correct
from calibrators.core.checks import as_float_array, check_length


def _bins_per_dim(n_bins: int | Sequence[int], k: int) -> tuple[int, ...]:
    """`(M_conf, M_1, ..., M_K)` from an int (all dims) or a sequence of K + 1 ints."""
    if isinstance(n_bins, (int, np.integer)) and not isinstance(n_bins, bool):
        return (check_n_bins("n_bins", n_bins),) * (k + 1)
    try:
        if isinstance(n_bins, str):
            raise TypeError
        seq = list(n_bins)
    except TypeError:
        raise ValueError(f"n_bins must be an int or a sequence of ints, got {n_bins!r}") from None
    if len(seq) != k + 1:
        raise ValueError(f"n_bins has {len(seq)} entries but confidence + {k} feature columns "
                         f"need {k + 1}")
    return tuple(check_n_bins(f"n_bins[{i}]", m) for i, m in enumerate(seq))


def _feature_ranges(feats: np.ndarray, ranges: Sequence[Sequence[float]] | None) -> np.ndarray:
    """`[K, 2]` (low, high) per feature column: the given `ranges` or the data's min..max."""
    k = feats.shape[1]
    if ranges is None:
        return np.stack([feats.min(axis=0), feats.max(axis=0)], axis=1)
    rng = as_float_array("ranges", ranges)
    if rng.shape != (k, 2):
        raise ValueError(f"ranges must have shape [{k}, 2] (low, high per feature column), "
                         f"got {rng.shape}")
    bad = rng[:, 1] <= rng[:, 0]
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"ranges[{i}] must have low < high, got {rng[i].tolist()}")
    return rng


def detection_ece(confidences: np.ndarray, correct: np.ndarray, features: np.ndarray,
                  n_bins: int | Sequence[int] = (10, 5, 5),
                  ranges: Sequence[Sequence[float]] | None = None) -> float:
    """D-ECE = sum_b |B_b|/n · |precision(B_b) − conf(B_b)| over joint bins.

    confidences: [N] in [0, 1]; correct: [N] bool or 0/1 (true positive);
    features: [N, K] (a 1-D [N] is one feature column), e.g. box centre x, y;
    n_bins: an int used for every dimension, or K + 1 ints (confidence first);
    ranges: optional [K, 2] (low, high) per feature; default each column's min..max.
    Features outside a given range fall in the first / last bin of that column; a constant
    column (min == max) puts everything in its first bin.
    """
    conf, hit = confidences_and_correct(confidences, correct)
    feats = as_float_array("features", features)
    if feats.ndim == 1:
        feats = feats[:, None]
    if feats.ndim != 2:
        raise ValueError(f"features must be [N, K] or [N], got shape {feats.shape}")
    check_length("features", feats, conf.shape[0], "confidences")
    dims = _bins_per_dim(n_bins, feats.shape[1])
    limits = _feature_ranges(feats, ranges)

    indices = [bin_index(conf, np.linspace(0.0, 1.0, dims[0] + 1))]
    for j in range(feats.shape[1]):
        low, high = limits[j]
        if high > low:
            indices.append(bin_index(feats[:, j], np.linspace(low, high, dims[j + 1] + 1)))
        else:
            indices.append(np.zeros(conf.shape[0], dtype=np.int64))
    flat = np.ravel_multi_index(tuple(indices), dims)
    size = int(np.prod(dims))
    conf_sum = np.bincount(flat, weights=conf, minlength=size)
    hit_sum = np.bincount(flat, weights=hit.astype(np.float64), minlength=size)
    # sum_b |B_b|/n · |hits_b/|B_b| − conf_b/|B_b|| = sum_b |hits_b − conf_b| / n
    return float(np.sum(np.abs(hit_sum - conf_sum)) / conf.shape[0])
