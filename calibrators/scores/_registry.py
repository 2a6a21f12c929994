"""Per-class binary score calibrators: the labelled class's logit -> P(true positive).

Every calibrator is fit on `z [N]` (the logit of each detection's labelled class: in sigmoid
mode its raw logit; for softmax the caller passes `logit(p_label)`), `labels [N]` in
[0, C), `tp [N]` and optionally `distances [N]`; `transform` gives probabilities `[N]` in
(0, 1). The label is never changed, and for a fixed class (and distance) the output is
strictly increasing in `z`: the ranking within a class changes only through Platt's range
term. A class with too few detections (or too few true or false positives) is served by the
pooled fit and listed in `fallback_classes_`. `to_dict()` is strict-JSON-able;
`score_calibrator_from_dict` loads any of them back.

Methods (`make_score_calibrator`): "class_temperature", "platt", "platt_range",
"isotonic", "histogram".
"""

from __future__ import annotations

from typing import Any

from calibrators.core.checks import check_choice
from calibrators.core.errors import FieldError
from calibrators.scores._calibrator import ClasswiseCalibrator
from calibrators.scores._class_temperature import ClassTemperatureScaler
from calibrators.scores._histogram import HistogramBinning
from calibrators.scores._isotonic import IsotonicCalibrator
from calibrators.scores._platt import PlattScaler

#: Method name -> (class, fixed keyword arguments).
_METHODS: dict[str, tuple[type[ClasswiseCalibrator], dict[str, Any]]] = {
    "class_temperature": (ClassTemperatureScaler, {}),
    "platt": (PlattScaler, {"range_term": False}),
    "platt_range": (PlattScaler, {"range_term": True}),
    "isotonic": (IsotonicCalibrator, {}),
    "histogram": (HistogramBinning, {}),
}
#: The method names `make_score_calibrator` accepts.
SCORE_CALIBRATION_METHODS: tuple[str, ...] = tuple(_METHODS)


def make_score_calibrator(method: str, **kwargs: Any) -> ClasswiseCalibrator:
    """An unfitted calibrator for `method` (one of `SCORE_CALIBRATION_METHODS`), with
    `kwargs` passed to its class (`range_term` is set by the method name)."""
    check_choice("method", method, SCORE_CALIBRATION_METHODS)
    cls, fixed = _METHODS[method]
    clash = sorted(set(fixed) & set(kwargs))
    if clash:
        raise FieldError("method", f"method {method!r} sets {clash[0]} itself; do not pass it")
    return cls(**fixed, **kwargs)


def score_calibrator_from_dict(data: dict[str, Any]) -> ClasswiseCalibrator:
    """The fitted calibrator of any method from its `to_dict()`."""
    if not isinstance(data, dict):
        raise ValueError(f"a score calibrator must be a dict, got {type(data).__name__}")
    method = data.get("method")
    if not isinstance(method, str):
        raise ValueError(f"method must be one of {list(SCORE_CALIBRATION_METHODS)}, "
                         f"got {method!r}")
    check_choice("method", method, SCORE_CALIBRATION_METHODS)
    return _METHODS[method][0].from_dict(data)


__all__ = [
    "SCORE_CALIBRATION_METHODS",
    "ClassTemperatureScaler",
    "ClasswiseCalibrator",
    "HistogramBinning",
    "IsotonicCalibrator",
    "PlattScaler",
    "make_score_calibrator",
    "score_calibrator_from_dict",
]
