"""BoxeR-2D in miniature (seed 004): a two-stage image-plane detector with box-attention.

    images [N, 4, H, W] (RGB + depth; a frame's six cameras are N = 6 images)
      -> ImageBackbone -> tokens at stride 4 (+ sinusoidal encoding of each token's window)
      -> encoder: box-attention of every token into the token map around itself
      -> proposal stage: a WindowHead (foreground logit, box from the token's window) per
         token; the top `n_queries` tokens become the decoder's queries (their features,
         without gradient) and their boxes its first reference windows (without gradient)
      -> decoder layers: self-attention, box-attention into the encoder memory, FFN; each
         layer's WindowHead gives class logits and a box, and that box (without gradient)
         is the next layer's reference window.

`forward(images)` returns a dict (L decoder layers, K = n_queries, C classes, T tokens;
boxes are cx cy w h in [0, 1] of the padded input, `Boxer2DConfig.input_size`):

    pred_logits      [L, N, K, C]  sigmoid class logits of every decoder layer
    pred_boxes       [L, N, K, 4]  boxes of every decoder layer
    ref_windows      [L, N, K, 4]  the reference window each layer's queries started from
    proposal_logits  [N, T]        foreground logit of every encoder token
    proposal_boxes   [N, T, 4]     the token's proposal box
    query_index      [N, K]        the tokens picked as queries (into T, row-major)
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from detectors.boxer2d.backbone import ImageBackbone
from detectors.boxer2d.boxes import sine_encoding
from detectors.boxer2d.config import Boxer2DConfig
from detectors.boxer2d.head import WindowHead
from detectors.boxer2d.layers import DecoderLayer, EncoderLayer

STRIDE = 4


class Boxer2D(nn.Module):
    """The image-plane detector; see the module docstring."""

    def __init__(self, config: Boxer2DConfig) -> None:
        super().__init__()
        self.config = config
        c, d = config, config.d_model
        self.backbone = ImageBackbone(c.c1, c.c2, d)
        self.encoder = nn.ModuleList(EncoderLayer(d, c.n_heads, c.d_ffn)
                                     for _ in range(c.n_encoder))
        self.proposal_head = WindowHead(d, 1)
        self.query_proj = nn.Sequential(nn.Linear(d, d), nn.LayerNorm(d))
        self.decoder = nn.ModuleList(DecoderLayer(d, c.n_heads, c.d_ffn)
                                     for _ in range(c.n_decoder))
        self.heads = nn.ModuleList(WindowHead(d, len(c.classes)) for _ in range(c.n_decoder))
        w, h = c.input_size
        self.register_buffer("anchors", _token_windows(w // STRIDE, h // STRIDE,
                                                       c.anchor_px / w, c.anchor_px / h),
                             persistent=False)                                 # [T, 4]

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        """`images [N, 4, H_in, W_in]` (`data.frame_inputs`) -> the output dict (module
        doc)."""
        n = images.shape[0]
        feature_map = self.backbone(images)                                    # [N, D, h, w]
        _, d, h, w = feature_map.shape
        windows = self.anchors.expand(n, -1, -1)                               # [N, T, 4]
        pos = sine_encoding(windows, d)
        tokens = feature_map.flatten(2).transpose(1, 2)                        # [N, T, D]
        for layer in self.encoder:
            tokens = layer(tokens, pos, windows, tokens.transpose(1, 2).reshape(n, d, h, w))
        memory = tokens.transpose(1, 2).reshape(n, d, h, w)
        prop_logits, prop_boxes = self.proposal_head(tokens, windows)
        prop_logits = prop_logits[..., 0]                                      # [N, T]

        k = min(self.config.n_queries, tokens.shape[1])
        index = prop_logits.detach().topk(k, dim=1).indices                   # [N, K]
        query = self.query_proj(tokens.detach().gather(1, index[..., None].expand(-1, -1, d)))
        ref = prop_boxes.detach().gather(1, index[..., None].expand(-1, -1, 4))
        logits, boxes, refs = [], [], []
        for layer, head in zip(self.decoder, self.heads, strict=True):
            query = layer(query, sine_encoding(ref, d), ref, memory)
            layer_logits, layer_boxes = head(query, ref)
            refs.append(ref)
            logits.append(layer_logits)
            boxes.append(layer_boxes)
            ref = layer_boxes.detach()
        return {"pred_logits": torch.stack(logits), "pred_boxes": torch.stack(boxes),
                "ref_windows": torch.stack(refs), "proposal_logits": prop_logits,
                "proposal_boxes": prop_boxes, "query_index": index}


def _token_windows(w: int, h: int, width: float, height: float) -> Tensor:
    """`[h * w, 4]` reference windows of a `h x w` token map (row-major): each centred on its
    token, `width x height` (normalised)."""
    ys = (torch.arange(h, dtype=torch.float32) + 0.5) / h
    xs = (torch.arange(w, dtype=torch.float32) + 0.5) / w
    cy, cx = torch.meshgrid(ys, xs, indexing="ij")
    size = torch.tensor([width, height]).expand(h * w, 2)
    return torch.cat([cx.reshape(-1, 1), cy.reshape(-1, 1), size], dim=1)
