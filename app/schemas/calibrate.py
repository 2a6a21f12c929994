"""Request and response models of POST /v1/calibrate and POST /v1/detect."""

from __future__ import annotations

from typing import Annotated, Literal, Self

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from app.schemas.calibrate_2d import Image2DIn
from app.schemas.types import Finite, Probability, ProfileRef, ProfileRefText
from calibrators.core.defaults import DEFAULT_LEVELS, ELLIPSE_CONFIDENCE
from calibrators.core.vocab import BOX_FIELDS, BOX_INDEX, REGION_METHODS
from calibrators.regions import GUARANTEES, MAX_LEVELS

Row = list[Finite]
#: A box row has every field, or every field up to the velocity.
_BOX_WIDTHS = (len(BOX_FIELDS), BOX_INDEX["vx"])
_BOX_TEXT = " ".join(BOX_FIELDS)

#: The levels served when a request names none.
#: Docs of the `levels` field; the rule itself is `calibrators.regions.check_levels`.
#: The schema of `levels` as the library checks it (`calibrators.regions.check_levels`):
#: published in OpenAPI, validated by the library alone.
LEVELS_SCHEMA = {"minItems": 1, "maxItems": MAX_LEVELS, "uniqueItems": True,
                 "items": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1}}
LEVELS_TEXT = (f"Coverage levels of the served `ellipses`: at most {MAX_LEVELS} distinct "
               f"numbers in (0, 1); a conformal group of n calibration points bounds a "
               f"level only up to n/(n + 1): above, the region is unbounded (null axes).")

_EXAMPLE_DETECTION = {
    "logits": [2.1, -3.0, -4.2, -5.0, -4.1, -3.3, -4.4, -4.9, -5.1, -3.8],
    "box": [12.4, -3.1, 0.9, 1.9, 4.6, 1.7, 0.12, 3.0, 0.1],
    "covariance": [[0.04, 0.0], [0.0, 0.04]],
}


def _rectangular(name: str, rows: list[list[float]] | None, width: int | None = None) -> None:
    if rows is None:
        return
    if not rows:
        raise ValueError(f"{name} must have at least one row")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise ValueError(f"{name} rows differ in length: {sorted(widths)}")
    got = widths.pop()
    if width is not None and got != width:
        raise ValueError(f"{name} rows must have {width} values, got {got}")


def _covariance(v: list[list[float]]) -> list[list[float]]:
    _rectangular("covariance", v, len(v))
    return v


#: A `[D, D]` covariance, checked square here; symmetry and positive semi-definiteness are
#: checked by the library against the profile (`calibrators.core.checks.check_covariances`).
Covariance = Annotated[list[Row], AfterValidator(_covariance), WithJsonSchema({
    "description": "A square [D, D] matrix, D in 1..9.",
    "anyOf": [{"type": "array", "minItems": d, "maxItems": d, "items": {
        "type": "array", "minItems": d, "maxItems": d, "items": {"type": "number"}}}
        for d in range(1, len(BOX_FIELDS) + 1)]})]


def _given(*fields: str, kind: str = "array") -> dict[str, object]:
    """The schema of an object whose `fields` are present and not null."""
    return {"required": list(fields),
            "properties": {f: {"type": "number" if f == "score" else kind} for f in fields}}


#: What `DetectionIn` checks, in the schema: exactly one form of class evidence, and a box.
_EVIDENCE = [_given("logits"), _given("layer_logits"), _given("scores"),
             {"required": ["score", "label"], "properties": {
                 "score": {"type": "number"}, "label": {"type": ["string", "integer"]}}}]
_BOXES = [_given("box"), _given("layer_boxes")]
#: The box hypotheses come together or not at all (the library refuses one without the other).
_HYPOTHESES = {"hypothesis_boxes": ["hypothesis_scores"],
               "hypothesis_scores": ["hypothesis_boxes"]}


