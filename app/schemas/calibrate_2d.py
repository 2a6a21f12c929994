"""The 2-D half of POST /v1/calibrate: the `images` of a request to a 2-D profile
(`calibrators.boxes2d.Profile2D`) and its answer, calibrated COCO results records per image.

A detection is a COCO results record without its `image_id` (its image gives it): the box
`bbox` `[x, y, w, h]` in pixels, the detector's `score`, and, as the profile needs them, its
`logits` (one per category in the profile's order, read in its `score_mode`) and
`layer_boxes` (the box of every decoder layer, for σ-scaled regions). The library checks
what the shapes here cannot (`w, h >= 0`, a category the profile knows, the logits' width):
a 422 names the detection's field."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.types import Finite, Probability, ProfileRef

Box = Annotated[list[Finite], Field(min_length=4, max_length=4)]

_EXAMPLE_DETECTION = {"id": "q17", "category_id": 1, "bbox": [120.0, 80.0, 64.0, 48.0],
                      "score": 0.82, "layer_boxes": [[118.0, 79.0, 66.0, 50.0],
                                                     [121.0, 81.0, 63.0, 47.0],
                                                     [120.0, 80.0, 64.0, 48.0]]}


class Detection2DIn(BaseModel):
    """One raw 2-D detection (a COCO results record of its image)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={
        "examples": [_EXAMPLE_DETECTION]})

    id: str | int | None = Field(None, description="Echoed back unchanged.")
    category_id: int = Field(description="A COCO category id of the profile.")
    bbox: Box = Field(description="`x, y, w, h` in pixels (top-left corner, width, height).")
    score: Probability = Field(description="The detector's confidence.")
    logits: list[Finite] | None = Field(
        None, min_length=1, description="Class logits `[C]` (`[C + 1]` softmax, last = "
                                        "no-object) in the profile's category order; required "
                                        "by a profile fit on logits, not read otherwise.")
    layer_boxes: list[Box] | None = Field(
        None, min_length=1, description="The box of every decoder layer `[L, 4]`; required "
                                        "(L >= 2) by a profile whose regions are `scaled`.")


class Image2DIn(BaseModel):
    """The detections of one image."""

    model_config = ConfigDict(extra="forbid")

    image_id: int = Field(examples=[1])
    width: Annotated[int, Field(gt=0)] | None = Field(
        None, description="Image width in pixels; with `height`, what a `position` score "
                          "calibrator needs (default: the profile's `image_size`).")
    height: Annotated[int, Field(gt=0)] | None = None
    detections: list[Detection2DIn]


class Region2DOut(BaseModel):
    """The box region of one level: the true box lies between `inner` and `outer`."""

    inner: Box | None = Field(description="Null when the level is unbounded (too few "
                                          "calibration true positives to certify it).")
    outer: Box | None
    guarantee: str = Field(description="`cell`, `pooled` or `marginal` (docs/boxes2d.md).")
    calibration_n: int


class Detection2DOut(BaseModel):
    """A calibrated 2-D detection: the COCO results record `detcal calibrate` writes, with
    `row` (its position in its image's `detections`) and `id`; one `region_<q>` key
    (`Region2DOut`) per level, `<q>` as `str(float(q))`."""

    model_config = ConfigDict(extra="allow")

    row: int
    id: str | int | None = None
    image_id: int
    category_id: int
    bbox: list[float]
    score: float = Field(description="Calibrated probability of being a true positive.")
    score_raw: float


class Image2DOut(BaseModel):
    """Calibrated detections of one image, in request order."""

    image_id: int
    detections: list[Detection2DOut]


class Category(BaseModel):
    """A COCO category of a 2-D profile."""

    id: int
    name: str


class CalibrateResponse2D(BaseModel):
    """Calibrated 2-D detections and the 2-D profile version that produced them."""

    profile: ProfileRef
    kind: str = Field(description="`boxes2d`.")
    categories: list[Category] = Field(description="The profile's categories, in the order "
                                                   "its `logits` follow.")
    levels: list[float] | None = Field(description="The levels of each `region_<q>`; null when "
                                                   "the profile serves no box regions.")
    images: list[Image2DOut]
