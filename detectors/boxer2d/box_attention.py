"""Box-attention (BoxeR, seed 004, Sec. 3.1): each query attends to a 2 x 2 grid of points
bilinearly sampled inside its reference window, per head, after that head has moved and
enlarged the window (the paper's translation and scaling functions, eqs. 1-4):

    dx = (q W_x + b_x) * w / tau          dy = (q W_y + b_y) * h / tau
    dw = max(q W_w + b_w, 0) * w / tau    dh = max(q W_h + b_h, 0) * h / tau
    window_h = (cx + dx, cy + dy, w + dw, h + dh),        tau = 8

The m x m = 2 x 2 points are the centres of the window's four quarters; each head's
attention weights are a softmax over its four points of a linear map of the query, and the
output is the weighted sum of the sampled values (projected per head), then an output
projection. Initialisation as the paper's appendix E: the attention-weight projection is
zero (uniform weights over the window), the window-offset projection has zero weights and a
random bias.

Shapes (N images, Q queries, D channels, H heads, feature map h_f x w_f):

    query [N, Q, D], window [N, Q, 4] (cx cy w h in [0, 1]), value [N, D, h_f, w_f]
    -> out [N, Q, D]

Coordinates are normalised to the feature map (0 = left / top edge, 1 = right / bottom
edge): a point (u, v) reads the map at pixel (u * w_f - 0.5, v * h_f - 0.5), bilinearly,
zeros outside (`grid_sample` with `align_corners=False`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

TAU = 8.0  # the temperature of eqs. 1-4
GRID = 2   # m: a 2 x 2 grid of sampled points per window and head


class BoxAttention(nn.Module):
    """Multi-head box-attention of `d_model` channels with `n_heads` heads."""

    def __init__(self, d_model: int, n_heads: int, tau: float = TAU) -> None:
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model {d_model} is not divisible by n_heads {n_heads}")
        self.n_heads = n_heads
        self.tau = tau
        self.value_proj = nn.Linear(d_model, d_model)
        self.window_proj = nn.Linear(d_model, n_heads * 4)
        self.weight_proj = nn.Linear(d_model, n_heads * GRID * GRID)
        self.out_proj = nn.Linear(d_model, d_model)
        nn.init.zeros_(self.window_proj.weight)
        nn.init.uniform_(self.window_proj.bias, -1.0, 1.0)
        nn.init.zeros_(self.weight_proj.weight)
        nn.init.zeros_(self.weight_proj.bias)
        step = (torch.arange(GRID, dtype=torch.float32) + 0.5) / GRID - 0.5   # -1/4, +1/4
        gy, gx = torch.meshgrid(step, step, indexing="ij")
        self.register_buffer("grid", torch.stack([gx.reshape(-1), gy.reshape(-1)], -1),
                             persistent=False)                                 # [m*m, 2]

    def head_windows(self, query: Tensor, window: Tensor) -> Tensor:
        """Each head's moved and enlarged window (eqs. 1-4): `[N, Q, D]`, `[N, Q, 4]` ->
        `[N, Q, H, 4]` cx cy w h."""
        n, q, _ = query.shape
        t = self.window_proj(query).view(n, q, self.n_heads, 4)
        size = window[..., None, 2:]                                          # [N, Q, 1, 2]
        centre = window[..., None, :2] + t[..., :2] * size / self.tau
        size = size + F.relu(t[..., 2:]) * size / self.tau
        return torch.cat([centre, size], dim=-1)

    def sample_points(self, windows: Tensor) -> Tensor:
        """The 2 x 2 grid of points of `[..., 4]` windows -> `[..., m*m, 2]` (x, y)."""
        return windows[..., None, :2] + self.grid * windows[..., None, 2:]

    def forward(self, query: Tensor, window: Tensor, value: Tensor) -> Tensor:
        n, q, d = query.shape
        h = self.n_heads
        _, _, hf, wf = value.shape
        v = self.value_proj(value.flatten(2).transpose(1, 2))                 # [N, hf*wf, D]
        v = v.transpose(1, 2).reshape(n * h, d // h, hf, wf)
        points = self.sample_points(self.head_windows(query, window))        # [N, Q, H, 4, 2]
        grid = (2 * points - 1).permute(0, 2, 1, 3, 4).reshape(n * h, q, GRID * GRID, 2)
        sampled = F.grid_sample(v, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=False)                         # [NH, D/H, Q, 4]
        weights = self.weight_proj(query).view(n, q, h, GRID * GRID).softmax(-1)
        weights = weights.permute(0, 2, 1, 3).reshape(n * h, 1, q, GRID * GRID)
        out = (sampled * weights).sum(-1)                                     # [NH, D/H, Q]
        out = out.view(n, d, q).transpose(1, 2)
        return self.out_proj(out)
