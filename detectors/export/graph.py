"""A calibration profile as one torch module: `build_graph(profile, ...) -> CalibrationGraph`.

The graph does what `CalibrationProfile.calibrate` (`calibrators.profile._calibrate`) does for one
covariance source and a fixed set of region levels, on tensors and in float64 whatever the
input dtype. Inputs, in this order (N detections, L decoder layers, C' logit columns, D =
len(cov_dims)):

    logits [N, C'] | layer_logits [N, L, C']   (layer_logits when the profile modulates)
    boxes [N, 9] | layer_boxes [N, L, 9]       (layer_boxes for cov_source "layers")
    ego_xy [N, 2]                              ego position of each detection's frame
    covariances_raw [N, D, D]                  only for cov_source "given" (Σ before scaling)
    hyp_boxes [N, H, 9], hyp_scores [N, H]     only for cov_source "hypotheses" (the group
                                               heads' box hypotheses and group scores)

Outputs (a dict, in this order): labels [N] int64, scores [N], scores_raw [N], class_scores
[N, C] (global temperature only), distances [N], covariances [N, D, D] (Σ'), and when
cov_dims hold x and y: radii [N, Q], semi_major [N, Q], semi_minor [N, Q] (one column per
level), angle [N], and for conformal regions region_group [N] int64 (the group serving each
detection, described in the graph's metadata).

A stage the graph cannot express, a covariance source the profile does not serve, or a
nothing is dropped. A conformal level some group cannot bound is served as the library serves
it: an infinite radius and infinite semi-axes (the whole plane).
Input checks the library makes per request (NaN, shapes, L >= 2 for the layer spread,
non-negative group scores) are the caller's: the graph computes what the numbers give.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from calibrators.core.defaults import DEFAULT_LEVELS
from calibrators.core.version import detcal_version
from calibrators.core.vocab import BOX_INDEX
from calibrators.profile import CalibrationProfile, SourceStage, score_stage, source_stage
from calibrators.regions import check_levels, chi2_2_quantile
from detectors.export.regions import (
    ConformalRadii,
    CovarianceScaling,
    EllipseAxes,
    GaussianRadii,
    HypothesesSpread,
    LayerSpread,
)
from detectors.export.scores import (
    ClassTemperature,
    Knots,
    LabelLogitScores,
    Modulation,
    Platt,
    Shrunk,
    TemperatureScores,
    given_raw,
    labels_and_raw,
)

#: Version of the exported graphs' input/output contract (in their metadata).
EXPORT_FORMAT = "detcal-export/1"


class ExportError(ValueError):
    """A profile (or an export option) cannot be written as a graph; the message names the
    stage or option."""


class CalibrationGraph(nn.Module):
    """The calibration of one profile as a module (module docstring). Built by `build_graph`;
    `input_names`, `output_names` and `metadata` (JSON text) describe it."""

    def __init__(self, scores: nn.Module, modulation: Modulation | None,
                 spread: LayerSpread | None, scaling: CovarianceScaling,
                 axes: EllipseAxes | None, regions: nn.Module | None, *, softmax: bool,
                 layer_logits: bool, layer_boxes: bool, dim: int, class_scores: bool,
                 conformal: bool, input_names: list[str], output_names: list[str],
                 metadata: str) -> None:
        super().__init__()
        self.scores = scores
        self.modulation = modulation
        self.spread = spread
        self.scaling = scaling
        self.axes = axes
        self.regions = regions
        self.softmax, self.layer_logits, self.layer_boxes = softmax, layer_logits, layer_boxes
        self.dim = dim
        self.class_scores, self.conformal = class_scores, conformal
        self.input_names, self.output_names, self.metadata = input_names, output_names, metadata

    def calibrate(self, logits: Tensor, boxes: Tensor, ego_xy: Tensor,
                  covariances: Tensor | None, given: Tensor | None = None
                  ) -> dict[str, Tensor]:
        """The outputs of the module docstring from the inputs (any float dtype); `given`
        `[N]` int64: the class each detection asserts (default: the arg-max)."""
        z_in = logits.to(torch.float64)
        box_in = boxes.to(torch.float64)
        ego = ego_xy.to(torch.float64)
        final = z_in[:, -1] if self.layer_logits else z_in
        box = box_in[:, -1] if self.layer_boxes else box_in
        if given is None:
            labels, raw = labels_and_raw(final, self.softmax)
        else:
            labels = given.to(torch.int64)
            raw = given_raw(final, labels, self.softmax)
        z = final
        if self.modulation is not None:
            z = self.modulation(z_in)
        dx, dy = box[:, 0] - ego[:, 0], box[:, 1] - ego[:, 1]
        distances = torch.sqrt(dx * dx + dy * dy)
        score, probs = self.scores(z, labels, distances)
        if covariances is not None:
            base = covariances.to(torch.float64)
        elif self.spread is not None:
            base = self.spread(box_in)
        else:
            base = torch.zeros((box.shape[0], self.dim, self.dim), dtype=torch.float64)
        cov = self.scaling(base, distances, labels)
        out: dict[str, Tensor] = {"labels": labels, "scores": score, "scores_raw": raw}
        if self.class_scores:
            out["class_scores"] = probs
        out["distances"] = distances
        out["covariances"] = cov
        if self.axes is not None and self.regions is not None:
            high, low, angle = self.axes(cov)
            radii, major, minor, group = self.regions(high, low, labels, distances)
            out["radii"] = radii
            out["semi_major"] = major
            out["semi_minor"] = minor
            out["angle"] = angle
            if self.conformal:
                out["region_group"] = group
        return out


class _Graph(CalibrationGraph):
    """Inputs: class evidence, boxes, ego_xy (cov_source "layers" or "none")."""

    def forward(self, logits: Tensor, boxes: Tensor, ego_xy: Tensor) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, None)


class _GraphWithCovariances(CalibrationGraph):
    """Inputs: class evidence, boxes, ego_xy, covariances_raw (cov_source "given")."""

    def forward(self, logits: Tensor, boxes: Tensor, ego_xy: Tensor, covariances_raw: Tensor
                ) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, covariances_raw)


class _GraphWithHypotheses(CalibrationGraph):
    """Inputs: class evidence, boxes, ego_xy, hyp_boxes, hyp_scores (cov_source
    "hypotheses"): Σ is the hypotheses' spread."""

    def __init__(self, *args: Any, hypotheses: HypothesesSpread, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.hypotheses = hypotheses

    def forward(self, logits: Tensor, boxes: Tensor, ego_xy: Tensor, hyp_boxes: Tensor,
                hyp_scores: Tensor) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, self.hypotheses(hyp_boxes, hyp_scores))


