"""The covariance and region stages of an exported profile as torch modules (float64).

Mirrors `calibrators.covariance` (`layer_spread`, `hypotheses_covariance`), `calibrators.profile`
(`_calibrate`: `_scaled`, `_regions`) and `calibrators.regions`: `Σ` from the layer
spread (`LayerSpread`) or the box hypotheses (`HypothesesSpread`), `Σ' = [s_c·]Σ + k_c·d·I`
(`CovarianceScaling`), the eigen-decomposition of its x, y block (`EllipseAxes`) and the
Mahalanobis radius of each level (`GaussianRadii`, `ConformalRadii`).

onnxruntime has no float64 `Atan`, so the major-axis angle uses `atan2` built from `+ − × ÷`
and `sqrt`: two half-angle reductions and a short series, within a few ulps of
`numpy.arctan2`, the same arithmetic in torch and in the ONNX graph. Constants float32 cannot
hold exactly (pi, the series) are float64 buffers (see `detectors.export.scores`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from detectors.export.scores import constant


class _BoxColumns(nn.Module):
    """The box columns `index [D]` a spread is taken over, which of them are angles
    (`yaw [D]`), and pi."""

    def __init__(self, index: list[int], yaw: list[bool]) -> None:
        super().__init__()
        self.register_buffer("index", torch.tensor(index, dtype=torch.int64))
        self.register_buffer("yaw", torch.tensor(yaw, dtype=torch.bool))
        self.any_yaw = bool(any(yaw))
        self.register_buffer("pi", constant(math.pi))


class LayerSpread(_BoxColumns):
    """Sample covariance (ddof = 1) `[N, D, D]` of layer boxes `[N, L, 9]` over the box
    columns `index [D]`; the columns at `yaw [D]` (True) are angles, wrapped to (−pi, pi]
    around the final layer's before the covariance is taken."""

    def forward(self, layer_boxes: Tensor) -> Tensor:
        values = layer_boxes.index_select(2, self.index)                      # [N, L, D]
        if self.any_yaw:   # calibrators.core.vocab.wrap_angle: pi − mod(pi − a, 2·pi)
            turn = self.pi - (values - values[:, -1:])
            wrapped = self.pi - (turn - 2.0 * self.pi * torch.floor(turn / (2.0 * self.pi)))
            values = torch.where(self.yaw, wrapped, values)
        centred = values - values.mean(dim=1, keepdim=True)
        return torch.matmul(centred.transpose(1, 2), centred) / (values.shape[1] - 1)


class HypothesesSpread(_BoxColumns):
    """Group-score-weighted covariance `[N, D, D]` of box hypotheses `[N, H, 9]` with scores
    `[N, H]` over the box columns `index [D]` (weights `s / Σ s`, equal where a row's scores
    sum to 0); the columns at `yaw [D]` (True) are wrapped to (−pi, pi] around the
    highest-scoring hypothesis's yaw before the covariance is taken."""

    def forward(self, hyp_boxes: Tensor, hyp_scores: Tensor) -> Tensor:
        values = hyp_boxes.to(torch.float64).index_select(2, self.index)      # [N, H, D]
        scores = hyp_scores.to(torch.float64)                                  # [N, H]
        total = scores.sum(dim=1, keepdim=True)
        equal = torch.ones_like(scores) / scores.shape[1]
        safe = torch.where(total > 0.0, total, torch.ones_like(total))
        weights = torch.where(total > 0.0, scores / safe, equal)
        if self.any_yaw:   # around the top hypothesis, as calibrators.core.vocab.wrap_angle
            top = scores.argmax(dim=1, keepdim=True).unsqueeze(2)             # [N, 1, 1]
            ref = values.gather(1, top.expand(-1, 1, values.shape[2]))         # [N, 1, D]
            turn = self.pi - (values - ref)
            wrapped = ref + (self.pi - (turn - 2.0 * self.pi
                                        * torch.floor(turn / (2.0 * self.pi))))
            values = torch.where(self.yaw, wrapped, values)
        mean = (weights.unsqueeze(2) * values).sum(dim=1, keepdim=True)        # [N, 1, D]
        centred = values - mean
        cov = torch.matmul((weights.unsqueeze(2) * centred).transpose(1, 2), centred)
        return 0.5 * (cov + cov.transpose(1, 2))


class CovarianceScaling(nn.Module):
    """`Σ' = s_c·Σ + k_c·d·I` `[N, D, D]` per label (`scale` None: `Σ + k_c·d·I`);
    `k [C]`, `scale [C] | None`."""

    def __init__(self, k: Tensor, scale: Tensor | None, dim: int) -> None:
        super().__init__()
        self.register_buffer("k", k.to(torch.float64))
        self.shrink = scale is not None
        self.register_buffer("scale", (scale if scale is not None else torch.ones_like(k))
                             .to(torch.float64))
        self.register_buffer("eye", torch.eye(dim, dtype=torch.float64))

    def forward(self, base: Tensor, distances: Tensor, labels: Tensor) -> Tensor:
        if self.shrink:
            base = base * self.scale[labels].unsqueeze(1).unsqueeze(2)
        return base + (self.k[labels] * distances).unsqueeze(1).unsqueeze(2) * self.eye


