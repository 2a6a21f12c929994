"""Reading a stored profile of any kind: its JSON's `kind` (`calibrators.core.vocab.
profile_kind`) says whether it is a 3-D `CalibrationProfile` (no `kind` key) or a 2-D
`calibrators.boxes2d.Profile2D` (`"kind": "boxes2d"`, imported only when one is read)."""

from __future__ import annotations

from typing import Any

from calibrators.core.json_safe import parse_json
from calibrators.core.vocab import profile_kind
from calibrators.profile._profile import CalibrationProfile

__all__ = ["read_profile"]


def read_profile(text: str | bytes) -> Any:
    """The profile the JSON `text` holds, validated as its kind: a `CalibrationProfile` or a
    `Profile2D` (each has `kind`: `3d` or `boxes2d`); a ValueError names the bad key."""
    document = parse_json(text)
    if profile_kind(document) == "boxes2d":
        from calibrators.boxes2d import Profile2D

        return Profile2D.from_dict(document)
    return CalibrationProfile.from_dict(document)
