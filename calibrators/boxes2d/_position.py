"""Position-dependent score calibration (netcal's `LogisticCalibration(detection=True)`): per
class c, logistic regression of "is a true positive" on the label's logit and the box's
position features as extra linear terms,

    p = sigmoid(a_c·z + b_c + Σ_f g_{c,f}·x_f),    x = (cx, cy, w, h) normalised (`_features`)

`(a_c, b_c, g_c)` minimise the binary NLL plus a light ridge `l2/2 · ((a − 1)² + b² + |g|²)`
towards the identity (separable data keeps finite parameters), by Newton's method on
standardised columns. `a_c >= min_slope > 0` is a bound, so for a fixed box the output is
strictly increasing in z: the ranking of a class's detections changes only through the box
terms. A class with fewer than `min_samples` detections, or fewer than `min_each` true or
false positives, is served by the fit on all detections (the pooled fit) and listed in
`fallback_classes_`, as the per-class calibrators of `calibrators.scores` do.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any, Self

import numpy as np
from scipy.special import expit

from calibrators.boxes2d._features import BOX_FEATURES, check_features
from calibrators.core.bins import as_binary, check_n_bins, check_nonempty
from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_fitted,
    check_index,
    check_length,
    check_min_samples,
)
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.scores import fit_logistic, unfitted

__all__ = ["PositionCalibrator"]


class PositionCalibrator:
    """Per-class logistic calibration of the logit with box-position terms (module docstring).

    Parameters
    ----------
    features : the position features used, among `BOX_FEATURES` ("cx", "cy", "w", "h"),
        in the column order of the `box_features` passed to `fit` and `transform`.
    min_samples, min_each : a class's fallback rule (the pooled fit).
    l2 : ridge weight (>= 0) against the summed (not mean) NLL.
    min_slope : lower bound of `a_c`, in (0, 1).

    Fitted: `n_classes_` (C), `coef_ [C, 2 + F]` rows `(a, b, g_1..g_F)` (a fallback class's
    row is the pooled one), `pooled_coef_ [2 + F]`, `fallback_classes_` (list),
    `n_samples_ [C]`, `n_positives_ [C]` (int64).
    """

    def __init__(self, features: Sequence[str] = BOX_FEATURES, min_samples: int = 50,
                 min_each: int = 5, l2: float = 1.0, min_slope: float = 1e-6) -> None:
        self.features = features
        self.min_samples = min_samples
        self.min_each = min_each
        self.l2 = l2
        self.min_slope = min_slope

    def fit(self, z: np.ndarray, labels: np.ndarray, tp: np.ndarray, n_classes: int,
            box_features: np.ndarray) -> Self:
        """Fit on the label's logit `z [N]`, `labels [N]` in [0, n_classes), `tp [N]` (bool or
        0/1) and `box_features [N, F]` (`box_features(...)` with this calibrator's
        `features`); returns self."""
        min_samples = check_min_samples(self.min_samples)
        min_each = check_n_bins("min_each", self.min_each, minimum=1)
        l2, low = self._hyper()
        c = check_n_bins("n_classes", n_classes, minimum=1)
        x, y, f = self._inputs(z, labels, box_features, c)
        check_nonempty("z", x)
        hit = as_binary("tp", tp, len(x), "z")
        if hit.all() or not hit.any():
            raise FieldError("tp", "tp must hold both true and false positives to fit a score "
                             f"calibrator, got {int(hit.sum())} of {len(hit)} true")
        design = np.column_stack([x, np.ones_like(x), f])
        pooled = fit_logistic(list(design.T), hit, l2, low)
        n_samples = np.bincount(y, minlength=c).astype(np.int64)
        n_pos = np.bincount(y, weights=hit, minlength=c).astype(np.int64)
        coef, fallback = np.empty((c, design.shape[1])), []
        for k in range(c):
            if (n_samples[k] < min_samples or n_pos[k] < min_each
                    or n_samples[k] - n_pos[k] < min_each):
                fallback.append(k)
                coef[k] = pooled
            else:
                rows = y == k
                coef[k] = fit_logistic(list(design[rows].T), hit[rows], l2, low)
        self.n_classes_, self.coef_, self.pooled_coef_ = c, coef, pooled
        self.fallback_classes_ = fallback
        self.n_samples_, self.n_positives_ = n_samples, n_pos
        return self

    def transform(self, z: np.ndarray, labels: np.ndarray, box_features: np.ndarray
                  ) -> np.ndarray:
        """Calibrated probability `[N]` in (0, 1) that each detection is a true positive."""
        check_fitted(self, "coef_")
        x, y, f = self._inputs(z, labels, box_features, self.n_classes_)
        coef = self.coef_[y]
        eta = coef[:, 0] * x + coef[:, 1] + np.einsum("nf,nf->n", coef[:, 2:], f)
        return expit(eta)

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict; `from_dict(to_dict())` serves identical probabilities."""
        check_fitted(self, "coef_")
        return to_jsonable({
            "method": "position_logistic",
            "hyper": {"features": list(self.features), "min_samples": self.min_samples,
                      "min_each": self.min_each, "l2": self.l2, "min_slope": self.min_slope},
            "n_classes": self.n_classes_, "coef": self.coef_, "pooled": self.pooled_coef_,
            "fallback_classes": self.fallback_classes_, "n_samples": self.n_samples_,
            "n_positives": self.n_positives_}, strict=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PositionCalibrator:
        """The fitted calibrator `to_dict` wrote; ValueError naming a missing or bad key."""
        self = unfitted(cls, data, "position calibrator")
        missing = [k for k in ("n_classes", "coef", "pooled", "fallback_classes", "n_samples",
                               "n_positives") if k not in data]
        if missing:
            raise ValueError(f"position calibrator dict lacks {missing[0]!r}")
        n_terms = 2 + len(check_features(self.features))
        c = check_n_bins("n_classes", data["n_classes"], minimum=1)
        coef = as_float_array("coef", data["coef"], ndim=2)
        pooled = as_float_array("pooled", data["pooled"], ndim=1)
        if coef.shape != (c, n_terms) or pooled.shape != (n_terms,) \
                or not (coef[:, 0] > 0).all() or not pooled[0] > 0:
            raise ValueError(f"coef must be [{c}, {n_terms}] and pooled [{n_terms}], each row "
                             "(a, b, g...) with a > 0")
        self.n_classes_, self.coef_, self.pooled_coef_ = c, coef, pooled
        self.fallback_classes_ = [int(k) for k in data["fallback_classes"]]
        self.n_samples_ = as_int_array("n_samples", data["n_samples"])
        self.n_positives_ = as_int_array("n_positives", data["n_positives"])
        return self

    # -- helpers -------------------------------------------------------------------------------
    def _hyper(self) -> tuple[float, float]:
        check_features(self.features)
        if not (isinstance(self.l2, numbers.Real) and 0.0 <= float(self.l2) < np.inf):
            raise FieldError("l2", f"l2 must be a finite number >= 0, got {self.l2!r}")
        if not (isinstance(self.min_slope, numbers.Real) and 0.0 < float(self.min_slope) < 1):
            raise FieldError("min_slope", f"min_slope must be a number in (0, 1), got "
                                          f"{self.min_slope!r}")
        return float(self.l2), float(self.min_slope)

    def _inputs(self, z: object, labels: object, box_features: object, n_classes: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = as_float_array("z", z, ndim=1)
        y = as_int_array("labels", labels)
        check_length("labels", y, len(x), "z")
        check_index("labels", y, n_classes, "classes")
        f = as_float_array("box_features", box_features, ndim=2)
        check_length("box_features", f, len(x), "z")
        width = len(check_features(self.features))
        if f.shape[1] != width:
            raise FieldError("box_features", f"box_features has {f.shape[1]} columns but "
                             f"features names {width}: {list(self.features)}")
        return x, y, f
