"""Logits modulation (Cal-DETR, thesis Eq. 4-1), applied post-hoc from the per-layer logits.

A DETR decoder predicts class logits at every layer `l = 1..L`. Where the layers disagree
about a class, the final layer's logit for it is less trustworthy. Modulation scales each
final-layer logit by a certainty factor:

    u_c  = Var_l(z_{l,c})                  population variance (ddof = 0) over the L layers,
                                           per detection and per logit column c
    z̃_c  = z_{L,c} · (1 − tanh(u_c))       Eq. 4-1; 1 − tanh(u) ∈ (0, 1]

Notes:
- The variance is the population variance (divide by L, as `numpy.var`); `torch.var`'s
  default would divide by L − 1. It needs at least two layers.
- The factor only shrinks logits towards 0: a confident logit (|z| large) whose layers
  disagree loses confidence, a stable one (u = 0) is unchanged. In sigmoid mode a negative
  logit moves *up* towards 0 (probability towards 0.5); in softmax mode the distribution
  flattens where the columns are unstable.
- Each column has its own factor, so the arg-max **may change** (an unstable winning class
  can fall below a stable runner-up). `CalibrationProfile.calibrate` therefore keeps the
  detector's label (arg-max of the raw final-layer logits) and uses modulation only to
  re-score it; `modulate_logits` itself returns the modulated logits as they are.
"""

from __future__ import annotations

import numpy as np

from calibrators.core.checks import as_float_array


def modulate_logits(layer_logits: np.ndarray) -> np.ndarray:
    """Modulated final-layer logits `[N, C']` from per-layer logits `[N, L, C']` (L >= 2).

    `z̃ = z_L · (1 − tanh(var_l z))`, variance over the L layers per column (ddof = 0),
    float64 whatever the input dtype. Raises ValueError naming `layer_logits` for a wrong
    shape, non-finite values or L < 2.
    """
    z = as_float_array("layer_logits", layer_logits, ndim=3)
    n_layers = z.shape[1]
    if n_layers < 2:
        raise ValueError(f"layer_logits has {n_layers} decoder layer(s); logits modulation "
                         "needs the variance over L >= 2 layers")
    return z[:, -1] * (1.0 - np.tanh(np.var(z, axis=1)))
