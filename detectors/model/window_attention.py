"""Cross-attention of each query to a window of the token map around its anchor.

Seed 000 attends over a 128 x 128 BEV grid of 0.8 m cells. Dense attention over its 16 384
tokens costs ~140 ms per lidar frame on this machine's 2 cores (docs/detectors.md), over the
50 ms budget; a query's attention, though, sits within a few metres of its object. So each
query attends to the `window` x `window` tokens centred on its anchor (the box centre of
the previous layer, or the heatmap cell for layer 1), as local-window and deformable DETRs
do. Outside its window a query's attention weight is exactly 0, so the weights scattered
back onto the full grid are a proper attention map over all T tokens, and the seed-000
attention spread reads them unchanged.

Shapes (B frames, Q queries, T = S*S tokens, D channels, H heads, W = window):

    query [B, Q, D], query_pos [B, Q, D], memory [B, T, D], memory_pos [1 | B, T, D],
    anchors [B, Q, 2] (x, y metres)
    -> (out [B, Q, D], weights [B, Q, T] head-averaged, or None)

No key or value is ever projected. With a query's head-h row q_h, the key projection
(W_k, b_k) and the value projection (W_v, b_v) taken per head,

    q_h . (W_k,h m + b_k,h) = (W_k,h^T q_h) . m + const     (the constant cancels in softmax)
    sum_j a_j (W_v,h m_j + b_v,h) = W_v,h (sum_j a_j m_j) + b_v,h      (sum_j a_j = 1)

so the query is folded into token space once (W_k,h^T q_h, [D] per head), the logits are
dot products with the raw gathered tokens, and W_v is applied once to the attention-weighted
token mix. Per layer that is Q*H*W*W*D multiply-adds for each of the two sides, against
Q*W*W*D*D to project the gathered keys and values (16x more at D = 64, H = 4); the result
is the same attention up to float rounding (tested against dense multi-head attention).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from detectors.model.bev import BEVGrid


class WindowCrossAttention(nn.Module):
    """Multi-head attention of every query to a `window` x `window` block of `grid`'s cells
    centred on its anchor (clamped to stay inside the grid)."""

    def __init__(self, d_model: int, n_heads: int, window: int, grid: BEVGrid) -> None:
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model {d_model} is not divisible by n_heads {n_heads}")
        if not 1 <= window <= grid.size:
            raise ValueError(f"attn_window must be in [1, {grid.size}], got {window}")
        self.n_heads = n_heads
        self.window = window
        self.grid = grid
        self.q_proj = nn.Linear(d_model, d_model)
        self.k_proj = nn.Linear(d_model, d_model)
        self.v_proj = nn.Linear(d_model, d_model)
        self.out_proj = nn.Linear(d_model, d_model)
        rows, cols = torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")
        self.register_buffer("offsets", (rows * grid.size + cols).reshape(-1),
                             persistent=False)

    def window_index(self, anchors: Tensor) -> Tensor:
        """`anchors [B, Q, 2]` metres -> `[B, Q, W*W]` flat token indices (row-major, row =
        y) of each query's window: the W x W cells nearest to the anchor, inside the grid."""
        g = self.grid
        pos = (anchors.detach() - g.origin) / g.cell - 0.5 * self.window   # window's corner
        start = torch.floor(pos + 0.5).clamp(0, g.size - self.window).long()  # [B, Q, 2]
        corner = start[..., 1] * g.size + start[..., 0]                      # row = y
        return corner[..., None] + self.offsets

    def forward(self, query: Tensor, query_pos: Tensor, memory: Tensor, memory_pos: Tensor,
                anchors: Tensor, need_weights: bool = True,
                weights_out: Tensor | None = None,
                memory_keys: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """`weights_out [B, Q, T]`, all zeros, receives the weights in place (the detector
        hands each layer its slice of one `[L, B, Q, T]` buffer: stacking per-layer maps
        copied 29 MB per lidar frame). `memory_keys [B, T, D]` = memory + memory_pos, when
        the caller computed it once for all its layers (computed here otherwise)."""
        b, q, d = query.shape
        h, dh = self.n_heads, d // self.n_heads
        t = memory.shape[1]
        if memory_keys is None:
            memory_keys = memory + memory_pos
        index = self.window_index(anchors)                                   # [B, Q, K]
        n = index.shape[-1]
        # The rows of every window, by index_select on the flattened [B*T, D] maps (forward
        # 5-10x faster than gather with an expanded index on the CPU; the backward is a
        # scatter-add, much faster than advanced indexing's index_put). The positions are
        # added to the token map once (`memory_keys`), not to every gathered row: that
        # spares a [B, Q, K, D] sum per layer, and its gradient, in every training step.
        rows = (index + torch.arange(b, device=index.device).view(b, 1, 1) * t).reshape(-1)
        keyed = memory_keys.reshape(b * t, d).index_select(0, rows).view(b * q, n, d)
        values = memory.reshape(b * t, d).index_select(0, rows).view(b * q, n, d)
        # Folded projections (module docstring): qk [B*Q, H, D] is the query in token
        # space, so no [B, Q, K, D] key or value tensor is ever projected. One attention
        # row per (query, head), as plain batched matmuls (much faster on the CPU than
        # scaled_dot_product_attention's flash kernel, built for long query blocks); the
        # logits are laid out [B*Q, K, H] so that the gradient of the gathered rows comes
        # out contiguous (the other orientation copied a [B, Q, K, D] gradient per layer).
        qh = self.q_proj(query + query_pos).view(b * q, h, dh)
        qk = torch.einsum("bhe,hed->bhd", qh, self.k_proj.weight.view(h, dh, d))
        attn = (keyed @ qk.transpose(1, 2) / math.sqrt(dh)).softmax(dim=1)   # [BQ, K, H]
        mixed = attn.transpose(1, 2) @ values                                 # [BQ, H, D]
        out = torch.einsum("bhd,hed->bhe", mixed, self.v_proj.weight.view(h, dh, d))
        out = out + self.v_proj.bias.view(h, dh)
        weights = None
        if need_weights:
            if weights_out is None:
                weights_out = query.new_zeros(b, q, t)
            weights = weights_out.scatter_(2, index, attn.mean(dim=2).view(b, q, n))
        return self.out_proj(out.reshape(b, q, d)), weights
