"""BoxeR's encoder and decoder layers (post-norm, no dropout: the paper's Table 1).

Shapes (N images, T = h_f * w_f tokens, Q queries, D channels):

    EncoderLayer: tokens [N, T, D], pos [N, T, D], windows [N, T, 4], map [N, D, h_f, w_f]
                  -> [N, T, D]   (box-attention of every token into the map around itself)
    DecoderLayer: query [N, Q, D], pos [N, Q, D], windows [N, Q, 4], memory [N, D, h_f, w_f]
                  -> [N, Q, D]   (self-attention, box-attention into the memory, FFN)
"""

from __future__ import annotations

from torch import Tensor, nn

from detectors.boxer2d.box_attention import BoxAttention


def _ffn(d_model: int, d_ffn: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_model, d_ffn), nn.ReLU(inplace=True),
                         nn.Linear(d_ffn, d_model))


class EncoderLayer(nn.Module):
    """Box-attention (tokens as queries) -> FFN, each with residual + LayerNorm."""

    def __init__(self, d_model: int, n_heads: int, d_ffn: int) -> None:
        super().__init__()
        self.attn = BoxAttention(d_model, n_heads)
        self.ffn = _ffn(d_model, d_ffn)
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)

    def forward(self, tokens: Tensor, pos: Tensor, windows: Tensor, feature_map: Tensor
                ) -> Tensor:
        tokens = self.norm1(tokens + self.attn(tokens + pos, windows, feature_map))
        return self.norm2(tokens + self.ffn(tokens))


class DecoderLayer(nn.Module):
    """Self-attention -> box-attention into the memory -> FFN, each with residual + norm."""

    def __init__(self, d_model: int, n_heads: int, d_ffn: int) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d_model, n_heads, batch_first=True)
        self.cross_attn = BoxAttention(d_model, n_heads)
        self.ffn = _ffn(d_model, d_ffn)
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.norm3 = nn.LayerNorm(d_model)

    def forward(self, query: Tensor, pos: Tensor, windows: Tensor, memory: Tensor) -> Tensor:
        q = query + pos
        attended, _ = self.self_attn(q, q, query, need_weights=False)
        query = self.norm1(query + attended)
        query = self.norm2(query + self.cross_attn(query + pos, windows, memory))
        return self.norm3(query + self.ffn(query))