class _LabelledGraph(CalibrationGraph):
    """`_Graph` with the `labels [N]` input (the class each detection asserts)."""

    def forward(self, logits: Tensor, labels: Tensor, boxes: Tensor, ego_xy: Tensor
                ) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, None, labels)


class _LabelledGraphWithCovariances(CalibrationGraph):
    """`_GraphWithCovariances` with the `labels [N]` input."""

    def forward(self, logits: Tensor, labels: Tensor, boxes: Tensor, ego_xy: Tensor,
                covariances_raw: Tensor) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, covariances_raw, labels)


class _LabelledGraphWithHypotheses(_GraphWithHypotheses):
    """`_GraphWithHypotheses` with the `labels [N]` input."""

    def forward(self, logits: Tensor, labels: Tensor, boxes: Tensor,  # type: ignore[override]
                ego_xy: Tensor, hyp_boxes: Tensor, hyp_scores: Tensor) -> dict[str, Tensor]:
        return self.calibrate(logits, boxes, ego_xy, self.hypotheses(hyp_boxes, hyp_scores),
                              labels)


def build_graph(profile: CalibrationProfile, *, cov_source: str | None = None,
                levels: Sequence[float] = DEFAULT_LEVELS, layer_logits: bool | None = None,
                labels: bool = False) -> CalibrationGraph:
    """The graph of `profile` for covariance source `cov_source` (default: the profile's own;
    any of `profile.served_sources`) with regions at `levels`. `layer_logits`: take the
    logits of every decoder layer `[N, L, C']` (default, and required, when the profile
    modulates) instead of the final layer's `[N, C']`. `labels`: take a `labels [N]` int64
    input after the logits, the class each detection asserts (a top-K (query, class)
    decoder's detections; without it the label is the arg-max). Raises `ExportError` naming
    what cannot be exported."""
    if not isinstance(profile, CalibrationProfile):
        raise ExportError(f"profile must be a CalibrationProfile, got {type(profile).__name__}")
    source = profile.cov_source if cov_source is None else cov_source
    stage = _source(profile, source)
    layer_logits = _layer_logits(profile, layer_logits)
    wanted = _levels(levels)
    softmax = profile.score_mode == "softmax"
    method, calibrator = score_stage(profile.score_calibration)
    scores = (TemperatureScores(profile.temperature, softmax) if calibrator is None
              else LabelLogitScores(_calibrator(method, calibrator), softmax))
    dims = tuple(profile.cov_dims)
    spread = (LayerSpread([BOX_INDEX[d] for d in dims], [d == "yaw" for d in dims])
              if source == "layers" else None)
    regions, groups = _regions(profile, stage, wanted, dims)
    has_xy = regions is not None
    inputs, outputs = _io_names(source, layer_logits, labels, calibrator is None, has_xy,
                                groups is not None)
    metadata = {
        "format": EXPORT_FORMAT, "detcal_version": detcal_version(),
        "profile_sha256": hashlib.sha256(profile.to_json().encode()).hexdigest(),
        "classes": list(profile.classes), "score_mode": profile.score_mode,
        "score_method": method, "modulation": profile.modulation, "cov_source": source,
        "cov_method": stage.cov_method, "cov_dims": list(dims),
        "region_method": stage.region_method if has_xy else None,
        "levels": wanted if has_xy else [], "region_groups": groups,
        "labels_input": bool(labels), "inputs": inputs, "outputs": outputs,
    }
    cls, extra = _graph_class(source, labels, dims)
    return cls(scores, Modulation() if profile.modulation else None, spread,
               _scaling(profile, stage),
               EllipseAxes(dims.index("x"), dims.index("y")) if has_xy else None, regions,
               softmax=softmax, layer_logits=bool(layer_logits),
               layer_boxes=source == "layers", dim=len(dims),
               class_scores=calibrator is None, conformal=groups is not None,
               input_names=inputs, output_names=outputs,
               metadata=json.dumps(metadata, allow_nan=False), **extra)


