"""The calibration profile: fitted parameters, fit report and provenance, as versioned JSON.

A profile is what `fit_profile` produces and what the service stores and applies:
`calibrate(...)` turns raw detections into calibrated scores `sigmoid/softmax(z / T)` (with
`modulation`, `z` is first modulated from the per-layer logits, `calibrators.modulation`),
covariances `Σ + k_c · d · I` (class `c`, BEV distance `d` from the ego) and confidence
ellipses of their `x, y` block. `to_json()` / `from_json()` round-trip exactly (floats are
written with `repr`, which Python reads back bit for bit).
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from typing import Any

import numpy as np
from scipy.special import expit, logit

from calibrators.checks import (
    as_float_array,
    as_int_array,
    check_covariances,
    check_index,
    check_length,
    check_probabilities,
)
from calibrators.covariance import dim_indices, layer_spread
from calibrators.depth import add_depth_term
from calibrators.ellipse import Ellipse, ellipse
from calibrators.exceptions import FieldError
from calibrators.modulation import modulate_logits
from calibrators.scores import class_probabilities, predict
from calibrators.vocab import COV_SOURCES, SCORE_MODES, detcal_version

SCHEMA_VERSION = 1
MATCHING_RULES = ("center_distance",)


@dataclass(kw_only=True)
class CalibrationProfile:
    """Fitted calibration of one detector (see the module docstring).

    classes : class names in logit column order.     score_mode : "sigmoid" or "softmax".
    temperature : T > 0.                              cov_dims : regression dims of Σ (D).
    modulation : True if logits modulation (Eq. 4-1) runs before the temperature; then
        `calibrate` needs the per-layer logits. Absent from older JSON: read as False.
    cov_source : "given" | "layers" | "none" (where Σ comes from before depth scaling).
    depth_k : class name -> k >= 0.                   pooled_k : k for classes not in depth_k.
    fallback_classes : classes whose k is pooled_k (too few matches when fit).
    matching : {"rule": "center_distance", "threshold": metres}.
    min_score : the minimum raw score a detection needed to take part in the fit, or None.
    report : JSON-able before/after metrics.          provenance : JSON-able fit provenance.
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
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        _check_schema_version(self.schema_version)
        self.classes = _names("classes", self.classes, distinct=True)
        if not self.classes:
            raise ValueError("classes must name at least one class")
        if self.score_mode not in SCORE_MODES:
            raise ValueError(f"score_mode must be one of {list(SCORE_MODES)}, "
                             f"got {self.score_mode!r}")
        self.temperature = _number("temperature", self.temperature, positive=True)
        if not isinstance(self.modulation, bool | np.bool_):
            raise ValueError(f"modulation must be true or false, got {self.modulation!r}")
        self.modulation = bool(self.modulation)
        self.cov_dims = _names("cov_dims", self.cov_dims, distinct=True)
        dim_indices(self.cov_dims)
        if self.cov_source not in COV_SOURCES:
            raise ValueError(f"cov_source must be one of {list(COV_SOURCES)}, "
                             f"got {self.cov_source!r}")
        self.depth_k = _depth_k(self.depth_k, self.classes)
        self.pooled_k = _number("pooled_k", self.pooled_k, nonnegative=True)
        self.fallback_classes = _names("fallback_classes", self.fallback_classes, distinct=True)
        _known("fallback_classes", self.fallback_classes, self.classes)
        self.matching = _matching(self.matching)
        if self.min_score is not None:
            self.min_score = _number("min_score", self.min_score)
            if not 0.0 <= self.min_score <= 1.0:
                raise ValueError(f"min_score must be in [0, 1] or null, got {self.min_score}")
        self.report = _jsonable("report", self.report)
        self.provenance = _jsonable("provenance", self.provenance)

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the profile in plain JSON types (tuples become lists),
        `schema_version` first."""
        out = {"schema_version": self.schema_version}
        out.update({f.name: copy.deepcopy(getattr(self, f.name)) for f in fields(self)})
        for key in ("classes", "cov_dims", "fallback_classes"):
            out[key] = list(out[key])
        return out

    def to_json(self, indent: int | None = 2) -> str:
        """Profile JSON; `from_json(to_json())` gives back an equal profile, float for float."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str | bytes) -> CalibrationProfile:
        """Parse and validate profile JSON; a ValueError names the offending key."""
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError, TypeError) as exc:
            raise ValueError(f"profile is not valid JSON: {exc}") from None
        return cls.from_dict(data)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CalibrationProfile:
        """Validate a decoded profile (every key required except those in `_OPTIONAL_KEYS`,
        which older profiles lack; no unknown keys) and build it."""
        if not isinstance(data, dict):
            raise ValueError(f"profile must be a JSON object, got {type(data).__name__}")
        data = {**_OPTIONAL_KEYS, **data}
        if "schema_version" not in data:
            raise ValueError("profile is missing key 'schema_version'")
        _check_schema_version(data["schema_version"])
        names = [f.name for f in fields(cls)]
        for key in names:
            if key not in data:
                raise ValueError(f"profile is missing key {key!r}")
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"profile has unknown key {unknown[0]!r}")
        for key, kinds in _JSON_TYPES.items():
            value = data[key]   # bool is an int in Python: only bool-typed keys take bools
            if isinstance(value, bool) != (bool in kinds) or not isinstance(value, kinds):
                raise ValueError(f"profile key {key!r} has the wrong type "
                                 f"{type(value).__name__}")
        return cls(**data)

    def summary(self) -> dict[str, Any]:
        """Small JSON-able overview (for listings): classes, T, k per class, source, created."""
        return {"classes": list(self.classes), "score_mode": self.score_mode,
                "temperature": self.temperature, "modulation": self.modulation,
                "depth_k": dict(self.depth_k),
                "pooled_k": self.pooled_k, "fallback_classes": list(self.fallback_classes),
                "cov_source": self.cov_source, "cov_dims": list(self.cov_dims),
                "created_at": self.provenance.get("created_at")}

    # -- application ---------------------------------------------------------------------
    def calibrate(self, logits: np.ndarray | None = None, scores: np.ndarray | None = None,
                  labels: np.ndarray | None = None, boxes: np.ndarray | None = None,
                  covariances: np.ndarray | None = None,
                  layer_boxes: np.ndarray | None = None, ego_xy: np.ndarray | None = None,
                  ellipse_confidence: float = 0.95,
                  layer_logits: np.ndarray | None = None) -> CalibratedDetections:
        """Calibrate N detections.

        Class evidence: `logits [N, C']` (C' = C sigmoid, C + 1 softmax), or `layer_logits
        [N, L, C']` from every decoder layer (the last is the final layer), or raw `scores [N]`
        with `labels [N]` (calibrated as `sigmoid(logit(p) / T)`). A profile with
        `modulation` needs `layer_logits` (L >= 2): the calibrated probabilities are those of
        the modulated logits over T, while the label stays the arg-max of the raw final layer
        (modulation re-scores a detection, it does not relabel it). `boxes [N, 9]` (required)
        give the distance from `ego_xy [N, 2]` (default origin). Σ comes from the profile's
        `cov_source`: `covariances [N, D, D]` ("given"), `layer_boxes [N, L, 9]` ("layers",
        spread across decoder layers) or zeros ("none"); `layer_boxes` are ignored otherwise.
        """
        labels_, scores_, raw, class_scores = self._class_evidence(logits, scores, labels,
                                                                   layer_logits)
        n = len(labels_)
        box = as_float_array("boxes", _required("boxes", boxes), ndim=2)
        if box.shape[1] != 9:
            raise FieldError("boxes", f"boxes must have shape [N, 9], got {box.shape}")
        check_length("boxes", box, n, "the class evidence")
        ego = np.zeros((n, 2)) if ego_xy is None else as_float_array("ego_xy", ego_xy, ndim=2)
        if ego.shape != (n, 2):
            raise FieldError("ego_xy", f"ego_xy must have shape [{n}, 2], got {ego.shape}")
        distances = np.hypot(box[:, 0] - ego[:, 0], box[:, 1] - ego[:, 1])
        base = self._base_covariance(covariances, layer_boxes, n)
        k_table = np.array([self.depth_k.get(c, self.pooled_k) for c in self.classes])
        cov = add_depth_term(base, distances, k_table[labels_])
        return CalibratedDetections(labels=labels_, scores=scores_, scores_raw=raw,
                                    class_scores=class_scores, covariances=cov,
                                    ellipses=self._ellipses(cov, ellipse_confidence),
                                    distances=distances)

    def _class_evidence(self, logits: np.ndarray | None, scores: np.ndarray | None,
                        labels: np.ndarray | None, layer_logits: np.ndarray | None
                        ) -> tuple[np.ndarray, ...]:
        """Labels, calibrated scores, raw scores `[N]` and class probabilities `[N, C]|None`."""
        given = [name for name, value in (("logits", logits), ("layer_logits", layer_logits),
                                          ("scores", scores)) if value is not None]
        if len(given) != 1:
            raise FieldError("logits", f"pass either logits or scores (with labels), or "
                                       f"layer_logits in place of logits; got {given or 'none'}")
        if self.modulation and layer_logits is None:
            raise FieldError("layer_logits", f"the profile applies logits modulation, which "
                                             f"needs layer_logits with at least 2 layers "
                                             f"[N, L, C'] (every decoder layer's logits), not "
                                             f"{given[0]}")
        n_classes = len(self.classes)
        want = n_classes + (1 if self.score_mode == "softmax" else 0)
        if layer_logits is not None:
            layers = as_float_array("layer_logits", layer_logits, ndim=3)
            if layers.shape[2] != want:
                raise FieldError("layer_logits", f"layer_logits has {layers.shape[2]} columns but "
                                                 f"the profile's {self.score_mode} mode with "
                                                 f"{n_classes} classes needs {want}")
            if self.modulation and layers.shape[1] < 2:
                raise FieldError("layer_logits", f"the profile applies logits modulation, "
                                                 f"which needs layer_logits with at least 2 "
                                                 f"layers, got {layers.shape[1]}")
            logits = layers[:, -1]
        if logits is not None:
            z = as_float_array("logits", logits, ndim=2)
            if z.shape[1] != want:
                raise FieldError("logits", f"logits has {z.shape[1]} columns but the profile's "
                                           f"{self.score_mode} mode with {n_classes} classes "
                                           f"needs {want}")
            pred, raw = predict(z, self.score_mode)
            if labels is not None:
                given_labels = as_int_array("labels", labels)
                check_length("labels", given_labels, len(pred), "logits")
                if not np.array_equal(given_labels, pred):
                    raise FieldError("labels", "labels differ from the arg-max of logits; "
                                               "pass one of them")
            if self.modulation:
                z = modulate_logits(layers)
            probs = class_probabilities(z, self.score_mode, self.temperature)
            return pred, probs[np.arange(len(pred)), pred], raw, probs
        p = as_float_array("scores", scores, ndim=1)
        check_probabilities("scores", p)
        lab = as_int_array("labels", _required("labels (with scores)", labels))
        check_length("labels", lab, len(p), "scores")
        check_index("labels", lab, n_classes, "classes")
        with np.errstate(divide="ignore"):
            calibrated = expit(logit(p) / self.temperature)
        return lab, calibrated, p, None

    def _base_covariance(self, covariances: np.ndarray | None, layer_boxes: np.ndarray | None,
                         n: int) -> np.ndarray:
        """`[N, D, D]` Σ before depth scaling, from the profile's cov_source."""
        dim = len(self.cov_dims)
        if self.cov_source != "given" and covariances is not None:
            raise FieldError("covariances", f"covariances were given but the profile's "
                                            f"cov_source is {self.cov_source!r}: its k was fit "
                                            f"without them")
        if self.cov_source == "given":
            if covariances is None:
                raise FieldError("covariances", f"covariances are required: the profile was fit "
                                                f"on given covariances (cov_source 'given') over "
                                                f"cov_dims {list(self.cov_dims)}")
            cov = as_float_array("covariances", covariances, ndim=3)
            if cov.shape[1:] != (dim, dim):
                raise FieldError("covariances", f"covariances are {cov.shape[1]}x{cov.shape[2]} "
                                                f"but the profile's cov_dims "
                                                f"{list(self.cov_dims)} need {dim}x{dim}")
            check_covariances("covariances", cov, n=n, dim=dim)
            return cov
        if self.cov_source == "layers":
            layers = _required("layer_boxes (the profile's cov_source is 'layers')", layer_boxes)
            spread = layer_spread(layers, self.cov_dims)
            check_length("layer_boxes", spread, n, "the class evidence")
            return spread
        return np.zeros((n, dim, dim))

    def _ellipses(self, cov: np.ndarray, confidence: float) -> Ellipse | None:
        """Ellipses of the x, y block of `cov [N, D, D]`, or None if cov_dims lack x or y."""
        if "x" not in self.cov_dims or "y" not in self.cov_dims:
            return None
        ix, iy = self.cov_dims.index("x"), self.cov_dims.index("y")
        block = cov[:, [ix, iy]][:, :, [ix, iy]]
        return ellipse(block, confidence)


