"""BoxeR-2D's prediction head: box offsets from the reference window, and class logits.

    box = (sigma(dx + sigma^-1(x)), sigma(dy + sigma^-1(y)),
           sigma(dw + sigma^-1(w)), sigma(dh + sigma^-1(h)))

with (dx, dy, dw, dh) from a 3-layer perceptron (ReLU, hidden width D) whose last layer
starts at zero, so an untrained head returns its reference window (the paper's appendix E),
and the class logits from one linear projection (one logit for the proposal stage's
foreground/background, C sigmoid logits in the decoder).

Shapes: query [..., D], window [..., 4] cx cy w h in [0, 1] -> (logits [..., K], box [..., 4]).
"""

from __future__ import annotations

from torch import Tensor, nn

from detectors.boxer2d.boxes import inverse_sigmoid
from detectors.model.bev import prior_bias


class WindowHead(nn.Module):
    """Class logits (`n_logits`) and the box as offsets from the reference window."""

    def __init__(self, d_model: int, n_logits: int, prior: float = 0.01) -> None:
        super().__init__()
        self.cls = nn.Linear(d_model, n_logits)
        self.offsets = nn.Sequential(nn.Linear(d_model, d_model), nn.ReLU(inplace=True),
                                     nn.Linear(d_model, d_model), nn.ReLU(inplace=True),
                                     nn.Linear(d_model, 4))
        nn.init.constant_(self.cls.bias, prior_bias(prior))
        nn.init.zeros_(self.offsets[-1].weight)
        nn.init.zeros_(self.offsets[-1].bias)

    def forward(self, query: Tensor, window: Tensor) -> tuple[Tensor, Tensor]:
        return self.cls(query), (self.offsets(query) + inverse_sigmoid(window)).sigmoid()