class EllipseAxes(nn.Module):
    """`(λ_max [N], λ_min [N], angle [N])` of the x, y block (rows/columns `ix`, `iy`) of
    `cov [N, D, D]`, as `calibrators.regions._ellipse._eigen`: the major axis from +x in
    (−pi/2, pi/2]."""

    def __init__(self, ix: int, iy: int, terms: int = 12) -> None:
        super().__init__()
        self.ix, self.iy = int(ix), int(iy)
        self.register_buffer("pi", constant(math.pi))
        # atan's series w·Σ (−1)ⁿ w²ⁿ / (2n + 1) on |w| <= tan(pi/16): 12 terms leave < 1e-19.
        self.register_buffer("coef", torch.tensor([(-1.0) ** n / (2 * n + 1)
                                                   for n in range(terms)], dtype=torch.float64))
        self.terms = int(terms)

    def forward(self, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        a, b, c = cov[:, self.ix, self.ix], cov[:, self.ix, self.iy], cov[:, self.iy, self.iy]
        mean = 0.5 * (a + c)
        half = 0.5 * (a - c)
        radius = torch.sqrt(half * half + b * b)
        angle = 0.5 * self.atan2(2.0 * b, a - c)
        angle = torch.where(angle <= -0.5 * self.pi, angle + self.pi, angle)
        zero = torch.zeros_like(mean)
        return torch.maximum(mean + radius, zero), torch.maximum(mean - radius, zero), angle

    def atan2(self, y: Tensor, x: Tensor) -> Tensor:
        """`numpy.arctan2(y, x)` for finite `y, x`, in (−pi, pi] (`y = −0` counts as +0)."""
        r = torch.sqrt(x * x + y * y)
        right = x > 0.0
        # x > 0: 2·atan(y / (r + x)); else ±pi − 2·atan(y / (r − x)); both |u| <= 1.
        den = torch.where(right, r + x, r - x)
        origin = den == 0.0                                              # x = y = 0
        u = y / torch.where(origin, torch.ones_like(den), den)
        half = self.atan_unit(u)
        side = torch.where(y >= 0.0, self.pi, -self.pi)
        out = torch.where(right, 2.0 * half, side - 2.0 * half)
        return torch.where(origin, torch.zeros_like(out), out)

    def atan_unit(self, u: Tensor) -> Tensor:
        """`atan(u)` for |u| <= 1: two half-angle steps `atan(u) = 2·atan(u / (1 +
        sqrt(1 + u²)))` (then |w| <= tan(pi/16)) and the series, by Horner."""
        w = u / (1.0 + torch.sqrt(1.0 + u * u))
        w = w / (1.0 + torch.sqrt(1.0 + w * w))
        w2 = w * w
        total = torch.zeros_like(w)
        for n in range(self.terms - 1, -1, -1):
            total = self.coef[n] + w2 * total
        return 4.0 * w * total


class GaussianRadii(nn.Module):
    """The χ²₂ regions of levels `[Q]`: radii `[N, Q]` = `sqrt(χ²₂(q))` and semi-axes
    `sqrt(χ²₂(q)·λ)` (`calibrators.regions.ellipse`)."""

    def __init__(self, chi2: Tensor) -> None:
        super().__init__()
        self.register_buffer("chi2", chi2.to(torch.float64))

    def forward(self, high: Tensor, low: Tensor, labels: Tensor, distances: Tensor
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`(radii [N, Q], semi_major [N, Q], semi_minor [N, Q], group [N] (all −1))`."""
        q = self.chi2.unsqueeze(0)
        radii = torch.sqrt(q) + torch.zeros_like(high).unsqueeze(1)
        return (radii, torch.sqrt(q * high.unsqueeze(1)), torch.sqrt(q * low.unsqueeze(1)),
                torch.full_like(labels, -1))


class ConformalRadii(nn.Module):
    """Split-conformal radii (`calibrators.regions.ConformalRegions.radii`): the group
    `serving [C, B]` of each label × distance bin (inner edges `[B − 1]`, a bin is the number
    of inner edges <= d), its radius `table [G, Q]`, semi-axes `r·sqrt(λ)`."""

    def __init__(self, inner_edges: Tensor, serving: Tensor, table: Tensor) -> None:
        super().__init__()
        self.register_buffer("inner_edges", inner_edges.to(torch.float64))
        self.register_buffer("serving", serving.to(torch.int64))
        self.register_buffer("table", table.to(torch.float64))

    def forward(self, high: Tensor, low: Tensor, labels: Tensor, distances: Tensor
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`(radii [N, Q], semi_major [N, Q], semi_minor [N, Q], group [N])`."""
        bins = (distances.unsqueeze(1) >= self.inner_edges.unsqueeze(0)).to(torch.int64)
        group = self.serving[labels, bins.sum(dim=1)]
        radii = self.table[group]
        unbounded = torch.isinf(radii)   # inf·0 would be nan: an unbounded region is inf
        return (radii, torch.where(unbounded, radii, radii * torch.sqrt(high).unsqueeze(1)),
                torch.where(unbounded, radii, radii * torch.sqrt(low).unsqueeze(1)), group)