@dataclass
class CalibratedDetections:
    """Result of `CalibrationProfile.calibrate` for N detections.

    labels [N] int64; scores [N] calibrated probability of the label; scores_raw [N] before
    calibration; class_scores [N, C] calibrated (None for scores-only input); covariances
    [N, D, D] = Σ + k·d·I; ellipses of the x, y block (arrays [N]) or None; distances [N] m.
    """

    labels: np.ndarray
    scores: np.ndarray
    scores_raw: np.ndarray
    class_scores: np.ndarray | None
    covariances: np.ndarray
    ellipses: Ellipse | None
    distances: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


def make_provenance(**counts: Any) -> dict[str, Any]:
    """Provenance dict: the given entries plus `created_at` (ISO-8601 UTC) and detcal version."""
    created = datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    return {**counts, "created_at": created, "detcal_version": detcal_version()}


# -- validation helpers -----------------------------------------------------------------------
_JSON_TYPES: dict[str, tuple[type, ...]] = {
    "schema_version": (int,), "classes": (list,), "score_mode": (str,),
    "temperature": (int, float), "modulation": (bool,), "cov_dims": (list,),
    "cov_source": (str,), "depth_k": (dict,),
    "pooled_k": (int, float), "fallback_classes": (list,), "matching": (dict,),
    "min_score": (int, float, type(None)), "report": (dict,), "provenance": (dict,),
}


