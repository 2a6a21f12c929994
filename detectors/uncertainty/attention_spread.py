"""Covariance source (b): attention spread (seed 000, Eqs. 1-3).

For one query, take its K largest cross-attention weights w over the BEV grid, renormalise
them to sum to one (W = sum of the top K), and compute the weighted mean mu_K and weighted
covariance C_K of the corresponding cell centres in metres:

    mu_K = 1/W sum w_pq (x_q, y_p)
    C_K  = 1/W sum w_pq ((x_q, y_p) - mu_K)((x_q, y_p) - mu_K)^T
    AS   = det(C_K)

Shapes: attention [N, T] (T cells, any order), centres [T, 2] metres of the same cells
-> AttentionSpread(mean [N, 2], covariance [N, 2, 2], spread [N]).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class AttentionSpread(NamedTuple):
    """Weighted mean `[N, 2]` and covariance `[N, 2, 2]` of the top-K attention, AS `[N]`."""

    mean: Tensor
    covariance: Tensor
    spread: Tensor


def attention_spread(attention: Tensor, centres: Tensor, top_k: int = 6) -> AttentionSpread:
    """Seed 000's attention spread of every query (see the module docstring).

    `attention [N, T]` non-negative weights of each query over the T BEV cells (one decoder
    layer, heads averaged), `centres [T, 2]` the cells' (x, y) in metres, `top_k` the K of
    the paper (6 there, on a 128 x 128 grid).
    """
    if attention.ndim != 2:
        raise ValueError(f"attention must have shape [N, T], got {tuple(attention.shape)}")
    if centres.ndim != 2 or centres.shape != (attention.shape[1], 2):
        raise ValueError(f"centres must have shape [{attention.shape[1]}, 2], "
                         f"got {tuple(centres.shape)}")
    if not 1 <= top_k <= attention.shape[1]:
        raise ValueError(f"top_k must be in [1, {attention.shape[1]}], got {top_k}")
    if not torch.isfinite(attention).all():
        raise ValueError("attention has non-finite weights")
    if (attention < 0).any():
        raise ValueError("attention has negative weights")
    weights, index = attention.topk(top_k, dim=1)  # [N, K]
    total = weights.sum(dim=1, keepdim=True)
    if (total <= 0).any():
        row = int(torch.nonzero(total[:, 0] <= 0)[0])
        raise ValueError(f"attention row {row} has no positive weight among its top {top_k}")
    w = weights / total
    xy = centres.to(attention.dtype)[index]  # [N, K, 2]
    mean = (w[..., None] * xy).sum(dim=1)
    d = xy - mean[:, None]
    cov = torch.einsum("nk,nki,nkj->nij", w, d, d)
    return AttentionSpread(mean=mean, covariance=cov, spread=torch.linalg.det(cov))