class DetectionIn(BaseModel):
    """One raw detection: class evidence (exactly one form), a box, optional uncertainty."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={
        "examples": [_EXAMPLE_DETECTION], "allOf": [{"oneOf": _EVIDENCE}, {"anyOf": _BOXES}],
        "dependentRequired": _HYPOTHESES})

    id: str | int | None = Field(None, description="Echoed back unchanged.")
    logits: Row | None = Field(None, min_length=1, description="Final-layer logits `[C']`.")
    layer_logits: list[Row] | None = Field(
        None, min_length=1, description="Logits of every decoder layer `[L, C']`, last = final.")
    scores: list[Probability] | None = Field(
        None, min_length=1, description="Per-class probabilities `[C']` in the profile's layout.")
    score: Probability | None = Field(None, description="Score of `label` only (needs `label`).")
    label: str | Annotated[int, Field(ge=0)] | None = Field(
        None, description="Class name or index; required with `score`. With logits (or "
                          "`layer_logits`, `scores`): the class this detection asserts, "
                          "default their arg-max (a top-K (query, class) decoder, as DETR3D "
                          "and PETR use, gives one query a detection per class).")
    box: Row | None = Field(None, description=f"`{_BOX_TEXT}` ({_BOX_WIDTHS[1]} values: no "
                                              "velocity).")
    layer_boxes: list[Annotated[Row, Field(min_length=len(BOX_FIELDS),
                                           max_length=len(BOX_FIELDS))]] | None = Field(
        None, min_length=1, description=f"Box of every decoder layer `[L, {len(BOX_FIELDS)}]`.")
    covariance: Covariance | None = Field(
        None, description="Box covariance `[D, D]` over the profile's `cov_dims`.")
    hypothesis_boxes: list[Annotated[Row, Field(min_length=len(BOX_FIELDS),
                                                max_length=len(BOX_FIELDS))]] | None = Field(
        None, min_length=1, description=f"Final-layer box of each of the detection's H group "
                                        f"regression heads `[H, {len(BOX_FIELDS)}]` (with "
                                        f"`hypothesis_scores`); what a profile with "
                                        f"cov_source `hypotheses` needs.")
    hypothesis_scores: list[Annotated[Finite, Field(ge=0.0)]] | None = Field(
        None, min_length=1, description="Group score of each hypothesis `[H]` (the summed "
                                        "class probabilities of its group, >= 0; H as in "
                                        "`hypothesis_boxes`).")

    @field_validator("box")
    @classmethod
    def _box(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and len(v) not in _BOX_WIDTHS:
            raise ValueError(f"box must have {_BOX_WIDTHS[0]} values ({_BOX_TEXT}) or "
                             f"{_BOX_WIDTHS[1]}, got {len(v)}")
        return v

    @field_validator("layer_logits")
    @classmethod
    def _layer_logits(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        _rectangular("layer_logits", v)
        return v

    @field_validator("layer_boxes", "hypothesis_boxes")
    @classmethod
    def _box_rows(cls, v: list[list[float]] | None, info: ValidationInfo
                  ) -> list[list[float]] | None:
        _rectangular(str(info.field_name), v, len(BOX_FIELDS))
        return v

    @model_validator(mode="after")
    def _one_evidence(self) -> Self:
        given = [k for k in ("logits", "layer_logits", "scores", "score")
                 if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of logits, layer_logits, scores, score; got "
                             + (", ".join(given) if given else "none"))
        if self.score is not None and self.label is None:
            raise ValueError("score needs label (class name or index)")
        if self.box is None and self.layer_boxes is None:
            raise ValueError("give box or layer_boxes")
        return self


class FrameIn(BaseModel):
    """The detections of one frame; `ego_translation` when boxes are not in the ego frame."""

    model_config = ConfigDict(extra="forbid")

    frame_id: str = Field("frame", examples=["scene-0001-frame-07"])
    ego_translation: Annotated[Row, Field(min_length=3, max_length=3)] | None = None
    detections: list[DetectionIn]


class CalibrateRequest(BaseModel):
    """Raw detections to calibrate with a stored profile: the `frames` of 3-D detections for a
    3-D profile, or the `images` of 2-D detections for a 2-D (`boxes2d`) profile."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "profile": "lidar", "ellipse_confidence": 0.95, "levels": [0.5, 0.9, 0.95, 0.99],
        "frames": [{"frame_id": "f0", "detections": [_EXAMPLE_DETECTION]}]}]})

    profile: ProfileRefText | None = Field(
        None, description="`name` (its active version), `name@version` or `name@alias`; "
                          "default: the configured default name.")
    ellipse_confidence: float = Field(ELLIPSE_CONFIDENCE, gt=0.0, lt=1.0)
    levels: list[float] = Field(list(DEFAULT_LEVELS), description=LEVELS_TEXT,
                                json_schema_extra=LEVELS_SCHEMA)
    classes: list[str] | None = Field(
        None, description="Optional: your detector's classes in its logits' column order. When "
                          "given and not the profile's list, the request is a 422 saying what "
                          "differs (the columns would be read as other classes).")
    frames: list[FrameIn] | None = Field(
        None, min_length=1, description="3-D detections, per frame (a 3-D profile).")
    images: list[Image2DIn] | None = Field(
        None, min_length=1, description="2-D detections, per image (a 2-D profile: "
                                        "docs/api.md, \"2-D profiles\").")

    @model_validator(mode="after")
    def _one_form(self) -> Self:
        if (self.frames is None) == (self.images is None):
            raise ValueError("give exactly one of `frames` (3-D detections, for a 3-D profile) "
                             "and `images` (2-D detections, for a 2-D profile)")
        return self


_UNBOUNDED = ("Metres; null when the region is unbounded (a conformal level above n/(n + 1) of "
              "its group's n calibration points: the whole plane).")


