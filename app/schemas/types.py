"""Shared pydantic types: strict finite numbers, profile names, versions and aliases (the one
parser of `name`, `name@version` and `name@alias`), JSON values that must be finite,
references to profile versions, error bodies.

Numbers are strict: a JSON string or boolean is never read as a number (`"1.5"`, `false`),
and a JSON float is never read as an integer (`1.0`)."""

from __future__ import annotations

import re
from datetime import datetime
from typing import Annotated, Any, NamedTuple

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    Field,
    Strict,
    TypeAdapter,
    ValidationError,
)

from calibrators.core.json_safe import to_jsonable

Finite = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Probability = Annotated[float, Strict(), Field(ge=0.0, le=1.0, allow_inf_nan=False)]

#: A profile name: letters, digits, `_ . -`, not starting with `.` or `-` (no `.`, `..`).
PROFILE_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$"
ProfileName = Annotated[str, Field(min_length=1, max_length=64, pattern=PROFILE_NAME_PATTERN,
                                   examples=["lidar"], description=(
                                       "A profile name: 1-64 letters, digits, `_ . -`, not "
                                       "starting with `.` or `-`."))]
#: The largest version number a store can hold (a 32-bit integer column on every backend).
MAX_VERSION = 2**31 - 1
#: A version as text (a path segment, a query value, the part after `@`): plain decimal digits,
#: no sign, space, leading zero or fraction (`1.0`, ` 1`, `+1`, `01` are refused).
VERSION_TEXT_PATTERN = r"^[1-9][0-9]{0,9}$"


def _plain_version(value: Any) -> Any:
    """Refuse a version given as text unless it is plain digits (a JSON number passes on to
    the strict integer check)."""
    if isinstance(value, str | bytes):
        text = value.decode("latin-1") if isinstance(value, bytes) else value
        if not re.fullmatch(VERSION_TEXT_PATTERN, text):
            raise ValueError("a version is a plain positive integer (1, 2, ...)")
    return value


# Field before the validator: so the JSON schema says minimum / maximum (after it, pydantic
# writes the non-standard `ge` / `le` keys, and clients see any integer as valid).
Version = Annotated[int, Field(ge=1, le=MAX_VERSION, description="Version number (1, 2, ...)."),
                    BeforeValidator(_plain_version)]

#: An alias: like a name but starting with a letter or `_` (so `name@2` is always a version).
ALIAS_PATTERN = r"^[A-Za-z_][A-Za-z0-9_.\-]*$"
AliasName = Annotated[str, Field(min_length=1, max_length=64, pattern=ALIAS_PATTERN,
                                 examples=["challenger"])]

_NAME: TypeAdapter[str] = TypeAdapter(ProfileName)
_VERSION: TypeAdapter[int] = TypeAdapter(Version)
_ALIAS: TypeAdapter[str] = TypeAdapter(AliasName)


def _reason(exc: ValidationError) -> str:
    return exc.errors(include_url=False)[0]["msg"]


def parse_version(text: str) -> int:
    """A version number from its text (a path segment, the part after `@`); ValueError says
    why not. The same rule as the `Version` path parameters."""
    try:
        return _VERSION.validate_strings(text)
    except ValidationError as exc:
        raise ValueError(f"version {text!r}: {_reason(exc)}") from None


class ParsedRef(NamedTuple):
    """A parsed profile reference: the name and at most one of a version and an alias."""

    name: str
    version: int | None
    alias: str | None


def parse_alias(text: str) -> str:
    """An alias from its text (a path segment, the part after `@`); ValueError says why not."""
    try:
        return _ALIAS.validate_python(text)
    except ValidationError as exc:
        raise ValueError(f"alias {text!r}: {_reason(exc)}") from None


def parse_profile_ref(text: str) -> ParsedRef:
    """`name`, `name@version` or `name@alias` -> `ParsedRef`; ValueError says what is wrong.
    After `@`, text starting with a digit is a version, anything else an alias."""
    name, at, rest = text.partition("@")
    try:
        name = _NAME.validate_python(name)
    except ValidationError as exc:
        raise ValueError(f"profile must be 'name', 'name@version' or 'name@alias', got "
                         f"{text!r}: name {_reason(exc)}") from None
    if not at:
        return ParsedRef(name, None, None)
    if rest[:1].isdigit() or rest[:1] in ("", "-", "+"):
        return ParsedRef(name, parse_version(rest), None)
    return ParsedRef(name, None, parse_alias(rest))


def _profile_ref(text: str) -> str:
    parse_profile_ref(text)
    return text


#: `name`, `name@version` or `name@alias` in a request body or query, checked by
#: `parse_profile_ref`. The schema's pattern (what clients and schema-driven generators see)
#: admits a subset of it.
ProfileRefText = Annotated[str, Field(
    max_length=140, examples=["lidar", "lidar@2", "lidar@champion"],
    json_schema_extra={"pattern": r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}"
                                  r"(@([1-9][0-9]{0,8}|[A-Za-z_][A-Za-z0-9_.\-]{0,63}))?$"}),
    AfterValidator(_profile_ref)]


def _finite_json(value: Any) -> Any:
    to_jsonable(value, strict=True)   # a ValueError naming the first NaN or infinity
    return value


#: Any JSON value, refused if it holds a NaN or an infinity anywhere (a number beyond the
#: float range, such as 1e400, is one); for free-form client data that is echoed back.
FiniteJson = Annotated[Any, AfterValidator(_finite_json)]


class ProfileRef(BaseModel):
    """The profile version a response was computed with."""

    id: str = Field(description="`name@version`", examples=["lidar@2"])
    name: str = Field(examples=["lidar"])
    version: int = Field(examples=[2])
    sha256: str = Field(description="sha256 of the stored profile JSON")


class ErrorItem(BaseModel):
    """One problem with a request: where (`loc`) and why (`msg`)."""

    loc: list[str | int] = Field(examples=[["body", "frames", 0, "detections", 3, "covariance"]])
    msg: str = Field(examples=["covariance is not positive semi-definite"])
    type: str = Field(examples=["value_error"])


class ErrorResponse(BaseModel):
    """The body of every 4xx: a message or a list of located problems."""

    detail: str | list[ErrorItem]


class Timestamped(BaseModel):
    """Mixin for records with a creation time."""

    created_at: datetime
