"""Scores: a detection's class evidence turned into probabilities, and their calibration.

- probabilities (`_probabilities`): `softmax` / `sigmoid` class probabilities at a temperature
  (`class_probabilities`, `predict`, `label_scores`) and the logits of probabilities
  (`probability_logit`, `probabilities_logits`, `label_logit`).
- modulation (`_modulation`): logits modulation over the decoder layers, `modulate_logits`.
- temperature (`_temperature`, with the NLL objectives and their binned / summed forms of
  `_temperature_nll`, searched on `log T` by `_temperature_search`): `p = softmax(z / T)` or
  `sigmoid(z / T)`, `TemperatureScaler`.

- per-class calibrators of the labelled class's logit (`_calibrator` the shared base,
  `_class_temperature`, `_platt`, `_isotonic`, `_histogram`, with the monotone knots of
  `_knots`; built by name and loaded back by `_registry`): `fit(z, labels, tp, distances)`,
  `transform` -> P(true positive), strictly increasing in `z` within a class; fit on the
  mergeable counts of a `ScoreTable` (`_score_table`) when the data come in parts.
"""

from calibrators.scores._calibrator import ClasswiseCalibrator, unfitted
from calibrators.scores._class_temperature import ClassTemperatureScaler
from calibrators.scores._histogram import HistogramBinning
from calibrators.scores._isotonic import IsotonicCalibrator
from calibrators.scores._knots import KnotCalibrator, isotonic_knots, monotone_knots
from calibrators.scores._logistic import fit_logistic
from calibrators.scores._modulation import modulate_logits
from calibrators.scores._platt import PlattScaler
from calibrators.scores._probabilities import (
    class_probabilities,
    label_logit,
    label_scores,
    predict,
    probabilities_logits,
    probability_logit,
)
from calibrators.scores._registry import (
    SCORE_CALIBRATION_METHODS,
    make_score_calibrator,
    score_calibrator_from_dict,
)
from calibrators.scores._score_table import (
    D_WIDTH,
    EXACT_ROWS,
    RANGE_Z_WIDTH,
    Z_WIDTH,
    ScoreRows,
    ScoreTable,
)
from calibrators.scores._temperature import (
    SUBSAMPLE_MIN,
    TemperatureScaler,
    subsample_rows,
    subsample_start,
)
from calibrators.scores._temperature_nll import (
    SIGMOID_BINS,
    SigmoidBins,
    SoftmaxSums,
    row_max,
    sigmoid_nll,
    softmax_mean,
    softmax_nll,
)

__all__ = ["D_WIDTH", "EXACT_ROWS", "RANGE_Z_WIDTH", "SCORE_CALIBRATION_METHODS", "SIGMOID_BINS",
           "SUBSAMPLE_MIN", "Z_WIDTH", "ClassTemperatureScaler", "ClasswiseCalibrator",
           "HistogramBinning", "IsotonicCalibrator", "KnotCalibrator", "PlattScaler", "ScoreRows",
           "ScoreTable", "SigmoidBins", "SoftmaxSums", "TemperatureScaler", "class_probabilities",
           "fit_logistic", "isotonic_knots", "label_logit", "label_scores",
           "make_score_calibrator", "modulate_logits", "monotone_knots", "predict",
           "probabilities_logits", "probability_logit", "row_max", "score_calibrator_from_dict",
           "sigmoid_nll", "softmax_mean", "softmax_nll", "subsample_rows", "subsample_start",
           "unfitted"]
