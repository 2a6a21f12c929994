"""Per-class temperature: `p = sigmoid(z / T_c)` on the labelled class's logit.

Each `T_c` is fit exactly as the global temperature (`calibrators.scores.
TemperatureScaler` in sigmoid mode: bounded Brent on `log T`, float64, binary NLL of "is a
true positive") on the detections labelled `c`; a class with too few of them takes the pooled
`T` (the same fit on every detection, i.e. the global sigmoid temperature). `T_c > 0`, so the
ranking within a class never changes.
"""

from __future__ import annotations

import numpy as np
from scipy.special import expit

from calibrators.core.checks import check_bounds
from calibrators.scores._calibrator import ClasswiseCalibrator
from calibrators.scores._temperature import TemperatureScaler


class ClassTemperatureScaler(ClasswiseCalibrator):
    """One temperature per class (module docstring).

    Parameters
    ----------
    min_samples, min_each : fallback rule of `ClasswiseCalibrator` (pooled temperature).
    bounds : (low, high) search interval for each `T`, 0 < low < high.
    xtol : Brent's absolute tolerance on `log T`.

    Fitted: `temperature_ [C]` (fallback classes hold `pooled_temperature_`),
    `pooled_temperature_`, besides the base attributes.
    """

    method = "class_temperature"
    _param_size = 1
    _param_text = "[T] with T > 0"
    _hyper = ("min_samples", "min_each", "bounds", "xtol", "shrink")

    def __init__(self, min_samples: int = 50, min_each: int = 5,
                 bounds: tuple[float, float] = (0.01, 100.0), xtol: float = 1e-7,
                 shrink: float = 0.0) -> None:
        self.shrink = shrink
        self.min_samples = min_samples
        self.min_each = min_each
        self.bounds = bounds
        self.xtol = xtol

    def _check_hyper(self) -> None:
        check_bounds(self.bounds)

    def _fit_one(self, z: np.ndarray, hit: np.ndarray, d: np.ndarray | None,
                 w: np.ndarray | None) -> np.ndarray:
        scaler = TemperatureScaler(mode="sigmoid", bounds=self.bounds, xtol=self.xtol)
        if w is None:
            return np.array([scaler.fit(z[:, None], hit.astype(np.int64)).temperature_])
        y, total = hit.astype(np.float64), float(w.sum())
        linear = float(np.dot(w * y, z)) / total

        def mean_nll(log_t: float) -> float:   # the weighted form of `sigmoid_nll`
            return float(np.dot(w, np.logaddexp(0.0, z * np.exp(-log_t)))) / total \
                - linear * float(np.exp(-log_t))

        return np.array([scaler.fit_objective(mean_nll, len(z), 1).temperature_])

    def _apply(self, params: np.ndarray, z: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        return expit(z / params[0])

    def _derive(self) -> None:
        self.temperature_ = np.array([p[0] for p in self.params_])
        self.pooled_temperature_ = float(self.pooled_params_[0])