class EllipseOut(BaseModel):
    """Uncertainty ellipse of the x, y block of the calibrated covariance."""

    semi_major: float | None = Field(description=_UNBOUNDED)
    semi_minor: float | None = Field(description=_UNBOUNDED)
    angle: float = Field(description="Major-axis angle from +x, radians, in (-pi/2, pi/2].")
    confidence: float


class LevelEllipseOut(BaseModel):
    """The served region of one level: an ellipse of the x, y block of the calibrated
    covariance with the Mahalanobis radius of its method."""

    semi_major: float | None = Field(description=_UNBOUNDED)
    semi_minor: float | None = Field(description=_UNBOUNDED)
    angle: float = Field(description="Major-axis angle from +x, radians, in (-pi/2, pi/2].")
    method: Literal[REGION_METHODS] = Field(  # type: ignore[valid-type]
        description="`conformal` (the group's split-conformal radius) or `gaussian` "
                    "(`sqrt(χ²₂(q))`).")
    group: str | None = Field(description="The conformal group (class × distance bin, e.g. "
                                          "`car 15-30 m`) that served it; null for gaussian.")
    guarantee: Literal[GUARANTEES] = Field(  # type: ignore[valid-type]
        description="What holds for this region: `cell` (the calibration true positives of its "
                    "own class × distance cell certify its level), `pooled` (those of a group "
                    "of merged distance bins or pooled small classes do), `marginal` (only all "
                    "of them together), `scaled` (its group's radius widened by how much wider "
                    "its cell's errors are: no finite-sample guarantee of its own), `none` "
                    "(gaussian).")
    calibration_n: int | None = Field(description="The calibration true positives behind the "
                                                  "guarantee; null for gaussian.")


class DetectionOut(BaseModel):
    """A calibrated detection; `row` and `id` with its frame's `frame_id` are its identity."""

    row: int = Field(description="The detection's position in its frame's request "
                                 "`detections` (or the detector's output order).")
    id: str | int | None = None
    label: str
    label_index: int
    score: float = Field(description="Calibrated score of `label`.")
    score_raw: float
    class_scores: list[float] | None = Field(
        None, description="Calibrated probability of every class, in the profile's class "
                          "order: given when logits or layer_logits were sent and the "
                          "profile's score stage is one temperature; null for score + label "
                          "and for a per-class score stage (Platt, isotonic, ...: docs/api.md).")
    box: list[float]
    covariance: list[list[float]] = Field(description="Calibrated `[D, D]` over `cov_dims`.")
    ellipse: EllipseOut | None = Field(description="None when cov_dims lack x or y.")
    ellipses: dict[str, LevelEllipseOut] | None = Field(
        description="The region at each requested level, keyed by the level as "
                    "`str(float(level))` (`\"0.95\"`); null when cov_dims lack x or y.")
    distance: float = Field(description="BEV distance from the ego, m.")


class FrameOut(BaseModel):
    """Calibrated detections of one frame, in request order."""

    frame_id: str
    detections: list[DetectionOut]


class CalibrateResponse(BaseModel):
    """Calibrated detections and the profile version that produced them."""

    profile: ProfileRef
    classes: list[str]
    cov_dims: list[str]
    ellipse_confidence: float
    frames: list[FrameOut]


class DetectRequest(BaseModel):
    """Run a bundled detector on a simulated frame (or uploaded points) and calibrate."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"sensor": "lidar", "seed": 123}]})

    sensor: str = Field("lidar", examples=["lidar"])
    seed: int | None = Field(None, ge=0, description="Simulated scene seed (default 0).")
    points: list[Row] | None = Field(
        None, min_length=1, description="Points `[P, F]` in the sensor's feature order "
                                        "instead of a simulated frame.")
    profile: ProfileRefText | None = Field(
        None, description="`name`, `name@version` or `name@alias`; default: the configured "
                          "default name.")
    min_score: float = Field(0.3, ge=0.0, le=1.0, description="Keep raw scores >= this.")
    ellipse_confidence: float = Field(ELLIPSE_CONFIDENCE, gt=0.0, lt=1.0)
    levels: list[float] = Field(list(DEFAULT_LEVELS), description=LEVELS_TEXT,
                                json_schema_extra=LEVELS_SCHEMA)

    @field_validator("points")
    @classmethod
    def _points(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        _rectangular("points", v)
        return v

    @model_validator(mode="after")
    def _one_source(self) -> Self:
        if self.points is not None and self.seed is not None:
            raise ValueError("give seed or points, not both")
        return self


class DetectResponse(CalibrateResponse):
    """Calibrated detections of a bundled detector, plus the frame's ground truth if simulated."""

    sensor: str
    seed: int | None
    ground_truth: list[dict[str, object]] | None = None
    warnings: list[str] = Field(default_factory=list, description=(
        "What may make the answer wrong though it could be served, e.g. a sensor with no "
        "profile of its name calibrated with the default profile."))