def _layer_logits(profile: CalibrationProfile, layer_logits: bool | None) -> bool | None:
    """Whether the graph takes every layer's logits (default: when the profile modulates,
    which needs them)."""
    if layer_logits is None:
        layer_logits = profile.modulation
    if profile.modulation and not layer_logits:
        raise ExportError("the profile applies logits modulation, which needs layer_logits "
                          "[N, L, C'] (every decoder layer's logits), not final logits")
    return layer_logits


def _levels(levels: Sequence[float]) -> list[float]:
    """The region levels, checked as the library checks them (`ExportError` otherwise)."""
    try:
        return [float(q) for q in check_levels(levels, "levels")]
    except ValueError as exc:
        raise ExportError(str(exc)) from None


def _io_names(source: str, layer_logits: bool | None, labels: bool, class_scores: bool,
              has_xy: bool, conformal: bool) -> tuple[list[str], list[str]]:
    """The graph's input and output names, in order (module docstring)."""
    inputs = ["layer_logits" if layer_logits else "logits", *(["labels"] if labels else []),
              "layer_boxes" if source == "layers" else "boxes", "ego_xy",
              *(["covariances_raw"] if source == "given" else []),
              *(["hyp_boxes", "hyp_scores"] if source == "hypotheses" else [])]
    outputs = ["labels", "scores", "scores_raw",
               *(["class_scores"] if class_scores else []), "distances", "covariances",
               *(["radii", "semi_major", "semi_minor", "angle"] if has_xy else []),
               *(["region_group"] if conformal else [])]
    return inputs, outputs


def _graph_class(source: str, labels: bool, dims: tuple[str, ...]
                 ) -> tuple[type[CalibrationGraph], dict[str, Any]]:
    """The graph class of the inputs `source` and `labels` take, and its extra arguments."""
    extra: dict[str, Any] = {}
    cls: type[CalibrationGraph] = _LabelledGraph if labels else _Graph
    if source == "given":
        cls = _LabelledGraphWithCovariances if labels else _GraphWithCovariances
    elif source == "hypotheses":
        cls = _LabelledGraphWithHypotheses if labels else _GraphWithHypotheses
        extra["hypotheses"] = HypothesesSpread([BOX_INDEX[d] for d in dims],
                                               [d == "yaw" for d in dims])
    return cls, extra


def _source(profile: CalibrationProfile, source: str) -> SourceStage:
    """The covariance and region stages serving `source`, read from the profile's fields."""
    if source not in profile.served_sources:
        raise ExportError(f"cov_source {source!r} is not served by this profile; it serves "
                          f"{list(profile.served_sources)}")
    if source == profile.cov_source:
        return source_stage(source, profile.depth_k, profile.pooled_k,
                            profile.covariance_scaling, profile.regions, profile.classes)
    other = (profile.sources or {})[source]
    return source_stage(source, other.get("depth_k"), other.get("pooled_k"),
                        other.get("covariance_scaling"), other.get("regions"),
                        profile.classes, where=f"sources[{source!r}].")


