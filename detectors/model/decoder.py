"""One transformer decoder layer: self-attention, cross-attention to BEV tokens, FFN.

Post-norm as in DETR/TransFusion. Dropout sits on the self-attention weights, on both
attention outputs (before the residual sums) and inside the FFN, so the layer supports MC
dropout (`detectors.infer.enable_mc_dropout`). The cross-attention weights themselves are
not dropped: over B x heads x Q x T entries that one dropout cost a fifth of a CPU training
step, and the weights (averaged over heads) are what the attention-spread covariance
source reads.

Shapes (B frames, Q queries, T = H*W BEV tokens, D channels):

    query [B, Q, D], query_pos [B, Q, D], memory [B, T, D], memory_pos [B, T, D]
    -> DecoderOutput(query [B, Q, D], attention [B, Q, T] | None)

`need_weights=False` skips the weights (None) and lets torch use its fused attention kernel:
training does not read them, and with fine token maps (T = 4 096 or 16 384) the
[B, heads, Q, T] weight matrix is the largest tensor of a training step.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor, nn

from detectors.model.bev import BEVGrid
from detectors.model.window_attention import WindowCrossAttention


class DecoderOutput(NamedTuple):
    """Updated queries `[B, Q, D]` and head-averaged cross-attention weights `[B, Q, T]`
    (None when not asked for)."""

    query: Tensor
    attention: Tensor | None


class DecoderLayer(nn.Module):
    """Self-attention -> cross-attention (weights returned) -> FFN, each with residual + norm."""

    def __init__(self, d_model: int, n_heads: int, d_ffn: int, dropout: float,
                 window: int = 0, grid: BEVGrid | None = None) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d_model, n_heads, dropout=dropout,
                                               batch_first=True)
        # window > 0: each query attends to the window x window tokens of `grid` (the token
        # grid) around its anchor (detectors.model.window_attention); 0: to every token.
        self.cross_attn: nn.Module
        if window:
            if grid is None:
                raise ValueError("a windowed cross-attention needs the token grid")
            self.cross_attn = WindowCrossAttention(d_model, n_heads, window, grid)
        else:
            self.cross_attn = nn.MultiheadAttention(d_model, n_heads, dropout=0.0,
                                                    batch_first=True)
        self.ffn = nn.Sequential(nn.Linear(d_model, d_ffn), nn.ReLU(inplace=True),
                                 nn.Dropout(dropout), nn.Linear(d_ffn, d_model))
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.norm3 = nn.LayerNorm(d_model)
        self.drop1 = nn.Dropout(dropout)
        self.drop2 = nn.Dropout(dropout)
        self.drop3 = nn.Dropout(dropout)

    def forward(self, query: Tensor, query_pos: Tensor, memory: Tensor,
                memory_pos: Tensor, need_weights: bool = True,
                anchors: Tensor | None = None,
                weights_out: Tensor | None = None,
                memory_keys: Tensor | None = None) -> DecoderOutput:
        """`anchors [B, Q, 2]` (metres) place a windowed cross-attention's windows;
        `weights_out [B, Q, T]` (zeros) receives a windowed attention's weights in place;
        `memory_keys [B, T, D]` (memory + memory_pos, computed once by the caller for all
        its layers) spares this layer that sum."""
        if memory_keys is None:
            memory_keys = memory + memory_pos
        q = query + query_pos
        attended, _ = self.self_attn(q, q, query, need_weights=False)
        query = self.norm1(query + self.drop1(attended))
        if isinstance(self.cross_attn, WindowCrossAttention):
            if anchors is None:
                raise ValueError("a windowed cross-attention needs the query anchors")
            attended, weights = self.cross_attn(query, query_pos, memory, memory_pos, anchors,
                                                need_weights=need_weights,
                                                weights_out=weights_out,
                                                memory_keys=memory_keys)
        else:
            attended, weights = self.cross_attn(query + query_pos, memory_keys,
                                                memory, need_weights=need_weights,
                                                average_attn_weights=True)
        query = self.norm2(query + self.drop2(attended))
        query = self.norm3(query + self.drop3(self.ffn(query)))
        return DecoderOutput(query=query, attention=weights)
