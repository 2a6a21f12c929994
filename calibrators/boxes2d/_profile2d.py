"""`Profile2D`: the fitted calibration of a 2-D (image-plane) detector, as versioned JSON.

What `fit_profile_2d` produces and the service stores next to the 3-D `CalibrationProfile`s.
Its JSON says what it is (`"kind": "boxes2d"`, `calibrators.core.vocab.profile_kind`):

    {"kind": "boxes2d", "schema_version": 1,
     "categories": [{"id": 1, "name": "car"}, ...],     # the instances' order = logit columns
     "score_mode": null | "sigmoid" | "softmax",        # how a request's logits read
     "image_size": [W, H] | null,                       # the fit images' size, if all shared it
     "matching": {"rule": "coco_iou", "iou_threshold": 0.5},
     "score_calibration": {"method", "temperature", "params"},          # `ScoreStage2D`
     "regions": {"score": "additive" | "scaled" | "adaptive", "min_sigma": 1.0,
                 "scale": {...},                    # adaptive only: `EdgeErrorScale`
                 "conformal": {...}} | null,                            # `ConformalBoxes`
     "report": {...}, "provenance": {...}}

`to_json()` / `from_json()` round-trip exactly; `from_dict` validates every key (a ValueError
names it) and parses the stages once into `score_stage`, `box_regions` and `error_scale`.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from typing import Any

from calibrators.boxes2d._box_scores import REGION_SCORES, conformity_score
from calibrators.boxes2d._conformal_boxes import ConformalBoxes
from calibrators.boxes2d._error_scale import EdgeErrorScale
from calibrators.boxes2d._score_fit import ScoreStage2D
from calibrators.core.json_safe import parse_json, to_jsonable
from calibrators.core.vocab import SCORE_MODES, profile_kind

__all__ = ["PROFILE_2D_VERSIONS", "Profile2D"]

#: The schema versions of `Profile2D` JSON this detcal reads (and the one it writes, last).
PROFILE_2D_VERSIONS: tuple[int, ...] = (1,)
_KIND = "boxes2d"
_KEYS = ("kind", "schema_version", "categories", "score_mode", "image_size", "matching",
         "score_calibration", "regions", "report", "provenance")


@dataclass(frozen=True, kw_only=True)
class Profile2D:
    """A fitted 2-D calibration (module docstring: the JSON).

    category_ids, category_names : the categories `[C]` (COCO ids and names), in the order of
        the logit columns a request's `logits` follow.
    score_mode : None (the detector's score is calibrated) or how `logits` read.
    image_size : (W, H) of every fit image when they all shared one (served when a request
        names no image size and serving reads it: `reads_image_size`), else None.
    matching : {"rule": "coco_iou", "iou_threshold": t}.
    score_calibration : `ScoreStage2D.to_dict()`.
    regions : {"score", "min_sigma", "conformal": `ConformalBoxes.to_dict()`, and for
        adaptive regions "scale": `EdgeErrorScale.to_dict()`} or None (no calibration part:
        no box regions).
    report, provenance : JSON objects.

    Parsed once (not fields, not in the JSON): `score_stage` (`ScoreStage2D`),
    `box_regions` (`ConformalBoxes` or None) and `error_scale` (`EdgeErrorScale` of adaptive
    regions, else None).
    """

    category_ids: tuple[int, ...]
    category_names: tuple[str, ...]
    score_mode: str | None
    image_size: tuple[int, int] | None
    matching: dict[str, Any]
    score_calibration: dict[str, Any]
    regions: dict[str, Any] | None = None
    report: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    schema_version: int = PROFILE_2D_VERSIONS[-1]

    def __post_init__(self) -> None:
        put = self._put
        if isinstance(self.schema_version, bool) or \
                self.schema_version not in PROFILE_2D_VERSIONS:
            raise ValueError(f"schema_version {self.schema_version!r} is not supported (this "
                             f"detcal reads 2-D profiles {list(PROFILE_2D_VERSIONS)})")
        ids = tuple(self.category_ids)
        if not ids or any(isinstance(i, bool) or not isinstance(i, int) for i in ids) \
                or len(set(ids)) != len(ids):
            raise ValueError("categories must list one or more distinct integer ids")
        names = tuple(self.category_names)
        if len(names) != len(ids) or not all(isinstance(n, str) for n in names):
            raise ValueError("categories must give each id a name (a string)")
        put("category_ids", ids)
        put("category_names", names)
        if self.score_mode is not None and self.score_mode not in SCORE_MODES:
            raise ValueError(f"score_mode must be one of {list(SCORE_MODES)} or null, got "
                             f"{self.score_mode!r}")
        put("image_size", _image_size(self.image_size))
        put("matching", _matching(self.matching))
        stage = ScoreStage2D.from_dict(self.score_calibration)
        n = getattr(stage.calibrator, "n_classes_", len(ids))
        if n != len(ids):
            raise ValueError(f"score_calibration serves {n} classes, the profile has "
                             f"{len(ids)} categories")
        put("score_stage", stage)
        put("box_regions", _regions(self.regions))
        put("error_scale", _scale(self.regions))
        for key in ("score_calibration", "regions", "report", "provenance"):
            value = getattr(self, key)
            if value is None and key == "regions":
                continue
            if not isinstance(value, dict):
                raise ValueError(f"{key} must be an object, got {type(value).__name__}")
            try:
                put(key, to_jsonable(value, strict=True))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{key} must hold JSON values with finite numbers: {exc}"
                                 ) from None

    def _put(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)

    @property
    def kind(self) -> str:
        """`boxes2d` (`calibrators.core.vocab.PROFILE_KINDS`)."""
        return _KIND

    @property
    def score_method(self) -> str:
        """The served score calibration (one of `SCORE_METHODS_2D`)."""
        return self.score_stage.method

    @property
    def region_score(self) -> str | None:
        """The served box regions' score (`REGION_SCORES`), None without regions."""
        return None if self.regions is None else self.regions["score"]

    @property
    def reads_image_size(self) -> bool:
        """Whether serving reads each detection's image size: a `position` score stage, or
        adaptive regions whose scale reads where a box meets its image's border."""
        return self.score_stage.uses_position or (
            self.error_scale is not None and self.error_scale.uses_image_size)

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The profile in plain JSON types (a deep copy), `kind` first."""
        return {"kind": _KIND, "schema_version": self.schema_version,
                "categories": [{"id": i, "name": n} for i, n in
                               zip(self.category_ids, self.category_names, strict=True)],
                "score_mode": self.score_mode,
                "image_size": None if self.image_size is None else list(self.image_size),
                **{k: copy.deepcopy(getattr(self, k)) for k in
                   ("matching", "score_calibration", "regions", "report", "provenance")}}

    def to_json(self, indent: int | None = 2) -> str:
        """Profile JSON; `from_json(to_json())` gives back an equal profile, float for float."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str | bytes) -> Profile2D:
        """Parse and validate profile JSON; a ValueError names the offending key."""
        return cls.from_dict(parse_json(text))

    @classmethod
    def from_dict(cls, data: Any) -> Profile2D:
        """Validate a decoded 2-D profile: every key of the module docstring, no other."""
        if not isinstance(data, dict):
            raise ValueError(f"profile must be a JSON object, got {type(data).__name__}")
        if profile_kind(data) != _KIND:
            raise ValueError(f"kind must be {_KIND!r} for a 2-D profile")
        missing = [k for k in _KEYS if k not in data]
        if missing:
            raise ValueError(f"profile is missing key {missing[0]!r}")
        unknown = sorted(set(data) - set(_KEYS))
        if unknown:
            raise ValueError(f"profile has unknown key {unknown[0]!r}")
        cats = data["categories"]
        if not isinstance(cats, list) or not all(
                isinstance(c, dict) and set(c) == {"id", "name"} for c in cats):
            raise ValueError("categories must be a list of {\"id\", \"name\"} objects")
        return cls(category_ids=tuple(c["id"] for c in cats),
                   category_names=tuple(c["name"] for c in cats),
                   **{k: data[k] for k in _KEYS if k not in ("kind", "categories")})

    def summary(self) -> dict[str, Any]:
        """Small JSON-able overview (for listings)."""
        return {"kind": _KIND, "categories": list(self.category_names),
                "score_mode": self.score_mode, "score_method": self.score_method,
                "region_score": self.region_score,
                "created_at": self.provenance.get("created_at")}


def _image_size(value: Any) -> tuple[int, int] | None:
    if value is None:
        return None
    size = tuple(value) if isinstance(value, list | tuple) else ()
    if len(size) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v <= 0
                             for v in size):
        raise ValueError(f"image_size must be [width, height], integers > 0, or null, got "
                         f"{value!r}")
    return (int(size[0]), int(size[1]))