_OPTIONAL_KEYS: dict[str, Any] = {"modulation": False}


def _required(name: str, value: Any) -> Any:
    """`value`, or a FieldError naming the argument (the first word of `name`) if None."""
    if value is None:
        raise FieldError(name.split()[0], f"{name} is required")
    return value


def _check_schema_version(value: Any) -> None:
    if isinstance(value, bool) or value != SCHEMA_VERSION:
        raise ValueError(f"schema_version {value!r} is not supported (this detcal reads "
                         f"{SCHEMA_VERSION})")


def _names(key: str, value: Any, distinct: bool = False) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, list | tuple | np.ndarray):
        raise ValueError(f"{key} must be a list of names, got {type(value).__name__}")
    names = tuple(value.tolist() if isinstance(value, np.ndarray) else value)
    for name in names:
        if not isinstance(name, str) or not name:
            raise ValueError(f"{key} must hold non-empty strings, got {name!r}")
    if distinct and len(set(names)) != len(names):
        raise ValueError(f"{key} has duplicate names")
    return names


def _number(key: str, value: Any, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{key} must be a number, got {type(value).__name__}")
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"{key} must be finite, got {x}")
    if positive and x <= 0:
        raise ValueError(f"{key} must be > 0, got {x}")
    if nonnegative and x < 0:
        raise ValueError(f"{key} must be >= 0, got {x}")
    return x


