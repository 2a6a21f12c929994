"""Covariance source (a), the thesis's: spread of a query's box across decoder layers.

Every decoder layer predicts a box for the same query; the sample covariance (ddof=1) of
those L boxes over the chosen dimensions is the query's box covariance. This is the torch
twin of `calibrators.covariance.layer_spread` (same definition, same dimension names), for
use on model outputs without leaving torch.

    layer_boxes [N, L, 9] -> covariance [N, D, D]
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from calibrators.core.vocab import BOX_INDEX, check_dims


def layer_covariance(layer_boxes: Tensor, dims: Sequence[str] = ("x", "y")) -> Tensor:
    """Sample covariance (ddof=1) of each query's box across its L decoder layers.

    `layer_boxes [N, L, 9]` (x y z w l h yaw vx vy per layer) -> `[N, D, D]` over `dims`.
    Raises ValueError for a wrong shape, fewer than two layers or an unknown dimension.
    """
    if layer_boxes.ndim != 3 or layer_boxes.shape[2] != 9:
        raise ValueError(f"layer_boxes must have shape [N, L, 9], got {tuple(layer_boxes.shape)}")
    n_layers = layer_boxes.shape[1]
    if n_layers < 2:
        raise ValueError(f"layer_boxes needs at least 2 decoder layers for a spread, "
                         f"got {n_layers}")
    x = layer_boxes[..., [BOX_INDEX[d] for d in check_dims(dims)]]  # [N, L, D]
    centred = x - x.mean(dim=1, keepdim=True)
    return torch.einsum("nld,nle->nde", centred, centred) / (n_layers - 1)
