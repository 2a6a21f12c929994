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
from calibrators.dump import BOX_FIELDS as BOX_DIMS

DIM_INDEX = {name: i for i, name in enumerate(BOX_DIMS)}


def layer_spread(layer_boxes: np.ndarray, dims: Sequence[str] = ("x", "y")) -> np.ndarray:
    """Sample covariance (ddof=1) `[N, D, D]` of each query's box `[N, L, 9]` across layers.

    `dims` names the `D` box fields (keys of `DIM_INDEX`), in the covariance's order.
    """
    idx = dim_indices(dims)
    boxes = as_float_array("layer_boxes", layer_boxes, ndim=3)
    if boxes.shape[2] != len(BOX_DIMS):
        raise ValueError(f"layer_boxes must have shape [N, L, 9], got {boxes.shape}")
    n_layers = boxes.shape[1]
    if n_layers < 2:
        raise ValueError(f"layer_boxes has {n_layers} decoder layer(s); the spread across "
                         "layers needs L >= 2")
    values = boxes[:, :, idx]
    for j, name in enumerate(dims):
        if name == "yaw":
            values[:, :, j] = _wrap(values[:, :, j] - values[:, -1:, j])
    centred = values - values.mean(axis=1, keepdims=True)
    return np.einsum("nli,nlj->nij", centred, centred) / (n_layers - 1)


def dim_indices(dims: Sequence[str]) -> list[int]:
    """Column of each name of `dims` in a 9-field box; distinct known names are required."""
    if isinstance(dims, str):
        raise ValueError(f"dims must be a sequence of box field names, not the string {dims!r}")
    names = list(dims)
    if not names:
        raise ValueError("dims must name at least one box field")
    for name in names:
        if name not in DIM_INDEX:
            raise ValueError(f"dims has unknown box field {name!r}; known: {list(BOX_DIMS)}")
    if len(set(names)) != len(names):
        raise ValueError(f"dims has duplicate names: {names}")
    return [DIM_INDEX[name] for name in names]


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)
