"""Apply a `CalibrationProfile` to N detections: `calibrate_detections` -> `CalibratedDetections`.

Class evidence: `logits [N, C']` (C' = C sigmoid, C + 1 softmax), or `layer_logits [N, L, C']`
from every decoder layer (the last is the final layer), or raw `scores [N]` with `labels [N]`.
The label is the arg-max of the raw final layer, or, with `labels [N]` beside the logits, the
class each detection asserts (top-K (query, class) decoding); it never changes. The score is
`sigmoid/softmax(z / T)` (version 1, and version 2 with the `temperature` method; from a raw
score, `sigmoid(logit(p) / T)`), or the profile's per-class calibrator of the label's logit
(`logit(p)` of a raw score; range-conditioned methods use the distance). A profile with
`modulation` needs `layer_logits` (L >= 2): `z` is then modulated over all layers.
`boxes [N, 9]` (required) give the distance `d` from `ego_xy [N, 2]` (default origin). Σ
comes from the profile's `cov_source`: `covariances [N, D, D]` ("given"), `layer_boxes
[N, L, 9]` ("layers", spread across decoder layers), `hyp_boxes [N, H, 9]` with `hyp_scores
[N, H]` ("hypotheses", the score-weighted spread of the box hypotheses) or zeros ("none").
A profile serving several sources takes, of what the call carries, given covariances first,
then the hypotheses, then the layer spread, then none. `Σ' = Σ + k_c·d·I`, or
`s_c·Σ + k_c·d·I` with a shrinkage stage. Regions are ellipses of the x, y block of `Σ'` with
semi-axes `r_q·sqrt(λ)`: `r_q = sqrt(χ²₂(q))` (gaussian) or the conformal radius of the
detection's class × distance group.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import expit

from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_covariances,
    check_index,
    check_length,
    check_probabilities,
)
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.covariance import (
    SOURCE_ARRAYS,
    add_depth_term,
    check_hypotheses,
    source_covariance,
    source_inputs,
    takes_phrase,
)
from calibrators.regions import (
    MAX_LEVELS,
    Ellipse,
    check_levels,
    ellipse,
    gaussian_radius,
    radius_ellipses,
)
from calibrators.scores import (
    class_probabilities,
    label_logit,
    label_scores,
    modulate_logits,
    predict,
    probability_logit,
)

if TYPE_CHECKING:
    from calibrators.profile._detections import Detections
    from calibrators.profile._profile import CalibrationProfile
    from calibrators.profile._serialise import SourceStage

__all__ = ["CalibratedDetections", "calibrate_detections"]


@dataclass(frozen=True)
class CalibratedDetections:
    """Result of `CalibrationProfile.calibrate` for N detections.

    labels [N] int64; scores [N] calibrated probability of the label; scores_raw [N] before
    calibration; class_scores [N, C] (None for scores-only input or a per-class score stage);
    covariances [N, D, D] = Σ'; ellipses at `ellipse_confidence` (arrays [N]) or None;
    distances [N] m. Per requested level: regions (ellipses [N]), region_radii (Mahalanobis
    radius [N]), region_guarantees ([N] what holds: cell, scaled, pooled, marginal, or none for
    gaussian; `ConformalRegions.guarantee_table`), region_counts ([N] the calibration scores
    behind it, -1 for gaussian). region_method: `gaussian` | `conformal` (None without x, y);
    region_groups: [N] the serving conformal group, e.g. `car 15-30 m` (None for gaussian);
    cov_source: the covariance source that served the call. classes, cov_dims: the
    profile's; detections: the `Detections` batch calibrated (identity: frame ids, rows, user
    ids), when it went through `Detections.calibrate`.
    """

    labels: np.ndarray
    scores: np.ndarray
    scores_raw: np.ndarray
    class_scores: np.ndarray | None
    covariances: np.ndarray
    ellipses: Ellipse | None
    distances: np.ndarray
    regions: dict[float, Ellipse] = field(default_factory=dict)
    region_method: str | None = None
    region_groups: list[str] | None = None
    region_radii: dict[float, np.ndarray] = field(default_factory=dict)
    region_guarantees: dict[float, np.ndarray] = field(default_factory=dict)
    region_counts: dict[float, np.ndarray] = field(default_factory=dict)
    cov_source: str | None = None
    classes: tuple[str, ...] = ()
    cov_dims: tuple[str, ...] = ()
    ellipse_confidence: float = ELLIPSE_CONFIDENCE
    detections: Detections | None = None

    def __len__(self) -> int:
        return len(self.labels)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types, field by field: arrays as lists, an ellipse as `{"semi_major",
        "semi_minor", "angle"}`, `regions` and `region_radii` keyed by `str(level)`, an
        unbounded axis or radius None, `detections` its identity `{"frame_ids", "rows", "ids"}`."""
        out, det = {f.name: getattr(self, f.name) for f in fields(self)}, self.detections
        out["ellipses"] = None if self.ellipses is None else self.ellipses._asdict()
        out["regions"] = {str(q): e._asdict() for q, e in self.regions.items()}
        for name in ("region_radii", "region_guarantees", "region_counts"):
            out[name] = {str(q): r for q, r in getattr(self, name).items()}
        out["detections"] = None if det is None else {
            "frame_ids": det.frame_ids, "rows": det.rows, "ids": det.detection_ids}
        return to_jsonable(out)

    def to_records(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per detection, in this order, with its identity
        (`calibrators.profile._detections.calibrated_records`)."""
        from calibrators.profile._detections import calibrated_records

        return calibrated_records(self)

    def to_arrow(self, metadata: dict[str, Any] | None = None) -> Any:
        """An Arrow record batch, a row per detection with its identity
        (`calibrators.io.arrow_batch.calibrated_batch`; needs pyarrow)."""
        from calibrators.io.arrow_batch import calibrated_batch

        return calibrated_batch(self, {} if metadata is None else metadata)

    def to_nuscenes(self, calibration: dict[str, Any] | None = None,
                    meta: dict[str, Any] | None = None) -> dict[str, Any]:
        """A nuScenes results document of these detections, grouped by frame token, each box
        with its identity (`calibrators.io.nuscenes_write.calibrated_document`)."""
        from calibrators.io.nuscenes_write import calibrated_document

        return calibrated_document(self, calibration, meta)


def calibrate_detections(profile: CalibrationProfile, *, logits: np.ndarray | None = None,
                         scores: np.ndarray | None = None, labels: np.ndarray | None = None,
                         boxes: np.ndarray | None = None, covariances: np.ndarray | None = None,
                         layer_boxes: np.ndarray | None = None,
                         ego_xy: np.ndarray | None = None,
                         ellipse_confidence: float = ELLIPSE_CONFIDENCE,
                         layer_logits: np.ndarray | None = None,
                         levels: Sequence[float] | np.ndarray | None = None,
                         hyp_boxes: np.ndarray | None = None,
                         hyp_scores: np.ndarray | None = None) -> CalibratedDetections:
    """Calibrate N detections with `profile` (module docstring). `levels`: the region levels
    to serve (at most 20, each in (0, 1)); a FieldError names the argument at fault."""
    box = as_float_array("boxes", _required("boxes", boxes), ndim=2)
    if box.shape[1] != 9:
        raise FieldError("boxes", f"boxes must have shape [N, 9], got {box.shape}")
    n = box.shape[0]
    ego = np.zeros((n, 2)) if ego_xy is None else as_float_array("ego_xy", ego_xy, ndim=2)
    if ego.shape != (n, 2):
        raise FieldError("ego_xy", f"ego_xy must have shape [{n}, 2], got {ego.shape}")
    distances = np.hypot(box[:, 0] - ego[:, 0], box[:, 1] - ego[:, 1])
    labels_, scores_, raw, class_scores = _class_evidence(profile, logits, scores, labels,
                                                          layer_logits, distances)
    check_length("boxes", box, len(labels_), "the class evidence")
    stage, base = _base_covariance(profile, covariances, layer_boxes, (hyp_boxes, hyp_scores), n)
    cov = _scaled(profile, stage, base, distances, labels_)
    wanted = None if levels is None else check_levels(levels)
    confidence = check_levels([ellipse_confidence], "ellipse_confidence")[0]
    served = [float(confidence)] + ([] if wanted is None else
                                    [float(q) for q in wanted if q != confidence])
    regions, radii, method, groups, index = _regions(profile, stage, cov, distances, labels_,
                                                     served)
    support = ({}, {}) if wanted is None or method is None else _guarantees(
        stage, index, [float(q) for q in wanted], len(labels_))
    out = CalibratedDetections(
        labels=labels_, scores=scores_, scores_raw=raw, class_scores=class_scores,
        covariances=cov, ellipses=regions.get(float(confidence)), distances=distances,
        regions=_at(regions, wanted), region_method=method, region_groups=groups,
        region_radii=_at(radii, wanted), region_guarantees=support[0],
        region_counts=support[1], cov_source=stage.source,
        classes=tuple(profile.classes), cov_dims=tuple(profile.cov_dims),
        ellipse_confidence=float(confidence))
    _check_finite(out, covariances is not None, radii.get(float(confidence)))
    return out


def _check_finite(res: CalibratedDetections, given_cov: bool,
                  confidence_radii: np.ndarray | None) -> None:
    """A FieldError at the first detection with a calibrated number that is not finite (finite
    but huge inputs can overflow float64): at its box when its distance overflowed or it gave
    no covariance, else at its covariance. An unbounded region (infinite radius: a level its
    conformal group cannot certify) is not an overflow."""
    n = len(res)
    if n == 0:
        return
    served = [(res.scores, None), (res.distances, None), (res.covariances, None),
              *((a, confidence_radii) for a in res.ellipses or ()),
              *((a, res.region_radii.get(q)) for q, region in res.regions.items()
                for a in region)]
    # Quick pass: a sum is finite only if every term is (a huge finite sum that overflows
    # just takes the row-by-row pass below, which also places the fault).
    unbounded = {id(r): bool(np.isinf(r).any()) for _, r in served if r is not None}
    if not any(unbounded.values()):
        with np.errstate(over="ignore", invalid="ignore"):
            if np.isfinite(sum(float(np.add.reduce(np.ravel(a))) for a, _ in served)):
                return
    bad = np.zeros(n, dtype=bool)
    for arr, radii in served:
        ok = np.isfinite(np.asarray(arr, dtype=np.float64).reshape(n, -1)).all(axis=1)
        if radii is not None:
            ok |= np.isinf(radii)
        bad |= ~ok
    if not bad.any():
        return
    row = int(np.argmax(bad))
    field = "boxes" if not np.isfinite(res.distances[row]) or not given_cov else "covariances"
    raise FieldError(field, f"the calibrated covariance or ellipse overflows float64 (distance "
                            f"{res.distances[row]:.3g} m): the box and covariance must be "
                            f"of a physical scale", row=row)


def _class_evidence(profile: CalibrationProfile, logits: np.ndarray | None,
                    scores: np.ndarray | None, labels: np.ndarray | None,
                    layer_logits: np.ndarray | None, distances: np.ndarray
                    ) -> tuple[np.ndarray, ...]:
    """Labels, calibrated scores, raw scores `[N]` and class probabilities `[N, C]|None`."""
    given = [name for name, value in (("logits", logits), ("layer_logits", layer_logits),
                                      ("scores", scores)) if value is not None]
    if len(given) != 1:
        raise FieldError("logits", f"pass either logits or scores (with labels), or "
                                   f"layer_logits in place of logits; got {given or 'none'}")
    if profile.modulation and layer_logits is None:
        raise FieldError("layer_logits", f"the profile applies logits modulation, which "
                                         f"needs layer_logits with at least 2 layers "
                                         f"[N, L, C'] (every decoder layer's logits), not "
                                         f"{given[0]}")
    n_classes, mode = len(profile.classes), profile.score_mode
    want = n_classes + (1 if mode == "softmax" else 0)
    method, calibrator = profile.score_calibrator
    if layer_logits is not None:
        layers = as_float_array("layer_logits", layer_logits, ndim=3)
        if layers.shape[2] != want:
            raise FieldError("layer_logits", f"layer_logits has {layers.shape[2]} columns but "
                                             f"the profile's {mode} mode with "
                                             f"{n_classes} classes needs {want}")
        if profile.modulation and layers.shape[1] < 2:
            raise FieldError("layer_logits", f"the profile applies logits modulation, "
                                             f"which needs layer_logits with at least 2 "
                                             f"layers, got {layers.shape[1]}")
        logits = layers[:, -1]
    if logits is not None:
        z = as_float_array("logits", logits, ndim=2)
        if z.shape[1] != want:
            raise FieldError("logits", f"logits has {z.shape[1]} columns but the profile's "
                                       f"{mode} mode with {n_classes} classes needs {want}")
        if labels is None:
            pred, raw = predict(z, mode)
        else:   # the class each detection asserts (top-K (query, class) decoding)
            pred = as_int_array("labels", labels)
            check_length("labels", pred, len(z), "logits")
            check_index("labels", pred, n_classes, "classes")
            raw = label_scores(z, pred, mode)
        if profile.modulation:
            z = modulate_logits(layers)
        if calibrator is None:
            probs = class_probabilities(z, mode, profile.temperature)
            return pred, probs[np.arange(len(pred)), pred], raw, probs
        check_length("logits", pred, len(distances), "boxes")
        return pred, calibrator.transform(label_logit(z, pred, mode), pred,
                                          distances=distances), raw, None
    p = as_float_array("scores", scores, ndim=1)
    check_probabilities("scores", p)
    lab = as_int_array("labels", _required("labels (with scores)", labels))
    check_length("labels", lab, len(p), "scores")
    check_index("labels", lab, n_classes, "classes")
    if calibrator is None:   # exactly 0 and 1 stay 0 and 1 (as version 1 profiles served)
        return lab, expit(probability_logit(p, clip=False) / profile.temperature), p, None
    check_length("scores", p, len(distances), "boxes")
    return lab, calibrator.transform(probability_logit(p), lab, distances=distances), p, None


def _base_covariance(profile: CalibrationProfile, covariances: np.ndarray | None,
                     layer_boxes: np.ndarray | None,
                     hypotheses: tuple[np.ndarray | None, np.ndarray | None], n: int
                     ) -> tuple[SourceStage, np.ndarray]:
    """The stage serving this call and its `[N, D, D]` Σ before scaling: given `covariances`
    if passed, else the spread of the `hypotheses` (`hyp_boxes`, `hyp_scores`) if passed
    and the profile serves them, else the spread of `layer_boxes` likewise, else none (Σ = 0)
    if the profile serves it; a FieldError names what the profile needs."""
    dim, stages = len(profile.cov_dims), profile.source_stages
    if covariances is not None:
        if "given" not in stages:
            raise FieldError("covariances", f"covariances were given but the profile's "
                                            f"cov_source is {profile.cov_source!r}: its k was "
                                            f"fit without them{takes_phrase(stages)}")
        cov = as_float_array("covariances", covariances, ndim=3)
        if cov.shape[1:] != (dim, dim):
            raise FieldError("covariances", f"covariances are {cov.shape[1]}x{cov.shape[2]} "
                                            f"but the profile's cov_dims "
                                            f"{list(profile.cov_dims)} need {dim}x{dim}")
        check_covariances("covariances", cov, n=n, dim=dim)
        return stages["given"], cov
    hyp_boxes, hyp_scores = hypotheses
    if (hyp_boxes is None) != (hyp_scores is None):
        missing, given = (("hyp_boxes", "hyp_scores") if hyp_boxes is None
                          else ("hyp_scores", "hyp_boxes"))
        raise FieldError(missing, f"{given} is given without {missing}: the box hypotheses "
                                  f"and their group scores go together")
    if hyp_boxes is not None and "hypotheses" in stages:
        boxes, scores = check_hypotheses(hyp_boxes, hyp_scores, n)
        return stages["hypotheses"], source_covariance("hypotheses", profile.cov_dims,
                                                        hyp_boxes=boxes, hyp_scores=scores)
    if layer_boxes is not None and "layers" in stages:
        spread = source_covariance("layers", profile.cov_dims, layer_boxes=layer_boxes)
        check_length("layer_boxes", spread, n, "boxes")
        return stages["layers"], spread
    if "none" in stages:
        return stages["none"], np.zeros((n, dim, dim))
    for source in dict.fromkeys((profile.cov_source, "layers", "hypotheses")):
        if source in stages and source in ("layers", "hypotheses"):
            raise FieldError(next(iter(SOURCE_ARRAYS[source])),
                             f"{source_inputs(source)} (the profile's cov_source is "
                             f"{profile.cov_source!r}) is required{takes_phrase(stages)}")
    raise FieldError("covariances", f"covariances are required: the profile was fit on given "
                                    f"covariances (cov_source 'given') over cov_dims "
                                    f"{list(profile.cov_dims)}")


def _scaled(profile: CalibrationProfile, stage: SourceStage, base: np.ndarray,
            distances: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Σ' = Σ + k·d·I, or s·Σ + k·d·I with a shrinkage stage (class of each detection)."""
    k_table = np.array([stage.depth_k.get(c, stage.pooled_k) for c in profile.classes])
    if stage.cov_method == "shrinkage":
        s_table = np.array([stage.scale.get(c, stage.pooled_scale) for c in profile.classes])
        base = base * s_table[labels][:, None, None]
    return add_depth_term(base, distances, k_table[labels])


def _regions(profile: CalibrationProfile, stage: SourceStage, cov: np.ndarray,
             distances: np.ndarray, labels: np.ndarray, levels: list[float]
             ) -> tuple[dict[float, Ellipse], dict[float, np.ndarray], str | None,
                        list[str] | None, np.ndarray | None]:
    """Ellipses of the x, y block of `cov [N, D, D]` at each level, their radii `[N]`, the
    method, the serving groups and their indices `[N]` (None for gaussian); all empty or
    None if cov_dims lack x or y."""
    if "x" not in profile.cov_dims or "y" not in profile.cov_dims:
        return {}, {}, None, None, None
    ix, iy = profile.cov_dims.index("x"), profile.cov_dims.index("y")
    block = cov[:, [ix, iy]][:, :, [ix, iy]]
    method, conformal = stage.region_method, stage.conformal
    n = len(labels)
    if conformal is None:
        return ({float(q): ellipse(block, q) for q in levels},
                {float(q): np.full(n, gaussian_radius(q)) for q in levels}, method, None, None)
    # `levels` is the ellipse confidence plus up to MAX_LEVELS requested levels: radii() takes
    # at most MAX_LEVELS at once
    index = conformal.group_index(labels, distances)
    radii = np.concatenate([conformal.radius_table(levels[i:i + MAX_LEVELS])
                            for i in range(0, len(levels), MAX_LEVELS)], axis=1)[index]
    names = {int(g): conformal.group_name(conformal.groups_[g], profile.classes)
             for g in np.unique(index)}
    # Σ' was built from checked Σ (or a spread) by adding k·d·I: symmetric PSD, or an
    # overflow that `_check_finite` places
    return (dict(zip(map(float, levels), radius_ellipses(block, radii, check=False),
                     strict=True)),
            {float(q): radii[:, j] for j, q in enumerate(levels)}, method,
            [names[g] for g in index.tolist()], index)


def _guarantees(stage: SourceStage, index: np.ndarray | None, levels: list[float], n: int
                ) -> tuple[dict[float, np.ndarray], dict[float, np.ndarray]]:
    """Per requested level, what each region guarantees and on how many calibration scores
    `[N]`: its group's row of `guarantee_table`, or "none" and -1 for gaussian regions."""
    if stage.conformal is None or index is None:
        return ({q: np.full(n, "none", dtype=object) for q in levels},
                {q: np.full(n, -1, dtype=np.int64) for q in levels})
    names, counts = stage.conformal.guarantee_table(levels)
    return ({q: names[index, j] for j, q in enumerate(levels)},
            {q: counts[index, j] for j, q in enumerate(levels)})


def _at(table: dict[float, Any], wanted: np.ndarray | None) -> dict[float, Any]:
    """The entries of `table` at the `wanted` levels ({} when none or no table)."""
    return {} if wanted is None or not table else {float(q): table[float(q)] for q in wanted}


def _required(name: str, value: Any) -> Any:
    """`value`, or a FieldError naming the argument (the first word of `name`) if None."""
    if value is None:
        raise FieldError(name.split()[0], f"{name} is required")
    return value
