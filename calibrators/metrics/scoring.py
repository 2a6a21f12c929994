"""Proper scoring rules for class probabilities: negative log-likelihood and Brier score.

Both take one of two forms (thesis Eq. 2-17, 2-18):
- binary: `probabilities [N]` = P(positive), `labels [N]` 0/1 or bool;
- multi-class: `probabilities [N, C]`, `labels [N]` int class index in [0, C).
Rows of a multi-class matrix are not required to sum to 1 (sigmoid heads give independent
per-class scores); only the entries are checked to lie in [0, 1].
"""

from __future__ import annotations

import numpy as np

from calibrators.core.bins import as_binary, check_nonempty, check_weights
from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_index,
    check_length,
    check_probabilities,
)

#: probabilities are clipped to [EPS, 1 - EPS] before the log so a confident miss costs
#: -log(1e-12) ≈ 27.6 nats instead of infinity.
EPS = 1e-12


def _inputs(probabilities: object, labels: object
            ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validated `(p, y, binary)`: binary → p [N], y [N] float 0/1; else p [N, C], y [N] int."""
    p = as_float_array("probabilities", probabilities)
    if p.ndim not in (1, 2):
        raise ValueError(f"probabilities must be [N] or [N, C], got shape {p.shape}")
    check_nonempty("probabilities", p)
    check_probabilities("probabilities", p)
    if p.ndim == 1:
        y = as_binary("labels", labels, p.shape[0], "probabilities")
        return p, y.astype(np.float64), True
    if p.shape[1] == 0:
        raise ValueError("probabilities has 0 classes")
    y = as_int_array("labels", labels, ndim=1)
    check_length("labels", y, p.shape[0], "probabilities")
    check_index("labels", y, p.shape[1], "classes")
    return p, y, False


def classification_nll(probabilities: np.ndarray, labels: np.ndarray,
                       sample_weight: np.ndarray | None = None) -> float:
    """Mean negative log-likelihood of the labels (nats), weighted by `sample_weight [N]`
    (>= 0, e.g. the counts of a `ScoreTable`'s rows) when given.

    binary: −mean(y log p + (1 − y) log(1 − p)); multi-class: −mean log p[i, y_i].
    p is clipped to [EPS, 1 − EPS] with EPS = 1e-12.
    """
    p, y, binary = _inputs(probabilities, labels)
    p = np.clip(p, EPS, 1.0 - EPS)
    if binary:
        loss = y * np.log(p) + (1.0 - y) * np.log1p(-p)
    else:
        loss = np.log(p[np.arange(p.shape[0]), y])
    if sample_weight is None:
        return float(-np.mean(loss))
    return float(-np.average(loss, weights=check_weights(sample_weight, p.shape[0],
                                                                 "probabilities")))


def brier_score(probabilities: np.ndarray, labels: np.ndarray) -> float:
    """Brier score.

    binary: mean (p − y)²; multi-class: mean over samples of sum over classes (p − onehot(y))².
    """
    p, y, binary = _inputs(probabilities, labels)
    if binary:
        return float(np.mean((p - y) ** 2))
    onehot = np.zeros_like(p)
    onehot[np.arange(p.shape[0]), y] = 1.0
    return float(np.mean(np.sum((p - onehot) ** 2, axis=1)))