def _calibrator(method: str, calibrator: Any) -> nn.Module:
    """The torch module of a fitted per-class score calibrator (with its shrinkage toward the
    pooled fit, `Shrunk`, where it has one)."""
    if method not in _SCORE_METHODS:
        raise ExportError(f"score_calibration.method {method!r} cannot be exported as a graph")
    own = _per_class(method, calibrator, list(calibrator.params_))
    weights = calibrator.class_weights()
    if (weights == 1.0).all():
        return own
    pooled = _per_class(method, calibrator, [calibrator.pooled_params_])
    return Shrunk(own, pooled, torch.as_tensor(weights))


def _per_class(method: str, calibrator: Any, params: list[np.ndarray]) -> nn.Module:
    """The module serving per-class `params` (a class's row each) of `calibrator`."""
    if method == "class_temperature":
        return ClassTemperature(torch.as_tensor(np.array([p[0] for p in params])))
    if method in ("platt", "platt_range"):
        return Platt(torch.as_tensor(np.stack(params)), bool(calibrator.range_term))
    x, y = _padded_knots(params)   # isotonic, histogram
    return Knots(x, y, float(calibrator.eps), float(calibrator.tie_break))


#: The per-class score methods a graph serves.
_SCORE_METHODS = ("class_temperature", "platt", "platt_range", "isotonic", "histogram")


def _padded_knots(tables: list[np.ndarray]) -> tuple[Tensor, Tensor]:
    """`x, y [C, K]` from knot tables `[2, K_c]`: each padded to K = max(2, max K_c) past its
    last knot (x + 1, + 2, ...; y held), which changes no interpolated value."""
    width = max(2, *(t.shape[1] for t in tables))
    xs, ys = [], []
    for t in tables:
        extra = width - t.shape[1]
        xs.append(np.r_[t[0], t[0, -1] + np.arange(1, extra + 1)])
        ys.append(np.r_[t[1], np.full(extra, t[1, -1])])
    return torch.as_tensor(np.stack(xs)), torch.as_tensor(np.stack(ys))


def _scaling(profile: CalibrationProfile, stage: SourceStage) -> CovarianceScaling:
    """`Σ + k·d·I` or `s·Σ + k·d·I` with the class tables of `stage`."""
    k = torch.tensor([stage.depth_k.get(c, stage.pooled_k) for c in profile.classes],
                     dtype=torch.float64)
    if stage.cov_method == "depth":
        return CovarianceScaling(k, None, len(profile.cov_dims))
    if stage.cov_method == "shrinkage":
        s = torch.tensor([stage.scale.get(c, stage.pooled_scale) for c in profile.classes],
                         dtype=torch.float64)
        return CovarianceScaling(k, s, len(profile.cov_dims))
    raise ExportError(f"covariance_scaling.method {stage.cov_method!r} cannot be exported as "
                      f"a graph")


def _regions(profile: CalibrationProfile, stage: SourceStage, levels: list[float],
             dims: tuple[str, ...]) -> tuple[nn.Module | None, list[dict] | None]:
    """The region module at `levels` and, for conformal regions, each group's description
    (None, None when cov_dims lack x or y: the library serves no regions then either)."""
    if "x" not in dims or "y" not in dims:
        return None, None
    if stage.region_method == "gaussian":
        return GaussianRadii(torch.tensor([chi2_2_quantile(q) for q in levels],
                                          dtype=torch.float64)), None
    if stage.region_method != "conformal" or stage.conformal is None:
        raise ExportError(f"regions.method {stage.region_method!r} cannot be exported as a "
                          f"graph")
    conformal = stage.conformal
    table = np.stack([g.radius(np.asarray(levels)) for g in conformal.groups_])   # [G, Q]
    edges = conformal.edges_
    groups = [{"class": None if g.label is None else profile.classes[int(g.label)],
               "distance_range": [float(edges[g.bins[0]]),
                                  None if not np.isfinite(edges[g.bins[1] + 1])
                                  else float(edges[g.bins[1] + 1])], "n": g.n}
              for g in conformal.groups_]
    serving = conformal.serving_[:len(profile.classes)]     # labels are the profile's classes
    # a level a group cannot bound has an infinite radius: the whole plane, as the library
    return ConformalRadii(torch.as_tensor(edges[1:-1]), torch.as_tensor(serving),
                          torch.as_tensor(table)), groups
