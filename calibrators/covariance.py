"""Covariance sources: the spread of a query's box across the decoder layers (thesis 4.1.4).

A DETR-style decoder refines each query's box layer by layer; the sample covariance of the
`L` per-layer boxes over the chosen dims is a cheap uncertainty estimate. `yaw` is an angle:
its deviations are wrapped to (-pi, pi] around the final layer's yaw before the covariance is
taken, so boxes at yaw ±pi are close, not 2·pi apart (this assumes the layers agree to within
pi, which holds for any sensible decoder).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.checks import as_float_array
from calibrators.exceptions import FieldError
from calibrators.vocab import BOX_FIELDS, BOX_INDEX, check_dims, wrap_angle


def layer_spread(layer_boxes: np.ndarray, dims: Sequence[str] = ("x", "y")) -> np.ndarray:
    """Sample covariance (ddof=1) `[N, D, D]` of each query's box `[N, L, 9]` across layers.

    `dims` names the `D` box fields (`calibrators.vocab.BOX_FIELDS`), in the covariance's
    order.
    """
    idx = dim_indices(dims)
    boxes = as_float_array("layer_boxes", layer_boxes, ndim=3)
    if boxes.shape[2] != len(BOX_FIELDS):
        raise FieldError("layer_boxes", f"layer_boxes must have shape [N, L, 9], got "
                                        f"{boxes.shape}")
    n_layers = boxes.shape[1]
    if n_layers < 2:
        raise FieldError("layer_boxes", f"layer_boxes has {n_layers} decoder layer(s); the "
                                        "spread across layers needs L >= 2")
    values = boxes[:, :, idx]
    for j, name in enumerate(dims):
        if name == "yaw":
            values[:, :, j] = wrap_angle(values[:, :, j] - values[:, -1:, j])
    centred = values - values.mean(axis=1, keepdims=True)
    return np.einsum("nli,nlj->nij", centred, centred) / (n_layers - 1)


def dim_indices(dims: Sequence[str]) -> list[int]:
    """Column of each name of `dims` in a 9-field box; distinct known names are required."""
    return [BOX_INDEX[name] for name in check_dims(dims)]