def _matching(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict) or set(value) != {"rule", "iou_threshold"} \
            or value["rule"] != "coco_iou":
        raise ValueError("matching must be {\"rule\": \"coco_iou\", \"iou_threshold\": t}")
    t = value["iou_threshold"]
    if isinstance(t, bool) or not isinstance(t, int | float) or not 0.0 <= t <= 1.0:
        raise ValueError(f"matching.iou_threshold must be a number in [0, 1], got {t!r}")
    return {"rule": "coco_iou", "iou_threshold": float(t)}


def _regions(value: Any) -> ConformalBoxes | None:
    """The served `ConformalBoxes` of the `regions` field (None for null)."""
    if value is None:
        return None
    keys = {"score", "min_sigma", "conformal"}
    if isinstance(value, dict) and value.get("score") == "adaptive":
        keys.add("scale")
    if not isinstance(value, dict) or set(value) != keys:
        raise ValueError("regions must be null or an object with score, min_sigma and "
                         "conformal (and scale, for adaptive regions)")
    if value["score"] not in REGION_SCORES:
        raise ValueError(f"regions.score must be one of {list(REGION_SCORES)}, got "
                         f"{value['score']!r}")
    sigma = value["min_sigma"]
    if isinstance(sigma, bool) or not isinstance(sigma, int | float) or not 0 < sigma < 1e300:
        raise ValueError(f"regions.min_sigma must be a number > 0, got {sigma!r}")
    boxes = ConformalBoxes.from_dict(value["conformal"])
    if boxes.score != conformity_score(value["score"]):
        raise ValueError("regions.score and regions.conformal's score differ")
    return boxes


def _scale(value: Any) -> EdgeErrorScale | None:
    """The edge-error scale of adaptive `regions` (None for others)."""
    if value is None or value["score"] != "adaptive":
        return None
    return EdgeErrorScale.from_dict(value["scale"])
