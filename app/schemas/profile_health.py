"""Models of GET /v1/profiles/{name}/health: calibration health of a version from feedback."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.feedback import HealthStatus
from app.schemas.types import ProfileRef


class Bounded(BaseModel):
    """A figure with its 95 % confidence bounds (null without data)."""

    value: float | None
    lower: float | None
    upper: float | None


class LevelCoverage(BaseModel):
    """Fraction of true centres inside the served ellipses of one level, over every cell."""

    level: float
    n: int = Field(description="True positives counted.")
    coverage: float | None
    lower: float | None = Field(description="Clopper-Pearson 95 % bounds.")
    upper: float | None


class CellCoverage(BaseModel):
    """Coverage of every level in one class × distance bin."""

    model_config = ConfigDict(validate_by_name=True, serialize_by_alias=True)

    class_: str = Field(alias="class", examples=["car"])
    distance_range: list[float | None] = Field(description="[lo, hi] m; null: no upper end")
    n: int
    coverage: list[float]
    lower: list[float | None]
    upper: list[float | None]


class CoverageFigures(BaseModel):
    """Served-ellipse coverage per level: overall and per class × distance bin."""

    levels: list[float]
    overall: list[LevelCoverage]
    cells: list[CellCoverage]


class HealthFigures(BaseModel):
    """The figures of a set of feedback frames."""

    frames: int
    detections: int
    tp: int
    gt: int
    ece: Bounded = Field(description="ECE (10 bins) of the calibrated scores against TP.")
    classwise_ece: dict[str, float | None]
    coverage: CoverageFigures


class AlarmOut(BaseModel):
    """A drift test that crossed its threshold (kept once raised)."""

    test: str = Field(examples=["region:car 30+ m:0.9"])
    kind: str = Field(description="score | region")
    subject: str = Field(description="The class (score tests) or region group (`car 30+ m`, "
                                     "`pooled classes 15-30 m`) tested.")
    frame: int = Field(description="Feedback frame of this version at which it crossed.")
    log_statistic: float
    reason: str


class AlarmRuleOut(BaseModel):
    """The alarm rule (docs/production.md)."""

    score_tolerance: float
    coverage_tolerance: float
    calibration_sigmas: float = Field(description="Slack of a region group's coverage for its "
                                                  "finite calibration set, in standard errors.")
    false_alarm: float = Field(description="Bound on the chance of any false alarm within "
                                           "`horizon_frames` in-distribution frames.")
    horizon_frames: int
    min_frames: int
    n_tests: int
    log_threshold: float


class HealthPoint(BaseModel):
    """One point of the time series: the rolling window after a chunk of feedback."""

    seq: int
    created_at: datetime
    frames_total: int
    status: HealthStatus
    ece: float | None
    coverage: list[float | None] = Field(description="Window coverage per level.")


class HealthDocument(BaseModel):
    """A version's calibration health: `status` and the figures behind it."""

    profile: ProfileRef
    status: HealthStatus = Field(description="ok | degraded (an alarm: see `reasons`) | "
                                             "insufficient (too little feedback yet)")
    reasons: list[str]
    activated_at: datetime | None = Field(description="When the version became champion "
                                                      "(null: it is not the active version).")
    window_frames: int
    window: HealthFigures
    since_activation: HealthFigures
    alarms: list[AlarmOut]
    alarm_rule: AlarmRuleOut
    series: list[HealthPoint]
