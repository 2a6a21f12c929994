"""The form fields of POST /v1/fit, built from the library's `FitOptions` (one definition).

Each option of `calibrators.FitOptions` becomes a form field with its type, default, allowed
values and help text; the library validates the values (a bad one is a 422 naming the field).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, create_model

from calibrators.fit import FitOptions


def _field(spec: Any) -> tuple[Any, Any]:
    """A form field: its type and default. A nullable option (default None) is simply left
    out of the form; a multipart form cannot carry a null, so the schema does not offer one."""
    kind: Any = Literal[spec.choices] if spec.choices else spec.type
    return kind, Field(spec.default, description=spec.help)


FitForm: type[BaseModel] = create_model(
    "FitForm", __doc__="Fit options (see FitOptions in docs/science.md).",
    **{spec.name: _field(spec) for spec in FitOptions.describe()})
