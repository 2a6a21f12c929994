"""The form fields of POST /v1/fit, built from the library's `FitOptions` and `FitOptions2D`
(one definition each; `app.fitting.options` joins them).

Each option becomes a form field with its type, default, allowed values and help text; the
library validates the values (a bad one is a 422 naming the field).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, create_model

from app.fitting.options import fit_option_specs


def _field(spec: Any) -> tuple[Any, Any]:
    """A form field: its type and default. A nullable option (default None) is simply left
    out of the form; a multipart form cannot carry a null, so the schema does not offer one."""
    kind: Any = Literal[spec.choices] if spec.choices else spec.type
    return kind, Field(spec.default, description=spec.help)


FitForm: type[BaseModel] = create_model(
    "FitForm", __doc__="Fit options (FitOptions in docs/science.md; a COCO pair's: "
                       "FitOptions2D in docs/boxes2d.md).",
    **{spec.name: _field(spec) for spec in fit_option_specs()})
