"""The score stage of an exported profile as torch modules (float64, TorchScript-able).

Each mirrors `calibrators.profile._calibrate` / `calibrators.scores`
on tensors: the label is the arg-max of the raw final-layer object logits; the score is
`sigmoid/softmax(z / T)` (`TemperatureScores`, which also gives the class probabilities) or a
per-class calibrator of the label's logit (`LabelLogitScores` around `ClassTemperature`,
`Platt` or `Knots`). `Modulation` is thesis Eq. 4-1 over the decoder layers. Shapes:
`z [N, C']` (C' = C sigmoid, C + 1 softmax), `labels [N]` int64, `distances [N]`.

Every constant that float32 cannot hold exactly (T, eps, ...) is a float64 buffer, never a
Python float: the ONNX exporter writes Python scalars as float32 constants.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

_EPS = 1e-12   # calibrators.scores.probability_logit's clipping


def constant(value: float) -> Tensor:
    """A 0-d float64 tensor of `value` (for a buffer)."""
    return torch.tensor(float(value), dtype=torch.float64)


def probabilities(z: Tensor, softmax: bool) -> Tensor:
    """Object-class probabilities `[N, C]` of logits `[N, C']` (already divided by T)."""
    if softmax:
        return torch.softmax(z, dim=1)[:, :-1]
    return torch.sigmoid(z)


def pick(values: Tensor, labels: Tensor) -> Tensor:
    """`values[i, labels[i]]` `[N]` of `values [N, C]`."""
    return torch.gather(values, 1, labels.unsqueeze(1)).squeeze(1)


def given_raw(z: Tensor, labels: Tensor, softmax: bool) -> Tensor:
    """Raw scores `[N]` of given `labels [N]` (any class: top-K (query, class) decoding)."""
    return pick(probabilities(z, softmax), labels)


def labels_and_raw(z: Tensor, softmax: bool) -> tuple[Tensor, Tensor]:
    """Labels `[N]` (arg-max of the object columns, first on ties) and raw scores `[N]`."""
    n_obj = z.shape[1] - 1 if softmax else z.shape[1]
    labels = torch.argmax(z[:, :n_obj], dim=1)
    return labels, pick(probabilities(z, softmax), labels)


class Modulation(nn.Module):
    """`z_L · (1 − tanh(var_l z))` `[N, C']` from layer logits `[N, L, C']` (population
    variance over the L layers, as `numpy.var`)."""

    def forward(self, layers: Tensor) -> Tensor:
        centred = layers - layers.mean(dim=1, keepdim=True)
        var = (centred * centred).mean(dim=1)
        return layers[:, -1] * (1.0 - torch.tanh(var))


class TemperatureScores(nn.Module):
    """The global temperature: `(score [N], class probabilities [N, C])`."""

    def __init__(self, temperature: float, softmax: bool) -> None:
        super().__init__()
        self.register_buffer("temperature", constant(temperature))
        self.softmax = bool(softmax)

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> tuple[Tensor, Tensor]:
        probs = probabilities(z / self.temperature, self.softmax)
        return pick(probs, labels), probs


class ClassTemperature(nn.Module):
    """`sigmoid(z / T_c)` of the label's logit `z [N]`; `temperature [C]`."""

    def __init__(self, temperature: Tensor) -> None:
        super().__init__()
        self.register_buffer("temperature", temperature.to(torch.float64))

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> Tensor:
        return torch.sigmoid(z / self.temperature[labels])


class Platt(nn.Module):
    """`sigmoid(a_c·z + b_c [+ g_c·d])`; `coef [C, 3]` rows `(a, b, g)`."""

    def __init__(self, coef: Tensor, range_term: bool) -> None:
        super().__init__()
        self.register_buffer("coef", coef.to(torch.float64))
        self.range_term = bool(range_term)

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> Tensor:
        row = self.coef[labels]
        eta = row[:, 0] * z + row[:, 1]
        if self.range_term:
            eta = eta + row[:, 2] * distances
        return torch.sigmoid(eta)


class Knots(nn.Module):
    """Isotonic / histogram knots served as `calibrators.scores._knots.serve`:
    `(1 − δ)·clip(interp(z; x_c, y_c), eps, 1 − eps) + δ·sigmoid(z)`. `x, y [C, K]`: each
    class's table padded to K >= 2 knots past its last one (x increasing, y held), which
    leaves `interp` unchanged (flat beyond the ends)."""

    def __init__(self, x: Tensor, y: Tensor, eps: float, tie_break: float) -> None:
        super().__init__()
        self.register_buffer("x", x.to(torch.float64))
        self.register_buffer("y", y.to(torch.float64))
        self.register_buffer("eps", constant(eps))
        self.register_buffer("tie_break", constant(tie_break))

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> Tensor:
        x, y = self.x[labels], self.y[labels]                              # [N, K]
        below = (x <= z.unsqueeze(1)).to(torch.int64).sum(dim=1) - 1
        j = torch.clamp(below, 0, x.shape[1] - 2).unsqueeze(1)
        x0, x1 = torch.gather(x, 1, j).squeeze(1), torch.gather(x, 1, j + 1).squeeze(1)
        y0, y1 = torch.gather(y, 1, j).squeeze(1), torch.gather(y, 1, j + 1).squeeze(1)
        t = torch.clamp((z - x0) / (x1 - x0), 0.0, 1.0)
        p = torch.clamp(y0 + t * (y1 - y0), self.eps, 1.0 - self.eps)
        return (1.0 - self.tie_break) * p + self.tie_break * torch.sigmoid(z)


class Shrunk(nn.Module):
    """`w_c·own + (1 − w_c)·pooled` (`calibrators.scores`: shrinkage toward the pooled fit);
    `pooled` is a one-class module, `weights [C]`."""

    def __init__(self, own: nn.Module, pooled: nn.Module, weights: Tensor) -> None:
        super().__init__()
        self.own, self.pooled = own, pooled
        self.register_buffer("weights", weights.to(torch.float64))

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> Tensor:
        w = self.weights[labels]
        pooled = self.pooled(z, torch.zeros_like(labels), distances)
        return w * self.own(z, labels, distances) + (1.0 - w) * pooled


class LabelLogitScores(nn.Module):
    """A per-class calibrator of the label's logit (`calibrators.scores.label_logit`: the
    label's column in sigmoid mode, the clipped `logit(p_label)` of the softmax at T = 1 in
    softmax mode): `(score [N], empty [N, 0])` (no class probabilities)."""

    def __init__(self, calibrator: nn.Module, softmax: bool) -> None:
        super().__init__()
        self.calibrator = calibrator
        self.softmax = bool(softmax)
        self.register_buffer("eps", constant(_EPS))

    def forward(self, z: Tensor, labels: Tensor, distances: Tensor) -> tuple[Tensor, Tensor]:
        if self.softmax:
            p = torch.clamp(pick(torch.softmax(z, dim=1), labels), self.eps, 1.0 - self.eps)
            logit = torch.log(p) - torch.log(1.0 - p)
        else:
            logit = pick(z, labels)
        return self.calibrator(logit, labels, distances), z[:, :0]
