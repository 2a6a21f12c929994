"""The DETR-style BEV detector (PillarFormer/TransFusion-L in miniature).

points -> PillarEncoder -> BEVBackbone -> (fine map: heatmap + query init,
coarse map + positional encoding: cross-attention tokens) -> L decoder layers, each followed
by its class and box head; every layer's centres become the next layer's anchors.

`forward(points)` takes a list of B point clouds `[P_b, F]` and returns a dict:

    pred_logits   [L, B, Q, C]   raw sigmoid class logits of every decoder layer
    pred_boxes    [L, B, Q, 9]   x y z w l h yaw vx vy, metres/radians/m/s, ego frame
    pred_encoded  [L, B, Q, 10]  the same boxes in regression space (heads.encode_boxes)
    attention     [L, B, Q, T]   head-averaged cross-attention weights over the T = H_t*W_t
                                 BEV tokens (row-major, row = y), every layer
    anchors       [L, B, Q, 2]   x y (metres) each layer's queries were anchored at;
                                 anchors[0] is the heatmap cell centre
    heatmap       [B, C, H, W]   class heatmap logits on the fine grid (stride 2)
    query_labels  [B, Q]         heatmap class each query was drawn from
    query_scores  [B, Q]         heatmap probability at each query's cell
    token_centres [T, 2]         x y (metres) of every token cell centre (attention support)

Grid metadata lives on the module: `token_grid` / `fine_grid` (BEVGrid: size, cell metres,
origin metres).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from detectors.model.bev import BEVBackbone, BEVGrid, PillarEncoder, PositionEncoding
from detectors.model.decoder import DecoderLayer
from detectors.model.heads import DetectionHead
from detectors.model.queries import HeatmapQueries


@dataclass(frozen=True)
class DetectorConfig:
    """Every hyper-parameter of one detector (values live in detectors.registry)."""

    # The sensor, its point features and the class list (detectors.registry, from the sim).
    sensor: str
    features: tuple[str, ...]
    classes: tuple[str, ...]
    # BEV grid: cells per side and metres per cell (fine map: stride 2, tokens: stride 4).
    grid_size: int = 128
    grid_cell: float = 0.8
    # Backbone: pillar feature width, channels of stage 1 and 2, extra conv blocks per stage.
    pillar_channels: int = 32
    c1: int = 64
    c2: int = 96
    blocks: tuple[int, int] = (1, 1)
    # Decoder: model width, attention heads, feed-forward width, decoder layers.
    d_model: int = 64
    n_heads: int = 4
    d_ffn: int = 128
    n_layers: int = 3
    # Queries per frame (heatmap top-K); decoder dropout (also what MC dropout samples).
    n_queries: int = 150
    dropout: float = 0.1
    # Classes exempt from the heatmap's 3x3 local-maximum suppression (TransFusion).
    keep_all_classes: tuple[str, ...] = ("pedestrian", "traffic_cone")
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DetectorConfig:
        data = dict(data)
        for key in ("features", "classes", "blocks", "keep_all_classes"):
            if key in data:
                data[key] = tuple(data[key])
        return cls(**data)


class Encoded(NamedTuple):
    """What the trunk hands the decoder: query init, memory [B, T, D], memory_pos [1, T, D].

    Deep sub-ensemble members share the trunk, so one `encode` serves all their decoders."""

    init: Any
    memory: Tensor
    memory_pos: Tensor


class Detector(nn.Module):
    """BEV DETR detector; see the module docstring for the output dict."""

    def __init__(self, config: DetectorConfig) -> None:
        super().__init__()
        self.config = config
        cfg = config
        grid = BEVGrid(size=cfg.grid_size, cell=cfg.grid_cell)
        self.grid = grid
        self.fine_grid = grid.strided(2)
        self.token_grid = grid.strided(4)
        n_classes = len(cfg.classes)
        self.pillars = PillarEncoder(len(cfg.features), cfg.pillar_channels, grid)
        self.backbone = BEVBackbone(self.pillars.out_channels, cfg.c1, cfg.c2, cfg.d_model,
                                    cfg.blocks)
        keep = tuple(cfg.classes.index(c) for c in cfg.keep_all_classes if c in cfg.classes)
        self.queries = HeatmapQueries(cfg.d_model, n_classes, cfg.n_queries, self.fine_grid,
                                      keep)
        self.position = PositionEncoding(cfg.d_model, grid.half_extent)
        self.layers = nn.ModuleList(DecoderLayer(cfg.d_model, cfg.n_heads, cfg.d_ffn,
                                                 cfg.dropout) for _ in range(cfg.n_layers))
        self.heads = nn.ModuleList(DetectionHead(cfg.d_model, n_classes, self.fine_grid.cell)
                                   for _ in range(cfg.n_layers))
        self.register_buffer("token_centres", self.token_grid.centres(), persistent=False)

    def forward(self, points: list[Tensor]) -> dict[str, Tensor]:
        return self.decode(self.encode(points))

    def encode(self, points: list[Tensor]) -> Encoded:
        """The trunk: pillars, backbone, heatmap queries and the cross-attention memory."""
        pillars = self.pillars(points)
        bev = self.backbone(pillars)
        init = self.queries(bev.fine)
        memory = bev.coarse.flatten(2).transpose(1, 2)  # [B, T, D]
        memory_pos = self.position(self.token_centres)[None]  # [1, T, D]
        return Encoded(init, memory, memory_pos)

    def decode(self, enc: Encoded) -> dict[str, Tensor]:
        """The decoder layers and their heads on an `encode` result (the output dict)."""
        init, memory, memory_pos = enc.init, enc.memory, enc.memory_pos
        query = init.content
        anchors = init.anchors
        logits, encoded, boxes, attention, anchor_list = [], [], [], [], []
        for layer, head in zip(self.layers, self.heads, strict=True):
            query_pos = self.position(anchors)
            out = layer(query, query_pos, memory, memory_pos)
            query = out.query
            pred = head(query, anchors)
            logits.append(pred.logits)
            encoded.append(pred.encoded)
            boxes.append(pred.boxes)
            attention.append(out.attention)
            anchor_list.append(anchors)
            anchors = pred.encoded[..., 0:2].detach()
        return {
            "pred_logits": torch.stack(logits),
            "pred_boxes": torch.stack(boxes),
            "pred_encoded": torch.stack(encoded),
            "attention": torch.stack(attention),
            "anchors": torch.stack(anchor_list),
            "heatmap": init.heatmap,
            "query_labels": init.labels,
            "query_scores": init.scores,
            "token_centres": self.token_centres,
        }
