"""A nuScenes detection results document (the devkit's submission format), as accepted and
returned by POST /v1/calibrate/nuscenes, with the extensions of docs/formats.md
(`detection_logits`, `covariance`, `detection_score_raw`, `detection_id`; the calibrated
document's boxes add `ellipse`, `ellipses` and `detection_row`). Unknown keys are kept, and echoed
back, so they and `meta` must hold finite numbers only (a NaN anywhere is a 422 naming it)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.calibrate import Covariance
from app.schemas.types import Finite, FiniteJson, Probability

Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]

_EXAMPLE = {
    "meta": {"use_lidar": True, "use_camera": False, "use_radar": False, "use_map": False,
             "use_external": False},
    "results": {"sample-token-0": [{
        "sample_token": "sample-token-0", "translation": [12.4, -3.1, 0.9],
        "size": [1.9, 4.6, 1.7], "rotation": [0.998, 0.0, 0.0, 0.06],
        "velocity": [3.0, 0.1], "detection_name": "car", "detection_score": 0.91,
        "attribute_name": "vehicle.moving"}]},
}


class NuScenesBox(BaseModel):
    """One `DetectionBox` of a results document; an optional `covariance` `[D, D]` extra key."""

    model_config = ConfigDict(extra="allow")
    __pydantic_extra__: dict[str, FiniteJson] = Field(init=False)

    sample_token: str
    translation: Vec3
    size: Vec3
    rotation: Annotated[list[Finite], Field(min_length=4, max_length=4,
                                            description="Quaternion w, x, y, z.")]
    velocity: Annotated[list[Finite], Field(min_length=2, max_length=2)] = [0.0, 0.0]
    detection_name: str
    detection_score: Probability
    attribute_name: str = ""
    ego_translation: Vec3 | None = Field(
        None, description="Box centre minus ego position (the devkit's add_center_dist); "
                          "absent: the box is in the ego frame.")
    detection_logits: list[Finite] | None = Field(
        None, min_length=1, description="Raw logits `[C']` (used instead of the score).")
    covariance: Covariance | None = None


class NuScenesResults(BaseModel):
    """`{"meta": ..., "results": {sample_token: [DetectionBox, ...]}}`."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [_EXAMPLE]})
    __pydantic_extra__: dict[str, FiniteJson] = Field(init=False)

    meta: dict[str, FiniteJson] = Field(default_factory=dict)
    results: dict[str, list[NuScenesBox]]
