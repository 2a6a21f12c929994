"""The DETR-style BEV detector (PillarFormer/TransFusion-L in miniature).

points -> PillarEncoder -> BEVBackbone -> (fine map: heatmap + query init,
token map + positional encoding: cross-attention tokens) -> L decoder layers, each followed
by its class and box head; every layer's centres become the next layer's anchors.

Two options (DetectorConfig): `head` "unified" (one box MLP, the shipped v1 weights) or
"group" (seed 001: one box MLP per class group, group-aware matching in training, option-A
refinement: the next anchor is the group-score-weighted mean of the G centres); and
`token_stride` 4 (tokens = the coarse map, 3.2 m cells with the default grid), 2 (the fine
map, 1.6 m) or 1 (`bev.PillarTokens`, 0.8 m: seed 000's 128 x 128).

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

A group head (G groups) adds, for every layer (the box in `pred_boxes` is then the one of
the group of the layer's top class):

    pred_group_boxes   [L, B, Q, G, 9]   every group head's box
    pred_group_encoded [L, B, Q, G, 10]  the same in regression space
    group_scores       [L, B, Q, G]      summed sigmoid class probabilities per group

`forward(points, need_attention=False)` leaves `attention` out (training: the fused
attention kernel, no [B, heads, Q, T] weight matrix).

Grid metadata lives on the module: `token_grid` / `fine_grid` (BEVGrid: size, cell metres,
origin metres).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from detectors.model.bev import (
    BEVBackbone,
    BEVFeatures,
    BEVGrid,
    PillarEncoder,
    PillarTokens,
    PositionEncoding,
)
from detectors.model.decoder import DecoderLayer
from detectors.model.group_head import GroupDetectionHead
from detectors.model.groups import DEFAULT_GROUPS, class_groups
from detectors.model.heads import DetectionHead
from detectors.model.queries import HeatmapQueries

#: Regression heads and token strides a DetectorConfig may name.
HEADS: tuple[str, ...] = ("unified", "group")
TOKEN_STRIDES: tuple[int, ...] = (4, 2, 1)


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
    # Regression head: "unified" (one box MLP) or "group" (one per class group, seed 001).
    head: str = "unified"
    groups: tuple[tuple[str, ...], ...] = DEFAULT_GROUPS
    # Cross-attention tokens: stride of the token map over the pillar grid (4, 2 or 1).
    token_stride: int = 4
    # Cross-attention window: 0 attends to every token; W > 0 to the W x W tokens around
    # each query's anchor (detectors.model.window_attention; with token_stride 1, seed
    # 000's 0.8 m grid within the forward budget).
    attn_window: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {list(HEADS)}, got {self.head!r}")
        if self.token_stride not in TOKEN_STRIDES:
            raise ValueError(f"token_stride must be one of {list(TOKEN_STRIDES)}, "
                             f"got {self.token_stride}")
        if not 0 <= self.attn_window <= self.grid_size // self.token_stride:
            raise ValueError(f"attn_window must be in [0, {self.grid_size // self.token_stride}]"
                             f" (tokens per side), got {self.attn_window}")
        if self.head == "group":
            class_groups(self.classes, self.groups)  # every class in exactly one group

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DetectorConfig:
        data = dict(data)
        for key in ("features", "classes", "blocks", "keep_all_classes"):
            if key in data:
                data[key] = tuple(data[key])
        if "groups" in data:
            data["groups"] = tuple(tuple(g) for g in data["groups"])
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
        self.token_grid = grid.strided(cfg.token_stride)
        n_classes = len(cfg.classes)
        self.pillars = PillarEncoder(len(cfg.features), cfg.pillar_channels, grid)
        self.backbone = BEVBackbone(self.pillars.out_channels, cfg.c1, cfg.c2, cfg.d_model,
                                    cfg.blocks)
        keep = tuple(cfg.classes.index(c) for c in cfg.keep_all_classes if c in cfg.classes)
        self.queries = HeatmapQueries(cfg.d_model, n_classes, cfg.n_queries, self.fine_grid,
                                      keep)
        if cfg.token_stride == 1:
            self.pillar_tokens = PillarTokens(self.pillars.out_channels, cfg.d_model)
        self.position = PositionEncoding(cfg.d_model, grid.half_extent)
        self.layers = nn.ModuleList(DecoderLayer(cfg.d_model, cfg.n_heads, cfg.d_ffn,
                                                 cfg.dropout, cfg.attn_window, self.token_grid)
                                    for _ in range(cfg.n_layers))
        if cfg.head == "group":
            self.class_group: tuple[int, ...] | None = class_groups(cfg.classes, cfg.groups)
            self.heads = nn.ModuleList(
                GroupDetectionHead(cfg.d_model, n_classes, self.class_group,
                                   self.fine_grid.cell) for _ in range(cfg.n_layers))
        else:
            self.class_group = None
            self.heads = nn.ModuleList(DetectionHead(cfg.d_model, n_classes,
                                                     self.fine_grid.cell)
                                       for _ in range(cfg.n_layers))
        self.register_buffer("token_centres", self.token_grid.centres(), persistent=False)

    def forward(self, points: list[Tensor], need_attention: bool = True) -> dict[str, Tensor]:
        return self.decode(self.encode(points), need_attention)

    def encode(self, points: list[Tensor]) -> Encoded:
        """The trunk: pillars, backbone, heatmap queries and the cross-attention memory."""
        pillars = self.pillars(points)
        bev = self.backbone(pillars)
        init = self.queries(bev.fine)
        tokens = self._tokens(pillars, bev)
        memory = tokens.flatten(2).transpose(1, 2)  # [B, T, D]
        if self.config.attn_window:
            # A windowed attention reads whole token rows; from this strided view of the
            # [B, D, S, S] map every row is a strided read (one copy here made the lidar
            # forward's window gathers ~20x faster). Dense attention keeps the view.
            memory = memory.contiguous()
        memory_pos = self.position(self.token_centres)[None]  # [1, T, D]
        return Encoded(init, memory, memory_pos)

    def _tokens(self, pillars: Tensor, bev: BEVFeatures) -> Tensor:
        """The token map `[B, D, S / token_stride, S / token_stride]`."""
        stride = self.config.token_stride
        if stride == 4:
            return bev.coarse
        if stride == 2:
            return bev.fine
        return self.pillar_tokens(pillars, bev.fine)

    def decode(self, enc: Encoded, need_attention: bool = True) -> dict[str, Tensor]:
        """The decoder layers and their heads on an `encode` result (the output dict)."""
        init, memory, memory_pos = enc.init, enc.memory, enc.memory_pos
        query = init.content
        anchors = init.anchors
        preds, attention, anchor_list = [], [], []
        # A windowed attention writes its weights straight into one [L, B, Q, T] buffer:
        # stacking per-layer maps afterwards cost ~6 ms of a ~45 ms lidar forward.
        keys = memory + memory_pos         # every layer's cross-attention keys, summed once
        buffer = None
        if need_attention and self.config.attn_window:
            buffer = memory.new_zeros(len(self.layers), *query.shape[:2], memory.shape[1])
        for i, (layer, head) in enumerate(zip(self.layers, self.heads, strict=True)):
            query_pos = self.position(anchors)
            out = layer(query, query_pos, memory, memory_pos, need_weights=need_attention,
                        anchors=anchors, weights_out=None if buffer is None else buffer[i],
                        memory_keys=keys)
            query = out.query
            pred = head(query, anchors)
            preds.append(pred)
            attention.append(out.attention)
            anchor_list.append(anchors)
            anchors = pred.next_anchors.detach()
        result = {
            "pred_logits": torch.stack([p.logits for p in preds]),
            "pred_boxes": torch.stack([p.boxes for p in preds]),
            "pred_encoded": torch.stack([p.encoded for p in preds]),
            "anchors": torch.stack(anchor_list),
            "heatmap": init.heatmap,
            "query_labels": init.labels,
            "query_scores": init.scores,
            "token_centres": self.token_centres,
        }
        if need_attention:
            result["attention"] = buffer if buffer is not None else torch.stack(attention)
        if self.class_group is not None:
            result["pred_group_boxes"] = torch.stack([p.group_boxes for p in preds])
            result["pred_group_encoded"] = torch.stack([p.group_encoded for p in preds])
            result["group_scores"] = torch.stack([p.group_scores for p in preds])
        return result
