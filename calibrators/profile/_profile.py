"""The calibration profile: fitted parameters, fit report and provenance, as versioned JSON.

A profile is what `fit_profile` produces and what the service stores and applies. Version 1
(the thesis): calibrated scores `sigmoid/softmax(z / T)` (with `modulation`, `z` is first
modulated from the per-layer logits, `calibrators.scores`), covariances `Σ + k_c · d · I`
(class `c`, BEV distance `d` from the ego) and Gaussian confidence ellipses of their `x, y`
block. Version 2 adds three stages, each `None` for the version-1 behaviour:
`score_calibration` (a per-class score calibrator of the label's logit), `covariance_scaling`
(`s_c · Σ + k_c · d · I`) and `regions` (split-conformal radii per class × distance bin).
`calibrate(...)` (see `calibrators.profile._calibrate`) applies them. `to_json()` / `from_json()`
round-trip exactly (floats are written with `repr`, which Python reads back bit for bit); a
version-1 profile is written back as version 1.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from types import MappingProxyType
from typing import Any

import numpy as np

import calibrators.profile._serialise as pf
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from calibrators.core.json_safe import parse_json
from calibrators.core.version import detcal_version
from calibrators.core.vocab import COV_SOURCES, SCORE_MODES
from calibrators.covariance import dim_indices
from calibrators.profile._calibrate import CalibratedDetections, calibrate_detections

SCHEMA_VERSION = pf.SCHEMA_VERSION
MATCHING_RULES = pf.MATCHING_RULES

__all__ = ["CalibratedDetections", "CalibrationProfile", "make_provenance"]


@dataclass(frozen=True, kw_only=True)
class CalibrationProfile:
    """Fitted calibration of one detector (see the module docstring).

    classes : class names in logit column order.     score_mode : "sigmoid" or "softmax".
    temperature : T > 0 (the global temperature; served unless a per-class score stage is).
    cov_dims : regression dims of Σ (D).
    modulation : True if logits modulation (Eq. 4-1) runs before the temperature; then
        `calibrate` needs the per-layer logits. Absent from older JSON: read as False.
    cov_source : "given" | "layers" | "hypotheses" | "none" (where Σ comes from before depth
        scaling; `calibrators.core.vocab.COV_SOURCES`).
    depth_k : class name -> k >= 0.                   pooled_k : k for classes not in depth_k.
    fallback_classes : classes whose k (and s) are pooled (too few matches when fit).
    matching : {"rule": "center_distance", "threshold": metres}.
    min_score : the minimum raw score a detection needed to take part in the fit, or None.
    report : JSON-able before/after metrics.          provenance : JSON-able fit provenance.
    score_calibration : v2, {"method", "params"} or None (the global temperature).
    covariance_scaling : v2, {"method", "scale": {class: s}, "pooled_scale"} or None (depth).
    regions : v2, {"method", "conformal"} or None (Gaussian χ²₂ radii).
    sources : v2, the same covariance and region stages (with their `depth_k`, `pooled_k`,
        `fallback_classes`) for the other covariance sources the val dump allowed, so a
        request is calibrated with whatever it carries (`{source: {...}}`), or None.

    A profile is immutable (frozen): `dataclasses.replace` gives a changed copy, validated
    again. `__post_init__` normalises the fields and parses the stages once, into two
    read-only attributes that are not fields (not in the JSON):
    score_calibrator : `(method, calibrator)`, the calibrator None for the global
        `temperature`, else a fitted `calibrators.scores` calibrator.
    source_stages : read-only `{covariance source: SourceStage}` of every source served, the
        own `cov_source` first (its `depth_k`, scales and conformal radii, parsed).
    They are plain attributes, not properties, so that serving reads them without a call.
    """

    classes: tuple[str, ...]
    score_mode: str
    temperature: float = 1.0
    modulation: bool = False
    cov_dims: tuple[str, ...] = ("x", "y")
    cov_source: str = "none"
    depth_k: dict[str, float] = field(default_factory=dict)
    pooled_k: float = 0.0
    fallback_classes: tuple[str, ...] = ()
    matching: dict = field(default_factory=lambda: {"rule": "center_distance",
                                                    "threshold": 2.0})
    min_score: float | None = None
    report: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    score_calibration: dict | None = None
    covariance_scaling: dict | None = None
    regions: dict | None = None
    sources: dict | None = None
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        pf.check_schema_version(self.schema_version)
        put = self._put
        put("classes", pf.names("classes", self.classes, distinct=True))
        if not self.classes:
            raise ValueError("classes must name at least one class")
        if self.score_mode not in SCORE_MODES:
            raise ValueError(f"score_mode must be one of {list(SCORE_MODES)}, "
                             f"got {self.score_mode!r}")
        put("temperature", pf.number("temperature", self.temperature, positive=True))
        if not isinstance(self.modulation, bool | np.bool_):
            raise ValueError(f"modulation must be true or false, got {self.modulation!r}")
        put("modulation", bool(self.modulation))
        put("cov_dims", pf.names("cov_dims", self.cov_dims, distinct=True))
        dim_indices(self.cov_dims)
        if self.cov_source not in COV_SOURCES:
            raise ValueError(f"cov_source must be one of {list(COV_SOURCES)}, "
                             f"got {self.cov_source!r}")
        put("depth_k", pf.class_numbers("depth_k", self.depth_k, self.classes))
        put("pooled_k", pf.number("pooled_k", self.pooled_k, nonnegative=True))
        put("fallback_classes", pf.names("fallback_classes", self.fallback_classes,
                                         distinct=True))
        pf.known("fallback_classes", self.fallback_classes, self.classes)
        put("matching", pf.matching(self.matching))
        if self.min_score is not None:
            put("min_score", pf.number("min_score", self.min_score))
            if not 0.0 <= self.min_score <= 1.0:
                raise ValueError(f"min_score must be in [0, 1] or null, got {self.min_score}")
        put("report", pf.jsonable("report", self.report))
        put("provenance", pf.jsonable("provenance", self.provenance))
        stages = [getattr(self, key) for key in pf.STAGE_KEYS]
        if self.schema_version == 1 and any(stage is not None for stage in stages):
            raise ValueError("a schema_version 1 profile has no score_calibration, "
                             "covariance_scaling or regions; use schema_version 2")
        for key in pf.STAGE_KEYS:
            if getattr(self, key) is not None:
                put(key, pf.jsonable(key, getattr(self, key)))
        # The parsed stages (validated here once, used by calibrate).
        put("score_calibrator", pf.score_stage(self.score_calibration))
        primary = pf.SourceStage(self.cov_source, self.depth_k, self.pooled_k,
                                 *pf.covariance_stage(self.covariance_scaling, self.classes),
                                 *pf.region_stage(self.regions, len(self.classes)))
        put("source_stages", MappingProxyType({
            self.cov_source: primary,
            **pf.other_sources(self.sources, self.cov_source, self.classes)}))

    def _put(self, name: str, value: Any) -> None:
        """Set `name` while `__post_init__` builds the (frozen) profile."""
        object.__setattr__(self, name, value)

    def __getstate__(self) -> dict[str, Any]:
        """The pickle (and deep copy) state: a mappingproxy does not pickle, its dict does."""
        return {**self.__dict__, "source_stages": dict(self.source_stages)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state, source_stages=MappingProxyType(state["source_stages"]))

    @property
    def kind(self) -> str:
        """`3d` (`calibrators.core.vocab.PROFILE_KINDS`; a 2-D profile is a `Profile2D`)."""
        return "3d"

    @property
    def score_method(self) -> str:
        """The served score calibration: `temperature` or a per-class method."""
        return self.score_calibrator[0]

    @property
    def cov_method(self) -> str:
        """The served covariance scaling: `depth` (Σ + k·d·I) or `shrinkage` (s·Σ + k·d·I)."""
        return self.source_stages[self.cov_source].cov_method

    @property
    def served_sources(self) -> tuple[str, ...]:
        """The covariance sources a request may carry: the profile's own `cov_source` first."""
        return tuple(self.source_stages)

    @property
    def region_method(self) -> str:
        """The served regions: `gaussian` (χ²₂ radii) or `conformal`."""
        return self.source_stages[self.cov_source].region_method

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the profile in plain JSON types (tuples become lists),
        `schema_version` first; a version-1 profile has no stage keys."""
        out: dict[str, Any] = {"schema_version": self.schema_version}
        out.update({f.name: copy.deepcopy(getattr(self, f.name)) for f in fields(self)
                    if self.schema_version > 1 or f.name not in pf.STAGE_KEYS})
        for key in ("classes", "cov_dims", "fallback_classes"):
            out[key] = list(out[key])
        return out

    def to_json(self, indent: int | None = 2) -> str:
        """Profile JSON; `from_json(to_json())` gives back an equal profile, float for float."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str | bytes) -> CalibrationProfile:
        """Parse and validate profile JSON; a ValueError names the offending key."""
        return cls.from_dict(parse_json(text))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CalibrationProfile:
        """Validate a decoded profile (every key required except those in
        `profile_fields.OPTIONAL_KEYS`, which older profiles lack; no unknown keys)."""
        if not isinstance(data, dict):
            raise ValueError(f"profile must be a JSON object, got {type(data).__name__}")
        data = {**pf.OPTIONAL_KEYS, **data}
        if "schema_version" not in data:
            raise ValueError("profile is missing key 'schema_version'")
        pf.check_schema_version(data["schema_version"])
        names = [f.name for f in fields(cls)]
        for key in names:
            if key not in data:
                raise ValueError(f"profile is missing key {key!r}")
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"profile has unknown key {unknown[0]!r}")
        for key, kinds in pf.JSON_TYPES.items():
            value = data[key]   # bool is an int in Python: only bool-typed keys take bools
            if isinstance(value, bool) != (bool in kinds) or not isinstance(value, kinds):
                raise ValueError(f"profile key {key!r} has the wrong type "
                                 f"{type(value).__name__}")
        return cls(**data)

    def summary(self) -> dict[str, Any]:
        """Small JSON-able overview (for listings): classes, T, k per class, source, created,
        and (version 2) the served score, covariance and region methods."""
        out = {"classes": list(self.classes), "score_mode": self.score_mode,
               "temperature": self.temperature, "modulation": self.modulation,
               "depth_k": dict(self.depth_k),
               "pooled_k": self.pooled_k, "fallback_classes": list(self.fallback_classes),
               "cov_source": self.cov_source, "cov_dims": list(self.cov_dims),
               "created_at": self.provenance.get("created_at")}
        if self.schema_version > 1:
            out.update(score_method=self.score_method, cov_method=self.cov_method,
                       region_method=self.region_method, sources=list(self.served_sources))
        return out

    # -- application ---------------------------------------------------------------------
    def calibrate(self, logits: np.ndarray | None = None, scores: np.ndarray | None = None,
                  labels: np.ndarray | None = None, boxes: np.ndarray | None = None,
                  covariances: np.ndarray | None = None,
                  layer_boxes: np.ndarray | None = None, ego_xy: np.ndarray | None = None,
                  ellipse_confidence: float = ELLIPSE_CONFIDENCE,
                  layer_logits: np.ndarray | None = None,
                  levels: np.ndarray | list[float] | None = None,
                  hyp_boxes: np.ndarray | None = None,
                  hyp_scores: np.ndarray | None = None) -> CalibratedDetections:
        """Calibrate N detections; `calibrators.profile._calibrate.calibrate_detections` says how
        (`hyp_boxes [N, H, 9]` and `hyp_scores [N, H]`: the box hypotheses a `hypotheses`
        covariance source needs)."""
        return calibrate_detections(self, logits=logits, scores=scores, labels=labels,
                                    boxes=boxes, covariances=covariances,
                                    layer_boxes=layer_boxes, ego_xy=ego_xy,
                                    ellipse_confidence=ellipse_confidence,
                                    layer_logits=layer_logits, levels=levels,
                                    hyp_boxes=hyp_boxes, hyp_scores=hyp_scores)


def make_provenance(**counts: Any) -> dict[str, Any]:
    """Provenance dict: the given entries plus `created_at` (ISO-8601 UTC) and detcal version."""
    created = datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    return {**counts, "created_at": created, "detcal_version": detcal_version()}


