"""Validation of a profile's fields (JSON types, names, numbers, the v2 stages): every error
names the key. Used by `calibrators.profile` only."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibrators.core.json_safe import to_jsonable
from calibrators.core.vocab import COV_METHODS, COV_SOURCES, REGION_METHODS, SCORE_METHODS
from calibrators.regions import ConformalRegions
from calibrators.scores import score_calibrator_from_dict

#: Profile JSON versions this detcal reads: 1 (temperature + depth k, Gaussian ellipses) and
#: 2 (adds the score, covariance-scaling and region stages). A v1 profile serves as before.
SCHEMA_VERSIONS = (1, 2)
SCHEMA_VERSION = 2
MATCHING_RULES = ("center_distance",)
#: The keys a version-2 profile adds.
STAGE_KEYS = ("score_calibration", "covariance_scaling", "regions", "sources")

JSON_TYPES: dict[str, tuple[type, ...]] = {
    "schema_version": (int,), "classes": (list,), "score_mode": (str,),
    "temperature": (int, float), "modulation": (bool,), "cov_dims": (list,),
    "cov_source": (str,), "depth_k": (dict,),
    "pooled_k": (int, float), "fallback_classes": (list,), "matching": (dict,),
    "min_score": (int, float, type(None)), "report": (dict,), "provenance": (dict,),
    "score_calibration": (dict, type(None)), "covariance_scaling": (dict, type(None)),
    "regions": (dict, type(None)), "sources": (dict, type(None)),
}


#: Keys older profiles lack, with the value that reproduces their behaviour.
OPTIONAL_KEYS: dict[str, Any] = {"modulation": False, **dict.fromkeys(STAGE_KEYS)}




def check_schema_version(value: Any) -> None:
    if isinstance(value, bool) or value not in SCHEMA_VERSIONS:
        raise ValueError(f"schema_version {value!r} is not supported (this detcal reads "
                         f"{list(SCHEMA_VERSIONS)})")


def names(key: str, value: Any, distinct: bool = False) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, list | tuple | np.ndarray):
        raise ValueError(f"{key} must be a list of names, got {type(value).__name__}")
    names = tuple(value.tolist() if isinstance(value, np.ndarray) else value)
    for name in names:
        if not isinstance(name, str) or not name:
            raise ValueError(f"{key} must hold non-empty strings, got {name!r}")
    if distinct and len(set(names)) != len(names):
        raise ValueError(f"{key} has duplicate names")
    return names


def number(key: str, value: Any, positive: bool = False, nonnegative: bool = False) -> float:
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


def known(key: str, names: tuple[str, ...], classes: tuple[str, ...]) -> None:
    for name in names:
        if name not in classes:
            raise ValueError(f"{key} names {name!r}, which is not in classes")


def class_numbers(key: str, value: Any, classes: tuple[str, ...], positive: bool = False
                  ) -> dict[str, float]:
    """`{class name: number}` with known names and numbers >= 0 (> 0 with `positive`)."""
    if not isinstance(value, dict):
        raise ValueError(f"{key} must map class names to numbers, got {type(value).__name__}")
    out = {}
    for name, k in value.items():
        known(key, (name,), classes)
        out[name] = number(f"{key}[{name!r}]", k, positive=positive, nonnegative=not positive)
    return out


def matching(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ValueError(f"matching must be an object, got {type(value).__name__}")
    if value.get("rule") not in MATCHING_RULES:
        raise ValueError(f"matching.rule must be one of {list(MATCHING_RULES)}, "
                         f"got {value.get('rule')!r}")
    threshold = number("matching.threshold", value.get("threshold"), positive=True)
    return {**value, "threshold": threshold}


class CheckedJSON(dict):
    """An object `jsonable` has already copied and checked: a profile rebuilt with
    `dataclasses.replace` passes its own fields again, and they are not converted twice (a
    fit rebuilds its profile stage by stage, and the report and stages are large)."""


def jsonable(key: str, value: Any) -> dict:
    """A deep copy of the object `value` in plain JSON types (`calibrators.core.json_safe`);
    non-finite numbers and values of no JSON type are refused so the profile is strict JSON.
    A `CheckedJSON` (a profile's own field) is returned as it is."""
    if type(value) is CheckedJSON:
        return value
    if not isinstance(value, dict):
        raise ValueError(f"{key} must be an object, got {type(value).__name__}")
    try:
        return CheckedJSON(to_jsonable(value, strict=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{key} must hold JSON-able values with finite numbers: {exc}"
                         ) from None


def _method(key: str, value: Any, methods: tuple[str, ...]) -> str:
    """The `method` of stage `key`, one of `methods`, or a ValueError naming `key.method`."""
    method = value.get("method") if isinstance(value, dict) else None
    if method not in methods:
        raise ValueError(f"{key}.method must be one of {list(methods)}, got {method!r}")
    return method


def _parsed(key: str, build: Any, data: Any) -> Any:
    """`build(data)`, a stage's fitted object, or a ValueError naming `key`."""
    try:
        return build(data)
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"{key} is not valid: {exc}") from None


def score_stage(value: Any) -> tuple[str, Any]:
    """`(method, calibrator or None)` of a v2 `score_calibration` (None: temperature)."""
    if value is None:
        return "temperature", None
    method = _method("score_calibration", value, SCORE_METHODS)
    if method == "temperature":
        return method, None
    return method, _parsed("score_calibration.params", score_calibrator_from_dict,
                           value.get("params"))


def covariance_stage(value: Any, classes: tuple[str, ...]) -> tuple[str, dict, float]:
    """`(method, s per class, pooled s)` of a v2 `covariance_scaling` (None: depth)."""
    if value is None:
        return "depth", {}, 1.0
    method = _method("covariance_scaling", value, COV_METHODS)
    scale = class_numbers("covariance_scaling.scale", value.get("scale", {}), classes,
                          positive=True)
    pooled = number("covariance_scaling.pooled_scale", value.get("pooled_scale", 1.0),
                    positive=True)
    return method, scale, pooled


def region_stage(value: Any, n_classes: int) -> tuple[str, ConformalRegions | None]:
    """`(method, conformal regions or None)` of a v2 `regions` (None: gaussian)."""
    if value is None:
        return "gaussian", None
    method = _method("regions", value, REGION_METHODS)
    if method == "gaussian":
        return method, None
    regions = _parsed("regions.conformal", ConformalRegions.from_dict, value.get("conformal"))
    if regions.classes_ != list(range(n_classes)):
        raise ValueError("regions.conformal must serve the profile's class indices")
    return method, regions


@dataclass(frozen=True)
class SourceStage:
    """How `Σ'` and its regions are served for detections whose raw Σ comes from `source`
    (`given` covariances, `layers` spread, or `none`): k and s per class, the methods, the
    conformal radii (None: Gaussian)."""

    source: str
    depth_k: dict[str, float]
    pooled_k: float
    cov_method: str
    scale: dict[str, float]
    pooled_scale: float
    region_method: str
    conformal: ConformalRegions | None


def source_stage(source: str, depth_k: Any, pooled_k: Any, covariance_scaling: Any,
                 regions: Any, classes: tuple[str, ...], where: str = "") -> SourceStage:
    """A validated `SourceStage`; `where` prefixes the keys named in errors."""
    cov_method, scale, pooled_scale = covariance_stage(covariance_scaling, classes)
    region_method, conformal = region_stage(regions, len(classes))
    return SourceStage(source, class_numbers(f"{where}depth_k", depth_k, classes),
                       number(f"{where}pooled_k", pooled_k, nonnegative=True), cov_method,
                       scale, pooled_scale, region_method, conformal)


def other_sources(value: Any, primary: str, classes: tuple[str, ...]
                  ) -> dict[str, SourceStage]:
    """The stages of a v2 `sources` object: `{source: {depth_k, pooled_k, fallback_classes,
    covariance_scaling, regions}}` for covariance sources other than the profile's own."""
    if value is None:
        return {}
    out = {}
    for source, stage in value.items():
        if source not in COV_SOURCES or source == primary:
            raise ValueError(f"sources has {source!r}: keys must be covariance sources "
                             f"{list(COV_SOURCES)} other than cov_source {primary!r}")
        if not isinstance(stage, dict):
            raise ValueError(f"sources[{source!r}] must be an object")
        where = f"sources[{source!r}]."
        known(f"{where}fallback_classes",
              names(f"{where}fallback_classes", stage.get("fallback_classes", [])), classes)
        out[source] = source_stage(source, stage.get("depth_k"), stage.get("pooled_k"),
                                   stage.get("covariance_scaling"), stage.get("regions"),
                                   classes, where)
    return out
