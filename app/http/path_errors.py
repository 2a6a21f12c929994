"""Path-parameter errors that name the parameter and the form it takes: a truncated job id is
told what a job id looks like, not shown a bare regular expression."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from fastapi.routing import APIRoute


def _path_fields(dependant: Any) -> Iterator[Any]:
    yield from dependant.path_params
    for sub in dependant.dependencies:
        yield from _path_fields(sub)


def path_forms(route: Any) -> dict[str, str]:
    """Each path parameter of `route` (an `APIRoute`) -> the description it documents."""
    if not isinstance(route, APIRoute):
        return {}
    return {f.alias: f.field_info.description for f in _path_fields(route.dependant)
            if f.field_info.description}


def explain(items: list[dict[str, Any]], errors: list[dict[str, Any]], route: Any
            ) -> list[dict[str, Any]]:
    """`items` (`{loc, msg, type}` of `errors`, in order) with the message of each path-
    parameter error saying which parameter, what it takes, and how long the value was."""
    forms = path_forms(route)
    out = []
    for item, err in zip(items, errors, strict=True):
        loc = item["loc"]
        if len(loc) == 2 and loc[0] == "path":
            name, value = str(loc[1]), err.get("input")
            got = (f" (got {len(value)} character{'s' if len(value) != 1 else ''})"
                   if isinstance(value, str) else "")
            form, msg = forms.get(name), str(item["msg"]).removeprefix("Value error, ")
            form = form and form[0].lower() + form[1:].rstrip(".")
            if form and item["type"] == "string_pattern_mismatch":   # the form, not a regex
                reason = f"expected {form}"
            else:
                reason = f"{msg}; expected {form}" if form else msg
            item = {**item, "msg": f"path parameter {name}: {reason}{got}"}
        out.append(item)
    return out
