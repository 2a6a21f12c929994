"""From raw logits to class probabilities, labels and scores in both score modes.

`sigmoid`: logits `[N, C]`, one independent probability per class (focal-loss heads).
`softmax`: logits `[N, C + 1]`, the last column is no-object; probabilities are the
first C columns of the softmax over all C + 1.
A detection's label is the arg-max of its object-class logits, unless the detector says
which class it asserts (DETR3D / PETR decode the top-K (query, class) pairs, so one query
can give detections of several classes: `label_scores`); its score is that class's
probability. A temperature never changes the label.
"""

from __future__ import annotations

import numpy as np
from scipy.special import expit, log_softmax

from calibrators.core.checks import as_float_array, check_choice, check_positive
from calibrators.core.vocab import SCORE_MODES

_EPS = 1e-12   # probability_logit: how far from 0 and 1 probabilities are clipped


def class_probabilities(logits: np.ndarray, mode: str, temperature: float = 1.0) -> np.ndarray:
    """Object-class probabilities `[N, C]` from logits `[N, C']` at temperature `T`."""
    z = _logits(logits, mode) / _temperature(temperature)
    if mode == "sigmoid":
        return expit(z)
    return np.exp(log_softmax(z, axis=1))[:, :-1]


def predict(logits: np.ndarray, mode: str, temperature: float = 1.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Labels `[N]` (int64) and scores `[N]` (probability of the label) from logits `[N, C']`."""
    z = _logits(logits, mode)
    n_obj = z.shape[1] if mode == "sigmoid" else z.shape[1] - 1
    labels = np.argmax(z[:, :n_obj], axis=1).astype(np.int64)
    probs = class_probabilities(z, mode, temperature)
    return labels, probs[np.arange(len(labels)), labels]


def label_scores(logits: np.ndarray, labels: np.ndarray, mode: str, temperature: float = 1.0
                 ) -> np.ndarray:
    """`[N]` probability of the given `labels [N]` (any class, not only the arg-max) from
    logits `[N, C']` at temperature `T`."""
    probs = class_probabilities(logits, mode, temperature)
    return probs[np.arange(len(probs)), np.asarray(labels, dtype=np.int64)]


def _logits(logits: np.ndarray, mode: str) -> np.ndarray:
    check_choice("score_mode", mode, SCORE_MODES)
    z = as_float_array("logits", logits, ndim=2)
    if mode == "softmax" and z.shape[1] < 2:
        raise ValueError("logits must have at least 2 columns in softmax mode (C + no-object)")
    if z.shape[1] < 1:
        raise ValueError("logits must have at least 1 column")
    return z


def _temperature(temperature: float) -> float:
    return check_positive("temperature", temperature)


def probability_logit(p: np.ndarray, clip: bool = True) -> np.ndarray:
    """`logit(p)` of probabilities `[N]`, clipped 1e-12 away from 0 and 1 (finite); with
    `clip=False`, ±inf at exactly 0 and 1 (a temperature maps them back to 0 and 1)."""
    q = np.asarray(p, dtype=np.float64)
    if clip:
        q = np.clip(q, _EPS, 1.0 - _EPS)
    with np.errstate(divide="ignore"):
        return np.log(q) - np.log1p(-q)


def probabilities_logits(p: np.ndarray, mode: str) -> np.ndarray:
    """Logits of probabilities `p [..., C']` in score `mode` (at T = 1, clipped as
    `probability_logit`): `logit(p)` (sigmoid), `log(p)` (softmax: defined up to a constant
    per row, which the softmax ignores)."""
    if mode == "sigmoid":
        return probability_logit(p)
    return np.log(np.clip(np.asarray(p, dtype=np.float64), _EPS, 1.0 - _EPS))


def label_logit(logits: np.ndarray, labels: np.ndarray, mode: str) -> np.ndarray:
    """`[N]` logit of the label's probability from final-layer logits `[N, C']` (or the label's
    column alone, `[N, 1]`): the label's logit in sigmoid mode, `logit(p_label)` of the
    softmax at T = 1 in softmax mode."""
    z = np.asarray(logits, dtype=np.float64)
    rows = np.arange(len(z))
    if mode == "sigmoid":
        return z[:, 0] if z.shape[1] == 1 else z[rows, labels]
    return probability_logit(np.exp(log_softmax(z, axis=1)[rows, labels]))
