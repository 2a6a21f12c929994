"""Query parameters of POST /v1/calibrate, one model for the FastAPI route (OpenAPI) and for
the Arrow fast path (`app.calibrate.arrow_route`), so both validate them by the same rules."""

from __future__ import annotations

from pydantic import BaseModel, Field

from app.schemas.calibrate import LEVELS_SCHEMA, LEVELS_TEXT
from app.schemas.types import ProfileRefText
from calibrators.core.defaults import ELLIPSE_CONFIDENCE

_FOR_ARROW = "For Arrow bodies; a JSON body's own field of the same name takes precedence."


class CalibrateQuery(BaseModel):
    """`profile`, `ellipse_confidence` and `levels` (repeated) of a calibrate request."""

    profile: ProfileRefText | None = Field(
        None, description=f"`name` or `name@version`. {_FOR_ARROW}")
    ellipse_confidence: float | None = Field(
        None, gt=0.0, lt=1.0, description=f"Default {ELLIPSE_CONFIDENCE}. {_FOR_ARROW}")
    levels: list[float] | None = Field(
        None, json_schema_extra=LEVELS_SCHEMA,
        description=f"{LEVELS_TEXT} Repeat it. {_FOR_ARROW}")

    @classmethod
    def from_pairs(cls, pairs: list[tuple[str, str]]) -> CalibrateQuery:
        """Validate decoded `(key, value)` pairs as FastAPI reads a query: the last value of a
        scalar parameter, every value of `levels`, other keys ignored; a pydantic
        ValidationError (locations without the `query` prefix) otherwise."""
        values: dict[str, object] = {}
        levels = [v for k, v in pairs if k == "levels"]
        for key, value in pairs:
            if key in ("profile", "ellipse_confidence"):
                values[key] = value
        if levels:
            values["levels"] = levels
        return cls.model_validate(values)
