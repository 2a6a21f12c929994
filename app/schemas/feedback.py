"""Models of POST /v1/feedback: frames the service calibrated, with their ground truth."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from app.schemas.calibrate import FrameIn, Row
from app.schemas.types import ProfileRef, ProfileRefText
from calibrators.core.vocab import BOX_FIELDS, BOX_INDEX

_BOX_WIDTHS = (len(BOX_FIELDS), BOX_INDEX["vx"])
HealthStatus = Literal["ok", "degraded", "insufficient"]

_EXAMPLE = {
    "profile": "lidar",
    "frames": [{
        "frame_id": "scene-0001-frame-07",
        "detections": [{
            "logits": [2.1, -3.0, -4.2, -5.0, -4.1, -3.3, -4.4, -4.9, -5.1, -3.8],
            "box": [12.4, -3.1, 0.9, 1.9, 4.6, 1.7, 0.12, 3.0, 0.1],
            "covariance": [[0.04, 0.0], [0.0, 0.04]]}],
        "ground_truth": [{"label": "car", "box": [12.0, -3.4, 0.9, 1.9, 4.6, 1.7, 0.1, 3.0, 0.0]}],
    }],
}


class GroundTruthIn(BaseModel):
    """One ground-truth box of a frame."""

    model_config = ConfigDict(extra="forbid")

    label: str | Annotated[int, Field(ge=0)] = Field(description="Class name or index.")
    box: Row = Field(description="`x y z w l h yaw vx vy` (7 values: no velocity).")

    @field_validator("box")
    @classmethod
    def _box(cls, v: list[float]) -> list[float]:
        if len(v) not in _BOX_WIDTHS:
            raise ValueError(f"box must have {_BOX_WIDTHS[0]} or {_BOX_WIDTHS[1]} values, "
                             f"got {len(v)}")
        return v


class FeedbackFrame(FrameIn):
    """A frame's raw detections (as sent to /v1/calibrate, with `logits` or `layer_logits`)
    and every ground-truth box of the frame."""

    ground_truth: list[GroundTruthIn] = Field(
        description="Every labelled object of the frame (an empty list: none).")


class FeedbackRequest(BaseModel):
    """Labelled feedback for the profile version that calibrated the frames."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [_EXAMPLE]})

    profile: ProfileRefText | None = Field(
        None, description="`name`, `name@version` or `name@alias` (default: the configured "
                          "default name's active version).")
    frames: list[FeedbackFrame] = Field(min_length=1)


class FeedbackResult(BaseModel):
    """What the feedback added and the version's health status after it."""

    profile: ProfileRef
    frames: int = Field(description="Frames in this request.")
    detections: int
    tp: int = Field(description="Detections matched to a ground-truth box (nuScenes rule, 2 m).")
    gt: int
    frames_total: int = Field(description="Feedback frames of this version so far.")
    status: HealthStatus
    new_alarms: list[str] = Field(description="Drift alarms this feedback raised.")
    refit_job: str | None = Field(None, description="With DETCAL_AUTO_REFIT: the fit job this "
                                                    "feedback queued (it first degraded the "
                                                    "champion); its version lands as "
                                                    "`challenger`, not activated.")