def _known(key: str, names: tuple[str, ...], classes: tuple[str, ...]) -> None:
    for name in names:
        if name not in classes:
            raise ValueError(f"{key} names {name!r}, which is not in classes")


def _depth_k(value: Any, classes: tuple[str, ...]) -> dict[str, float]:
    if not isinstance(value, dict):
        raise ValueError(f"depth_k must map class names to k, got {type(value).__name__}")
    out = {}
    for name, k in value.items():
        _known("depth_k", (name,), classes)
        out[name] = _number(f"depth_k[{name!r}]", k, nonnegative=True)
    return out


def _matching(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ValueError(f"matching must be an object, got {type(value).__name__}")
    if value.get("rule") not in MATCHING_RULES:
        raise ValueError(f"matching.rule must be one of {list(MATCHING_RULES)}, "
                         f"got {value.get('rule')!r}")
    threshold = _number("matching.threshold", value.get("threshold"), positive=True)
    return {**value, "threshold": threshold}


def _jsonable(key: str, value: Any) -> dict:
    """A deep copy of `value` in plain JSON types (numpy scalars/arrays converted, tuples to
    lists); non-finite numbers are refused so the profile is strict JSON."""
    if not isinstance(value, dict):
        raise ValueError(f"{key} must be an object, got {type(value).__name__}")

    def default(obj: Any) -> Any:
        if isinstance(obj, np.generic | np.ndarray):
            return obj.tolist()
        raise TypeError(f"{type(obj).__name__} is not JSON-able")

    try:
        return json.loads(json.dumps(value, allow_nan=False, default=default))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{key} must hold JSON-able values with finite numbers: {exc}"
                         ) from None
