"""Covariance sources: the spread of a query's box across the decoder layers (thesis 4.1.4),
and the one dispatch from a source name to the arrays it reads and the Σ it gives.

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
from calibrators.hypotheses import hypotheses_covariance
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


#: The arrays each covariance source reads: keyword of `CalibrationProfile.calibrate` ->
#: the `Dump` attribute holding it (`auto` is resolved before, `none` reads nothing).
SOURCE_ARRAYS: dict[str, dict[str, str]] = {
    "given": {"covariances": "det_cov"},
    "layers": {"layer_boxes": "det_boxes"},
    "hypotheses": {"hyp_boxes": "det_hyp_boxes", "hyp_scores": "det_hyp_scores"},
    "none": {},
}


def source_covariance(source: str, dims: Sequence[str], *,
                      covariances: np.ndarray | None = None,
                      layer_boxes: np.ndarray | None = None,
                      hyp_boxes: np.ndarray | None = None,
                      hyp_scores: np.ndarray | None = None) -> np.ndarray | None:
    """`[N, D, D]` uncalibrated Σ over `dims` from covariance `source`: the given
    `covariances [N, D, D]`, the spread of `layer_boxes [N, L, 9]` (`layer_spread`), the
    spread of the box hypotheses `hyp_boxes [N, H, 9]` weighted by `hyp_scores [N, H]`
    (`hypotheses_covariance`), or None (`none`)."""
    if source == "given":
        return covariances
    if source == "layers":
        return layer_spread(layer_boxes, dims)
    if source == "hypotheses":
        return hypotheses_covariance(hyp_boxes, hyp_scores, dims)
    return None
