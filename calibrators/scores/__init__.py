"""Scores: a detection's class evidence turned into probabilities, and their calibration.

- probabilities (`_probabilities`): `softmax` / `sigmoid` class probabilities at a temperature
  (`class_probabilities`, `predict`, `label_scores`) and the logits of probabilities
  (`probability_logit`, `probabilities_logits`, `label_logit`).
- modulation (`_modulation`): logits modulation over the decoder layers, `modulate_logits`.
- temperature (`_temperature`, with the NLL objectives and their binned / summed forms of
  `_temperature_nll`, searched on `log T` by `_temperature_search`): `p = softmax(z / T)` or
  `sigmoid(z / T)`, `TemperatureScaler`.

The per-class score calibrators live in `calibrators.score_calibration`.
"""

from calibrators.scores._modulation import modulate_logits
from calibrators.scores._probabilities import (
    class_probabilities,
    label_logit,
    label_scores,
    predict,
    probabilities_logits,
    probability_logit,
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
)

__all__ = ["SIGMOID_BINS", "SUBSAMPLE_MIN", "SigmoidBins", "SoftmaxSums", "TemperatureScaler",
           "class_probabilities", "label_logit", "label_scores", "modulate_logits", "predict",
           "probabilities_logits", "probability_logit", "row_max", "sigmoid_nll",
           "softmax_mean", "subsample_rows", "subsample_start"]
